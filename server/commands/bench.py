"""``facecast bench NAME ...``: benchmarks that report ratios against a baseline measured in the same run.

Only benchmarks of the server's own code ship here; those that drive a server from outside (the
live load generator ``bench/serve.py``) live in the checkout's bench/ and are named in ``MOVED``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

BENCHES: dict[str, str] = {
    "deform": "facecast.server.bench.deform",
}
#: Benchmarks that left ``facecast bench``: where they are now.
MOVED: dict[str, str] = {
    "serve": "python bench/serve.py (same options), from a checkout: the live load generator is a client "
    "of the server and lives in bench/",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="NAME")
    sub.required = True
    for name, module in BENCHES.items():
        try:
            mod = importlib.import_module(module)
        except ImportError as e:  # a benchmark whose dependencies are missing stays listed
            sub.add_parser(name, help=f"unavailable: {e}")
            continue
        mod.add_arguments(sub.add_parser(name))
    for name, where in MOVED.items():
        moved = sub.add_parser(name, help=f"moved: {where}", add_help=False, prefix_chars="+")
        moved.add_argument("rest", nargs="*")  # any options: the message says where they go now


def run(args: argparse.Namespace) -> int:
    if args.bench in MOVED:
        print(f"facecast: bench {args.bench}: moved; run {MOVED[args.bench]}", file=sys.stderr)
        return 2
    return int(importlib.import_module(BENCHES[args.bench]).run(args) or 0)
