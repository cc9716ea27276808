"""Client-side ``facecast`` subcommands: ``add_arguments(parser)`` and ``run(args) -> int``."""

from __future__ import annotations

import argparse
import os


def add_token_argument(p: argparse.ArgumentParser, role: str) -> None:
    """``--token``: the session's ``role`` (producer, viewer) token, default ``$FACECAST_TOKEN``."""
    p.add_argument(
        "--token",
        default=os.environ.get("FACECAST_TOKEN"),
        required=not os.environ.get("FACECAST_TOKEN"),
        help=f"the session's {role} token (default: $FACECAST_TOKEN, which keeps it out of the "
        "process list); it is sent in the Authorization header, never in the URL",
    )
