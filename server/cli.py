"""The ``facecast`` command. Each subcommand lives in its own module, imported only when used.

A command module defines ``add_arguments(parser)`` and ``run(args) -> int``. Errors derived from
``FacecastError`` are printed as one line ("facecast: <where>: <what>") with exit status 2.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("facecast.server.commands.serve", "start the server (built-in face, in-process jobs, local disk)"),
    "render": ("facecast.server.commands.render", "batch: .fap, audio or mocap in; .glb, .npz or .fap out"),
    "lipsync": ("facecast.server.commands.lipsync", "audio in; viseme track out (JSON)"),
    "faces": ("facecast.server.commands.faces", "list built-in faces, or describe a face"),
    "info": ("facecast.server.commands.info", "version, backend and OpenCL device in use"),
    "bench": ("facecast.server.commands.bench", "benchmarks: deform, serve, ..."),
    "session": ("facecast.client.commands.session", "create or close a live session on a server"),
    "stream": ("facecast.client.commands.stream", "push an input file to a live session at its real rate"),
    "watch": ("facecast.client.commands.watch", "watch a live session; report fps, latency, bandwidth, drops"),
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="facecast", description="Networked facial-animation server.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == wanted:  # import only the module that will run
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from .errors import FacecastError

    try:
        return int(importlib.import_module(COMMANDS[args.command][0]).run(args) or 0)
    except FacecastError as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
