"""``facecast bench NAME ...``: benchmarks that report ratios against a baseline measured in the same run."""
from __future__ import annotations

import argparse
import importlib

BENCHES: dict[str, str] = {
    "deform": "facecast.server.bench.deform",
    "serve": "facecast.server.bench.serve",
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


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(BENCHES[args.bench]).run(args) or 0)
