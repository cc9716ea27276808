"""Client-side ``facecast`` subcommands: ``add_arguments(parser)`` and ``run(args) -> int``."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
from collections.abc import Awaitable


def add_session_arguments(p: argparse.ArgumentParser, role: str) -> None:
    """``--url``, ``--session`` and ``--token``: the session's ``role`` (producer, viewer) token,
    default ``$FACECAST_TOKEN``."""
    p.add_argument("--url", required=True, help="server URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--session", required=True, help="session id (from 'facecast session create')")
    p.add_argument(
        "--token",
        default=os.environ.get("FACECAST_TOKEN"),
        required=not os.environ.get("FACECAST_TOKEN"),
        help=f"the session's {role} token (default: $FACECAST_TOKEN, which keeps it out of the "
        "process list); it is sent in the Authorization header, never in the URL",
    )


def add_reconnect_argument(p: argparse.ArgumentParser) -> None:
    """``--reconnect-for SECONDS`` (default 60; 0: do not reconnect)."""
    p.add_argument(
        "--reconnect-for",
        type=float,
        default=60.0,
        metavar="SECONDS",
        help="when the connection drops, reconnect for up to this long before giving up "
        "(default 60; 0 = do not reconnect)",
    )


async def until_signal(work: Awaitable[object]) -> bool:
    """Run ``work`` until it ends or SIGINT/SIGTERM arrives (then it is cancelled, so that a command
    can still report what it did); True when a signal stopped it."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(work)
    stopped = []

    def stop() -> None:
        stopped.append(True)
        task.cancel()

    handled = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop)
            handled.append(sig)
        except (ValueError, RuntimeError, NotImplementedError):  # not the main thread, Windows
            pass
    try:
        await task
    except asyncio.CancelledError:
        if not stopped:
            raise
    finally:
        for sig in handled:
            loop.remove_signal_handler(sig)
    return bool(stopped)
