"""``facecast lipsync AUDIO [--json]``: the viseme track of a speech file.

``--json`` prints ``{"fps": F, "frames": [{"t": s, "viseme": 0-14, "weight": 0-1}, ...]}`` with
MPEG-4 viseme ids (0 = silence): the classified viseme of the analysis frame nearest t and its
intensity (the animation made from it by ``facecast render`` is coarticulated). Without
``--json``, a readable table of viseme segments.
"""
from __future__ import annotations

import argparse
import json
import sys

from ..audio.pipeline import lipsync_file
from ..audio.visemes import VISEME_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("audio", help="speech file (.wav, .flac, .ogg; any rate, any channels)")
    parser.add_argument("--json", action="store_true", help="print the frame track as JSON")
    parser.add_argument("--fps", type=float, default=100.0, help="output frame rate (default 100)")
    parser.add_argument("--lookahead", type=float, default=None,
                        help="coarticulation look-ahead in seconds (default: free, as in batch)")
    parser.add_argument("--silence-db", type=float, default=None,
                        help="explicit silence threshold, dB full scale (default: from the file)")
    parser.add_argument("--max-db", type=float, default=None,
                        help="explicit loudest speech level, dB full scale (default: from the file)")


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError

    if args.fps <= 0 or args.fps > 1000:
        raise InputError(f"--fps must be in (0, 1000], got {args.fps}", where="--fps")
    if args.lookahead is not None and args.lookahead < 0:
        raise InputError(f"--lookahead must be >= 0 s, got {args.lookahead}", where="--lookahead")
    ls = lipsync_file(args.audio, fps=args.fps, lookahead=args.lookahead,
                      silence_db=args.silence_db, max_db=args.max_db)
    tr = ls.track
    if args.json:
        vis, weight = ls.labels_at(tr.t)
        frames = [{"t": round(float(t), 6), "viseme": int(v), "weight": round(float(w), 4)}
                  for t, v, w in zip(tr.t, vis, weight)]
        json.dump({"fps": args.fps, "frames": frames}, sys.stdout)
        sys.stdout.write("\n")
        return 0
    try:
        _table(args, ls)
    except BrokenPipeError:  # e.g. piped into head
        pass
    return 0


def _table(args: argparse.Namespace, ls) -> None:
    tr = ls.track
    vis, _ = ls.labels_at(tr.t)
    start = 0
    print(f"{args.audio}: {ls.duration:.2f} s, {len(tr.t)} frames at {args.fps:g} fps; silence "
          f"{ls.calibration.silence_db:.1f} dB, max {ls.calibration.max_db:.1f} dB")
    print(f"{'start':>8} {'end':>8}  viseme")
    for i in range(1, len(tr.t) + 1):
        if i == len(tr.t) or vis[i] != vis[start]:
            v = int(vis[start])
            print(f"{tr.t[start]:8.3f} {tr.t[i - 1] + 1 / args.fps:8.3f}  {v:2d} {VISEME_NAMES[v]}")
            start = i
