"""Server-side producers for a live session: the built-in demo and playback of an uploaded file.

- ``GET /v1/sessions/{id}/tokens`` (admin): the session's producer and viewer tokens, so a page
  holding the admin key can watch any session it lists.
- ``POST /v1/sessions/{id}/demo`` / ``DELETE .../demo`` (admin or ``?token=`` producer token): start
  or stop the demo performance (expressions, visemes, blinks, head sway, gaze) at the session's rate.
- ``POST /v1/sessions/{id}/play`` (admin or producer token): upload a ``.fap``, audio, marker or
  ``.bml`` file (a marker take with its layout's JSON content in a ``layout`` part, a BML with its
  recordings as ``audio`` parts named as its speeches name them; never a path); it is decoded
  with the batch drivers and played into the session at its real rate. The answer gives
  ``start_wall`` (Unix seconds of media time 0) so a page can start the sound in sync. Uploads wait
  in ``<data dir>/tmp`` (emptied at each start), are limited by kind (``ServerConfig.upload_limit``),
  and at most ``max_concurrent_decodes`` decode at once (503 with ``Retry-After`` beyond).

A server-side producer (``live.server_producer``) holds the session's producer slot: a WebSocket
producer is refused (4409) while it runs, and a DELETE of the demo (or the end of the file) frees it.
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import ClassVar

from fastapi import APIRouter, Request, status
from fastapi.responses import Response

from ...protocol.rest import ErrorBody
from ..drivers import input_kind, load_animation
from ..drivers.demo import demo_states
from ..errors import FacecastError, InputError, Unauthorized, Unavailable
from ..jobs.upload import (
    LAYOUT_PART,
    PayloadTooLarge,
    UploadParser,
    boundary_of,
    input_suffix,
    multipart_doc,
    receive,
    safe_display_name,
    upload_dir,
    upload_layout,
)
from ..live.server_producer import Busy, ServerProducer  # noqa: F401  (Busy: re-exported)
from .routes_sessions import registry
from .security import bearer, same

log = logging.getLogger(__name__)

router = APIRouter(
    prefix="/v1/sessions/{session_id}",
    tags=["sessions"],
    responses={401: {"model": ErrorBody}, 404: {"model": ErrorBody}, 409: {"model": ErrorBody}},
)

#: Seconds between the answer to ``play`` and media time 0, so the caller can get ready.
LEAD_IN = 0.5


def _authorise(request: Request, session, token: str | None) -> None:
    if same(bearer(request), request.app.state.admin_key) or same(
        token, session.spec.producer_token
    ):
        return
    raise _Unauthorised


class _Unauthorised(Unauthorized):
    status = 401

    def __init__(self) -> None:
        super().__init__(
            "send the admin key ('Authorization: Bearer <key>') or the session's producer token "
            "(?token=...)",
            where="token",
        )


@router.get("/tokens")
async def tokens(session_id: str, request: Request) -> dict:
    """The session's tokens (admin only)."""
    session = registry(request.app).get(session_id)
    if not same(bearer(request), request.app.state.admin_key):
        raise _Unauthorised
    return {
        "id": session_id,
        "producer_token": session.spec.producer_token,
        "viewer_token": session.spec.viewer_token,
    }


@router.post("/demo", status_code=status.HTTP_202_ACCEPTED)
async def start_demo(session_id: str, request: Request, token: str | None = None) -> dict:
    """Play the demo performance into the session until stopped."""
    session = registry(request.app).get(session_id)
    _authorise(request, session, token)
    if session.spec.input != "fap":
        raise InputError(
            f"the demo drives FAP sessions; this one takes {session.spec.input}", where="input"
        )
    producer = ServerProducer.claim(session, "demo")
    fps = session.spec.fps
    producer.play(demo_states(fps), fps, time.time(), name=f"demo-{session_id}")
    log.info("session %s: demo started at %g fps", session_id, fps)
    return {"id": session_id, "producer": "demo", "fps": fps}


@router.delete("/demo", status_code=status.HTTP_204_NO_CONTENT)
async def stop_demo(session_id: str, request: Request, token: str | None = None) -> Response:
    session = registry(request.app).get(session_id)
    _authorise(request, session, token)
    ServerProducer.stop_in(session)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


_PLAY_DOC = multipart_doc(
    file={
        "type": "string",
        "format": "binary",
        "description": "input: .fap, .wav/.flac/.ogg, .c3d/.trc/.csv or .bml",
    },
    layout=LAYOUT_PART,
    audio={
        "type": "array",
        "items": {"type": "string", "format": "binary"},
        "description": "a .bml input's recordings, each named as its speech's audio names it",
    },
)


class TooBusy(Unavailable):
    """Every decode slot is taken: the client should retry after ``Retry-After`` seconds."""

    status = 503
    headers: ClassVar[Mapping[str, str]] = MappingProxyType({"Retry-After": "2"})


