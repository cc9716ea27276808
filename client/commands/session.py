"""``facecast session create|close|list``: manage live sessions on a server (needs the admin key).

``create`` prints ``{"id", "producer_token", "viewer_token", ...}`` as JSON on stdout.
The admin key comes from ``--admin-key`` or ``FACECAST_ADMIN_KEY``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys

from ...protocol.messages import INPUT_ALIASES, INPUT_KINDS


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("create", help="open a live session; prints its id and tokens as JSON")
    c.add_argument("--face", help="face name (default: the server's face)")
    c.add_argument(
        "--input",
        choices=INPUT_KINDS + tuple(INPUT_ALIASES),  # the server reads an alias as its kind
        default="fap",
        help="what the producer sends",
    )
    c.add_argument("--fps", type=float, default=60.0, help="output frame rate (audio/markers)")
    c.add_argument("--engine", default="fp", help="deformation engine: fp | rbf | shell")
    c.add_argument("--max-viewers", type=int, help="viewer limit for this session")
    c.add_argument(
        "--tolerance",
        type=float,
        default=0.1,
        help="compact encoding: largest error of a decoded vertex, mm (default 0.1)",
    )
    d = sub.add_parser(
        "close", help="close a live session (its producer and viewers are disconnected)"
    )
    d.add_argument("id", nargs="?", help="session id")
    d.add_argument("--session", dest="session", help="session id (alternative to the positional)")
    sub.add_parser("list", help="list live sessions with their counters")
    for q in (c, d, sub.choices["list"]):
        q.add_argument("--url", required=True, help="server URL, e.g. http://127.0.0.1:8000")
        q.add_argument("--admin-key", help="admin key (default: $FACECAST_ADMIN_KEY)")


async def _main(args: argparse.Namespace) -> int:
    from ..api import SessionAdmin

    key = args.admin_key or os.environ.get("FACECAST_ADMIN_KEY")
    async with SessionAdmin(args.url, key) as admin:
        if args.action == "create":
            s = await admin.create(
                face=args.face,
                input=args.input,
                fps=args.fps,
                engine=args.engine,
                max_viewers=args.max_viewers,
                tolerance=args.tolerance,
            )
            print(s.model_dump_json())
        elif args.action == "close":
            sid = args.id or args.session
            if not sid:
                raise SystemExit("facecast session close: give the session id")
            await admin.close(sid)
            print(json.dumps({"closed": sid}))
        else:
            print(json.dumps({"sessions": [s.model_dump() for s in await admin.list()]}, indent=2))
    return 0


def run(args: argparse.Namespace) -> int:
    import logging

    from ..api import LiveError

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise here

    try:
        return asyncio.run(_main(args))
    except LiveError as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
