"""``facecast stream INPUT --url URL --session ID --token T``: push a file to a live session in real time.

INPUT: ``.fap`` (FAP frames), ``.wav/.flac/.ogg`` (PCM chunks, the session must take audio) or
``.trc/.csv`` (marker frames, the session must take markers). Frames are paced at the input's own
rate (``--speed`` scales it) and carry the sender's wall clock, so viewers can measure latency.

``--role`` names the layer the stream drives (default ``primary``): a ``.fap`` file streamed as
``--role expression`` (or ``gaze``, ``head``, ``idle``) is mixed over the session's primary
producer (the speech), with a token that carries that role (``facecast session token``).

``--loop`` replays the input (media time continues), ``--seconds S`` stops after S seconds of
media time: ``facecast stream joy.fap --loop --seconds 600 ...`` is a ten-minute live source.
When the connection drops (the node goes away, a failover), the producer reconnects by itself
(backoff from 50 ms, capped at 1 s, jittered; ``--reconnect-for`` bounds the outage it waits out)
and goes on at the media time the wall clock has reached, skipping what it could not send.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Any

from ...protocol.errors import InputError
from ...protocol.messages import ROLES
from . import add_reconnect_argument, add_session_arguments, until_signal

log = logging.getLogger(__name__)

AUDIO = (".wav", ".flac", ".ogg")
MARKERS = (".trc", ".csv", ".c3d")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help=".fap, .wav/.flac/.ogg or .trc/.csv file")
    add_session_arguments(p, "producer")
    p.add_argument(
        "--role",
        choices=ROLES,
        default="primary",
        help="the layer this stream drives (default primary; the others take .fap files)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="pace multiplier (2 = twice real time; 0 = no pacing)",
    )
    p.add_argument(
        "--loop",
        type=int,
        nargs="?",
        const=0,
        default=1,
        metavar="N",
        help="send the input N times (media time continues); --loop alone: until --seconds "
        "(or Ctrl-C)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        help="stop after this many seconds of media time (with --loop: replay until then)",
    )
    add_reconnect_argument(p)
    p.add_argument(
        "--json-frames",
        action="store_true",
        help=".fap: send JSON 'fap' messages instead of binary frames",
    )
    p.add_argument(
        "--chunk", type=float, default=0.02, help="audio: seconds per PCM chunk (default 0.02)"
    )
    p.add_argument(
        "--layout",
        type=Path,
        help="markers: marker layout JSON file (default: <take>.layout.json or layout.json "
        "beside the take); its content is sent in the hello",
    )


class StreamError(InputError):
    """A take, audio file or layout the stream command cannot read or use."""


def _read_fap(path: Path):
    from ...protocol.fap_file import FapFormatError, read_fap

    try:
        return read_fap(path.read_text(), where=str(path))
    except (OSError, UnicodeDecodeError) as e:
        raise StreamError(f"{path}: cannot read: {e}") from None
    except FapFormatError as e:
        raise StreamError(str(e)) from None


def _read_audio(path: Path):
    import numpy as np
    import soundfile as sf

    try:
        data, rate = sf.read(str(path), dtype="int16", always_2d=True)
    except (RuntimeError, OSError, sf.LibsndfileError) as e:
        raise StreamError(f"{path}: cannot read audio: {e}") from None
    return np.ascontiguousarray(
        data.mean(axis=1).astype(np.int16) if data.shape[1] > 1 else data[:, 0]
    ), int(rate)


def _read_markers(path: Path):
    from ...protocol.markers_file import MarkerFileError, read_take

    try:
        return read_take(path.read_bytes(), path.suffix, where=str(path))
    except OSError as e:
        raise StreamError(f"{path}: cannot read: {e}") from None
    except MarkerFileError as e:
        raise StreamError(str(e)) from None


def _read_layout(args: argparse.Namespace) -> dict:
    """The marker layout to send: ``--layout``, else ``<take>.layout.json`` / ``layout.json`` beside it."""
    take = args.input
    candidates = (
        [args.layout]
        if args.layout
        else [take.with_name(take.stem + ".layout.json"), take.with_name("layout.json")]
    )
    for path in candidates:
        if path.is_file():
            try:
                layout = json.loads(path.read_text())
            except (OSError, UnicodeDecodeError, ValueError) as e:
                raise StreamError(f"{path}: cannot read the marker layout: {e}") from None
            if not isinstance(layout, dict):
                raise StreamError(
                    f"{path}: a marker layout is a JSON object with 'markers' and 'stable'"
                )
            return layout
    raise StreamError(
        f"{take}: a marker take needs its layout: pass --layout layout.json (or put "
        f"{take.stem}.layout.json beside the take)"
    )


#: Seconds an input item may be overdue before it is skipped (after a reconnection, a stall).
LATE = 0.25

Send = Callable[[Any, int, int, float], Awaitable[None]]


async def _replay(
    p: Any,
    times: Sequence[float],
    period: float,
    send: Send,
    args: argparse.Namespace,
    counts: dict[str, int],
) -> None:
    """Send items at media times ``times`` (s, one pass, paced at ``--speed``), ``--loop`` passes
    of ``period`` s each, until ``--seconds``: ``send(p, item, pass, media_t)``. Items overdue by
    more than ``LATE`` s are skipped when reconnecting is on. Counts ``sent`` and ``skipped``."""
    from ..api import Pacer

    pacer = Pacer(args.speed, late=LATE if args.reconnect_for > 0 else None)
    k = 0
    while args.loop == 0 or k < args.loop:
        for i, t in enumerate(times):
            tm = k * period + t
            if args.seconds is not None and tm >= args.seconds - 1e-9:  # k * period rounds
                return
            if await pacer.until(tm):
                await send(p, i, k, tm)
                counts["sent"] += 1
            else:
                counts["skipped"] += 1
        if period <= 0:
            break
        k += 1


async def _main(args: argparse.Namespace) -> dict:
    import numpy as np

    from ...protocol.messages import ProducerHello
    from ..api import Retry, fap_frames, produce

    # callers that build the namespace themselves may leave out the newer options
    args.seconds = getattr(args, "seconds", None)
    args.reconnect_for = getattr(args, "reconnect_for", 0.0)
    suffix = args.input.suffix.lower()
    t_start = time.monotonic()
    role = getattr(args, "role", "primary")
    if role != "primary" and suffix != ".fap":
        raise StreamError(
            f"{args.input}: a '{role}' stream sends FAP frames: give a .fap file (only the "
            "primary producer sends audio or markers)"
        )
    times: Sequence[float]
    send: Send
    if suffix == ".fap":
        fap = _read_fap(args.input)
        hello = ProducerHello(input="fap", role="producer" if role == "primary" else role)
        items = fap_frames(fap)
        times, period = [t for t, *_ in items], float(fap.duration)

        async def send(p: Any, i: int, k: int, t: float) -> None:
            _, faps, vis, exp = items[i]
            await p.send_faps(faps, t, viseme=vis, expression=exp, binary=not args.json_frames)

        kind, rate = "fap", float(fap.fps)
    elif suffix in AUDIO:
        samples, rate = _read_audio(args.input)
        hello = ProducerHello(input="audio", rate=rate, sample_format="i16")
        step = max(1, int(round(args.chunk * rate)))
        starts = range(0, len(samples), step)
        times, period = [s / rate for s in starts], len(samples) / rate

        async def send(p: Any, i: int, k: int, t: float) -> None:
            start = starts[i]
            await p.send_pcm(
                samples[start : start + step], rate=rate, sample_offset=k * len(samples) + start
            )

        kind = "audio"
    elif suffix in MARKERS:
        take = _read_markers(args.input)
        hello = ProducerHello(
            input="markers", markers=list(take.names), layout=_read_layout(args), units=take.units
        )
        times, period = [i / take.fps for i in range(take.n_frames)], take.n_frames / take.fps

        async def send(p: Any, i: int, k: int, t: float) -> None:
            await p.send_markers(np.asarray(take.xyz[i], np.float32), take.t0 + t)

        kind, rate = "markers", float(take.fps)
    else:
        raise StreamError(
            f"{args.input}: unsupported input {suffix or '(none)'}; use .fap, "
            f"{', '.join(AUDIO)} or {', '.join(MARKERS)}"
        )
    retry = Retry(give_up=args.reconnect_for) if args.reconnect_for > 0 else None
    counts = {"sent": 0, "skipped": 0}
    async with produce(args.url, args.session, args.token, hello, retry=retry) as p:
        interrupted = await until_signal(_replay(p, times, period, send, args, counts))
        errors, recovered = p.errors, p.recovered
        reconnects, outages, dropped = p.reconnects, p.outages, p.dropped
    return {
        "input": str(args.input),
        "kind": kind,
        "role": role,
        "frames_sent": counts["sent"] - dropped,
        "frames_skipped": counts["skipped"] + dropped,
        "interrupted": interrupted,
        "reconnects": reconnects,
        "max_outage_s": round(max(outages), 3) if outages else 0.0,
        "rate": rate,
        "seconds": round(time.monotonic() - t_start, 3),
        "errors": [e.message for e in errors],
        "recovered_errors": [e.message for e in recovered],  # closes it reconnected after
    }


def run(args: argparse.Namespace) -> int:
    import logging

    from ..api import LiveError

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise here

    try:
        report = asyncio.run(_main(args))
    except (LiveError, StreamError) as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
    print(json.dumps(report))
    return 1 if report["errors"] else 0