def _decode_slots(app) -> threading.Semaphore:
    """The app's decode slots. A slot is given back by the decoding thread when it ends, so a client
    that hangs up mid-decode cannot start more decodes than the limit."""
    slots = getattr(app.state, "decode_slots", None)
    if slots is None:
        slots = app.state.decode_slots = threading.BoundedSemaphore(
            max(1, int(app.state.config.max_concurrent_decodes))
        )
    return slots


def _decode(path: Path, face, name: str, kind: str, options: dict):
    """``load_animation`` of a client's file; any failure of the decoder is the input's fault (4xx)."""
    try:
        return load_animation(path, face, **options)
    except FacecastError as e:  # name the client's file, not the server's copy of it
        e.args = tuple(a.replace(str(path), name) if isinstance(a, str) else a for a in e.args)
        e.where = e.where.replace(str(path), name)
        raise
    except MemoryError:
        raise PayloadTooLarge(
            f"{name!r} needs more memory to decode than this server allows; send a shorter file",
            where="file",
        ) from None
    except Exception as e:  # a decoder's own error (FapFormatError...) or one it let through
        own = type(e).__module__.startswith("facecast.")
        if not own:
            log.warning("decoding %s input %r failed", kind, name, exc_info=True)
        detail = (str(e) if own else f"{type(e).__name__}: {e}").replace(str(path), name)
        raise InputError(
            f"could not read {name!r} as {kind} input: {detail[:500]}", where="file"
        ) from None


@router.post(
    "/play",
    status_code=status.HTTP_202_ACCEPTED,
    openapi_extra=_PLAY_DOC,
    responses={
        413: {"model": ErrorBody},
        415: {"model": ErrorBody},
        503: {
            "model": ErrorBody,
            "description": "every decode slot is busy; retry after Retry-After seconds",
        },
    },
)
async def play(session_id: str, request: Request, token: str | None = None) -> dict:
    """Upload a file (multipart part ``file``) and play it into the session at its real rate.

    A marker take needs its layout: a ``layout`` part holding the layout file's JSON content (a file
    part or an inline field). The server never opens a file a client names.
    """
    app = request.app
    reg = registry(app)
    session = reg.get(session_id)
    _authorise(request, session, token)
    cfg = app.state.config
    tmp_root = upload_dir(cfg.data_dir)
    with tempfile.TemporaryDirectory(prefix="facecast-play-", dir=tmp_root) as tmp:
        upload = Path(tmp) / "upload"
        parser = UploadParser(
            boundary_of(request.headers.get("content-type", "")),
            upload,
            int(cfg.max_upload_bytes),
            kind_limit=cfg.upload_limit,
            attachment_field="audio",
        )
        await receive(request, parser)
        if parser.size == 0:
            raise InputError("the uploaded file is empty", where="file")
        path = Path(tmp) / f"input{input_suffix(parser.filename, parser.head)}"
        upload.replace(path)
        kind = input_kind(path)
        name = safe_display_name(parser.filename, path.name)
        unknown = sorted(set(parser.fields) - {"layout"})
        if unknown:
            raise InputError(
                f"unknown form field(s) {', '.join(unknown)}; known: file, layout", where="form"
            )
        layout = upload_layout(kind, parser.fields.get("layout"))
        options: dict = {} if layout is None else {"layout": layout}
        if parser.attachments and kind != "bml":
            raise InputError("'audio' parts go with a .bml performance only", where="audio")
        if kind == "bml":  # its recordings: the 'audio' parts named as its speeches name them
            from ..bml.upload import match_media

            options["media"] = match_media(path, parser.attachments, display=name)[1]
            options["fps"] = session.spec.fps
        slots = _decode_slots(app)
        if not slots.acquire(blocking=False):
            raise TooBusy(
                f"the server is decoding {cfg.max_concurrent_decodes} upload(s) already; retry in a "
                "few seconds",
                where="file",
            )

        def decode():
            try:
                return _decode(path, session.face, name, kind, options)
            finally:
                slots.release()

        loop = asyncio.get_running_loop()
        try:
            future = loop.run_in_executor(reg.executor, decode)
        except BaseException:
            slots.release()
            raise
        animation = await future
    if not animation.states:
        raise InputError("the file holds no frames", where="file")
    animator = None
    if animation.control_vertices is not None:
        animator = await loop.run_in_executor(
            reg.executor, reg.animator_for, session, animation.control_vertices
        )
    producer = ServerProducer.claim(session, f"play:{kind}")
    if animator is not None:
        producer.deform_with(reg.batcher_for(animator), animation.control_vertices)
    start = time.time() + LEAD_IN
    t0 = animation.states[0].t
    for s in animation.states:
        s.t -= t0
    producer.play(animation.states, animation.fps, start, name=f"play-{session_id}")
    log.info(
        "session %s: playing %s (%d frames at %g fps)",
        session_id,
        name,
        len(animation),
        animation.fps,
    )
    return {
        "id": session_id,
        "kind": kind,
        "frames": len(animation),
        "fps": animation.fps,
        "seconds": len(animation) / animation.fps,
        "start_wall": start,
    }
