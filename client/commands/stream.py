"""``facecast stream INPUT --url URL --session ID --token T``: push a file to a live session in real time.

INPUT: ``.fap`` (FAP frames), ``.wav/.flac/.ogg`` (PCM chunks, the session must take audio) or
``.trc/.csv`` (marker frames, the session must take markers). Frames are paced at the input's own
rate (``--speed`` scales it) and carry the sender's wall clock, so viewers can measure latency.

``--role`` names the layer the stream drives (default ``primary``): a ``.fap`` file streamed as
``--role expression`` (or ``gaze``, ``head``, ``idle``) is mixed over the session's primary
producer (the speech), with a token that carries that role (``facecast session token``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import time
from pathlib import Path

from ...protocol.errors import InputError
from ...protocol.messages import ROLES
from . import add_token_argument

log = logging.getLogger(__name__)

AUDIO = (".wav", ".flac", ".ogg")
MARKERS = (".trc", ".csv", ".c3d")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help=".fap, .wav/.flac/.ogg or .trc/.csv file")
    p.add_argument("--url", required=True, help="server URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--session", required=True, help="session id (from 'facecast session create')")
    add_token_argument(p, "producer")
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
        "--loop", type=int, default=1, help="send the input this many times (media time continues)"
    )
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


async def _main(args: argparse.Namespace) -> dict:
    from ...protocol.messages import ProducerHello
    from ..api import produce, stream_fap, stream_markers, stream_pcm

    suffix = args.input.suffix.lower()
    t_start = time.monotonic()
    role = getattr(args, "role", "primary")
    if role != "primary" and suffix != ".fap":
        raise StreamError(
            f"{args.input}: a '{role}' stream sends FAP frames: give a .fap file (only the "
            "primary producer sends audio or markers)"
        )
    if suffix == ".fap":
        fap = _read_fap(args.input)
        hello = ProducerHello(input="fap", role="producer" if role == "primary" else role)
        async with produce(args.url, args.session, args.token, hello) as p:
            n = 0
            for i in range(args.loop):
                n += await stream_fap(
                    p, fap, speed=args.speed, binary=not args.json_frames, t_offset=i * fap.duration
                )
            errors = p.errors
        kind, rate = "fap", float(fap.fps)
    elif suffix in AUDIO:
        samples, rate = _read_audio(args.input)
        hello = ProducerHello(input="audio", rate=rate, sample_format="i16")
        async with produce(args.url, args.session, args.token, hello) as p:
            n = 0
            for i in range(args.loop):
                n += await stream_pcm(
                    p,
                    samples,
                    rate,
                    chunk=args.chunk,
                    speed=args.speed,
                    sample_offset=i * len(samples),
                )
            errors = p.errors
        kind = "audio"
    elif suffix in MARKERS:
        take = _read_markers(args.input)
        hello = ProducerHello(
            input="markers", markers=list(take.names), layout=_read_layout(args), units=take.units
        )
        async with produce(args.url, args.session, args.token, hello) as p:
            n = 0
            for i in range(args.loop):
                n += await stream_markers(
                    p,
                    take.xyz,
                    take.fps,
                    t0=take.t0 + i * take.n_frames / take.fps,
                    speed=args.speed,
                )
            errors = p.errors
        kind, rate = "markers", float(take.fps)
    else:
        raise StreamError(
            f"{args.input}: unsupported input {suffix or '(none)'}; use .fap, "
            f"{', '.join(AUDIO)} or {', '.join(MARKERS)}"
        )
    return {
        "input": str(args.input),
        "kind": kind,
        "role": role,
        "frames_sent": n,
        "rate": rate,
        "seconds": round(time.monotonic() - t_start, 3),
        "errors": [e.message for e in errors],
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
