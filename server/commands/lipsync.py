"""``facecast lipsync AUDIO``: the viseme track of a speech file.

Formats (``--format``; ``--json`` = ``--format json``):

- ``table`` (default): a readable table of viseme segments (start, end, MPEG-4 viseme id, name);
- ``cues``: the same segments as JSON ``{"duration": s, "cues": [{"start", "end", "viseme",
  "name"}, ...]}``;
- ``json``: ``{"fps": F, "frames": [{"t": s, "viseme": 0-14, "weight": 0-1}, ...]}``, the
  classified viseme of the analysis frame nearest t and its intensity (the animation made from
  it by ``facecast render`` is coarticulated);
- ``rhubarb`` / ``rhubarb-tsv``: Rhubarb Lip Sync's JSON / TSV mouth cues (shapes A-H, X), for
  tools that read Rhubarb's output.

``--text "..."`` aligns the transcript's phones to the audio (refused, exit 2, when the text does
not match); ``--calibrate FILE`` calibrates the energy levels from a recording of room noise and a
loud sustained /a/ (the source's procedure) instead of from the file itself. ``-o PATH`` writes
the output to a file (atomically) instead of standard output.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..audio.cues import named_segments, rhubarb_cues, rhubarb_json, rhubarb_tsv
from ..audio.pipeline import calibration_file, lipsync_file
from ..mpeg4.highlevel import VISEME_NAMES
from ..output.atomic import write_bytes_atomic

FORMATS = ("table", "cues", "json", "rhubarb", "rhubarb-tsv")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("audio", help="speech file (.wav, .flac, .ogg; any rate, any channels)")
    parser.add_argument(
        "--format",
        choices=FORMATS,
        default=None,
        help="table: viseme segments (default); cues: the segments as JSON; "
        "json: one frame per 1/fps s; rhubarb / rhubarb-tsv: Rhubarb Lip "
        "Sync's JSON / TSV mouth cues (shapes A-H, X)",
    )
    parser.add_argument("--json", action="store_true", help="same as --format json")
    parser.add_argument("-o", "--output", default=None, help="write to this file, not stdout")
    parser.add_argument(
        "--text", default=None, help="the transcript (English): align its phones to the audio"
    )
    parser.add_argument(
        "--calibrate",
        default=None,
        metavar="FILE",
        help="calibration recording: room noise, then a loud sustained /a/",
    )
    parser.add_argument("--fps", type=float, default=100.0, help="output frame rate (default 100)")
    parser.add_argument(
        "--lookahead",
        type=float,
        default=None,
        help="coarticulation look-ahead in seconds (default: free, as in batch)",
    )
    parser.add_argument(
        "--silence-db",
        type=float,
        default=None,
        help="explicit silence threshold, dB full scale (default: from the file)",
    )
    parser.add_argument(
        "--max-db",
        type=float,
        default=None,
        help="explicit loudest speech level, dB full scale (default: from the file)",
    )


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError

    if args.fps <= 0 or args.fps > 1000:
        raise InputError(f"--fps must be in (0, 1000], got {args.fps}", where="--fps")
    if args.lookahead is not None and args.lookahead < 0:
        raise InputError(f"--lookahead must be >= 0 s, got {args.lookahead}", where="--lookahead")
    fmt = args.format or ("json" if args.json else "table")
    if args.json and args.format not in (None, "json"):
        raise InputError(f"--json contradicts --format {args.format}", where="--json")
    cal = calibration_file(args.calibrate) if args.calibrate is not None else None
    ls = lipsync_file(
        args.audio,
        fps=args.fps,
        lookahead=args.lookahead,
        calibration=cal,
        silence_db=args.silence_db,
        max_db=args.max_db,
        text=args.text,
    )
    text = _render(fmt, args, ls)
    if args.output:
        try:
            write_bytes_atomic(args.output, text.encode("utf-8"))
        except OSError as e:
            raise InputError(
                f"cannot write the output: {e.strerror or e}", where=args.output
            ) from None
        return 0
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:  # e.g. piped into head
        pass
    return 0


def _render(fmt: str, args: argparse.Namespace, ls) -> str:
    tr = ls.track
    vis, weight = ls.labels_at(tr.t)
    if fmt == "json":
        frames = [
            {"t": round(float(t), 6), "viseme": int(v), "weight": round(float(w), 4)}
            for t, v, w in zip(tr.t, vis, weight)
        ]
        return json.dumps({"fps": args.fps, "frames": frames}) + "\n"
    if fmt == "cues":
        return (
            json.dumps({"duration": round(ls.duration, 6), "cues": named_segments(vis, args.fps)})
            + "\n"
        )
    if fmt in ("rhubarb", "rhubarb-tsv"):
        cues = rhubarb_cues(vis, args.fps, ls.duration)
        if fmt == "rhubarb-tsv":
            return rhubarb_tsv(cues)
        return rhubarb_json(cues, str(args.audio), ls.duration)
    lines = [
        (
            f"{args.audio}: {ls.duration:.2f} s, {len(tr.t)} frames at {args.fps:g} fps; silence "
            f"{ls.calibration.silence_db:.1f} dB, max {ls.calibration.max_db:.1f} dB"
        ),
        f"{'start':>8} {'end':>8}  viseme",
    ]
    for s in named_segments(vis, args.fps):
        lines.append(
            f"{s['start']:8.3f} {s['end']:8.3f}  {s['viseme']:2d} {VISEME_NAMES[s['viseme']]}"
        )
    return "\n".join(lines) + "\n"
