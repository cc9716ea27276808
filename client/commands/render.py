"""``facecast render INPUT -o OUT --server URL``: the same render, done as a job on a facecast server.

The ``render`` command's flags are the local renderer's (``facecast.server.commands.render``); the
``facecast`` entry point runs this module instead when ``--server`` is given, so the server package
never imports the client. Errors are one line (``facecast: <where>: <what>``) and exit status 2,
like a local render's. The admin key comes from ``$FACECAST_ADMIN_KEY``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable
from typing import get_args

from ...protocol.errors import InputError
from ...protocol.rest import OutputFormat

#: Output suffixes a job can produce: ``.glb``, ``.npz``, ``.fap``.
OUTPUT_SUFFIXES = tuple(f".{name}" for name in get_args(OutputFormat))
#: ``render`` flags (argparse names) that tune the local mocap cleaning; a server uses its own.
LOCAL_ONLY_FLAGS = (
    "filter",
    "lowrank",
    "stable",
    "neutral_frame",
    "prior",
    "layer",
    "idle",
    "seed",
    "gaze",
)


class _Refused(InputError):
    """A render refused before or by the server: ``where`` is the file or flag at fault."""


def _progress_bar(name: str) -> tuple[Callable[[int, int], None] | None, Callable[[], None]]:
    """A ``(callback, close)`` pair drawing the job's progress in percent on a terminal, else nothing."""
    if not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(
        desc=name,
        total=100,
        file=sys.stderr,
        leave=False,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}",
    )

    def update(done: int, total: int) -> None:
        bar.n = round(100 * done / total) if total else 0
        bar.refresh()

    return update, bar.close


def render(args: argparse.Namespace) -> None:
    """Check the arguments as a local render would, then run the job; raises ``_Refused``."""
    from ..jobs import RemoteJobError, render_remote

    suffix = args.output.suffix.lower()
    if suffix not in OUTPUT_SUFFIXES:
        raise _Refused(
            f"unsupported output type {suffix or '(none)'!r}; expected one of "
            f"{', '.join(OUTPUT_SUFFIXES)}",
            where=str(args.output),
        )
    if not args.input.is_file():
        raise _Refused("input file not found", where=str(args.input))
    if any(getattr(args, name, None) is not None for name in LOCAL_ONLY_FLAGS):
        raise _Refused(
            "--filter, --lowrank, --stable, --neutral-frame, --prior, --layer, --idle, --seed and "
            "--gaze apply to local renders only",
            where="--server",
        )
    options = {"face": args.face, "engine": args.engine}
    if args.layout:
        options["layout"] = args.layout
    progress, close = _progress_bar(args.input.name)
    try:
        render_remote(
            args.server,
            args.input,
            args.output,
            options=options,
            progress=progress,
            admin_key=os.environ.get("FACECAST_ADMIN_KEY"),
        )
    except RemoteJobError as e:
        raise _Refused(str(e), where=args.server) from None
    finally:
        close()


def run(args: argparse.Namespace) -> int:
    if not getattr(args, "verbose", 0):
        logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per poll otherwise
    try:
        render(args)
    except _Refused as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
    return 0
