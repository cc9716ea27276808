"""The ``facecast`` command. Each subcommand lives in its own module, imported only when used.

A command module defines ``add_arguments(parser)`` and ``run(args) -> int``. Errors derived from
``FacecastError`` are printed as one line ("facecast: <where>: <what>") with exit status 2; client
commands print theirs the same way themselves.

This entry point is the one place that knows both sides: it names command modules as strings and
imports only the one that runs, so ``facecast.server`` never imports ``facecast.client`` (an
import-linter contract in pyproject.toml). Client-side commands live in ``facecast.client.commands``;
a command that has both a local and a remote form (``render`` and ``render --server URL``) takes its
flags from the local module and runs the client module named in ``REMOTE`` when ``--server`` is given.

Every ``--url`` and ``--server`` is a server URL, taken as typed (``127.0.0.1:8000`` works; see
``facecast.protocol.urls.server_url``). Logs go to stderr at WARNING; ``-v`` shows INFO, ``-vv`` DEBUG.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import re
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "serve": (
        "facecast.server.commands.serve",
        "start the server (built-in face, in-process jobs, local disk)",
    ),
    "render": (
        "facecast.server.commands.render",
        "batch: .fap, audio or mocap in; .glb, .npz or .fap out",
    ),
    "lipsync": ("facecast.server.commands.lipsync", "audio in; viseme track out (JSON)"),
    "faces": ("facecast.server.commands.faces", "list built-in faces, or describe a face"),
    "info": ("facecast.server.commands.info", "version, backend and OpenCL device in use"),
    "bench": ("facecast.server.commands.bench", "benchmarks: deform, serve, ..."),
    "session": ("facecast.client.commands.session", "create or close a live session on a server"),
    "stream": (
        "facecast.client.commands.stream",
        "push an input file to a live session at its real rate",
    ),
    "watch": (
        "facecast.client.commands.watch",
        "watch a live session; report fps, latency, bandwidth, drops",
    ),
}
#: Commands run by a client module instead when ``--server URL`` is given.
REMOTE: dict[str, str] = {"render": "facecast.client.commands.render"}


#: Log level by the number of ``-v`` flags.
LOG_LEVELS = (logging.WARNING, logging.INFO, logging.DEBUG)
#: Arguments that name a facecast server.
URL_ARGS = ("url", "server")


def _version() -> str:
    from . import __version__

    return f"facecast {__version__}"


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="facecast", description="Networked facial-animation server."
    )
    parser.add_argument("--version", action="version", version=_version())
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="log more: -v for INFO, -vv for DEBUG (default: warnings only); also after the command",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == wanted:  # import only the module that will run
            importlib.import_module(module).add_arguments(p)
    return parser


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The parsed command line, with every server URL normalised (exits 2 on a bad one).

    ``-v`` counts wherever it stands, also after a command's own subcommand (``session list -v``).
    """
    from ..protocol.urls import server_url

    parser = build_parser(argv)
    args, rest = parser.parse_known_args(argv)
    unknown = [a for a in rest if not re.fullmatch(r"-v+|--verbose", a)]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.verbose += sum(1 if a == "--verbose" else len(a) - 1 for a in rest)
    for name in URL_ARGS:
        value = getattr(args, name, None)
        if isinstance(value, str):
            try:
                setattr(args, name, server_url(value))
            except ValueError as e:
                parser.error(f"--{name}: {e}")
    return args


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    level = LOG_LEVELS[min(args.verbose, len(LOG_LEVELS) - 1)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from .errors import FacecastError

    module = COMMANDS[args.command][0]
    if getattr(args, "server", None) and args.command in REMOTE:
        module = REMOTE[args.command]
    try:
        return int(importlib.import_module(module).run(args) or 0)
    except FacecastError as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
