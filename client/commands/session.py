"""``facecast session create|close|list|token|layers|layer``: manage live sessions on a server.

``create`` prints ``{"id", "producer_token", "viewer_token", ...}`` as JSON on stdout.
The admin key comes from ``--admin-key`` or ``FACECAST_ADMIN_KEY``.

A session's layers (the admin key, or ``--token`` the session's producer token):

- ``session token ID --roles expression,gaze``: a producer token for those roles only (for
  ``facecast stream --role expression --token T``);
- ``session layers ID``: its layers; ``session layer set ID NAME kind=idle seed=3`` (or one JSON
  object) sets one, ``session layer patch ID NAME amount=0.5`` changes some fields,
  ``session layer rm ID [NAME]`` removes one (without NAME: all the REST layers).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
from typing import Any

from ...protocol.messages import INPUT_ALIASES, INPUT_KINDS, ROLES


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
    t = sub.add_parser("token", help="make a producer token for some roles only")
    t.add_argument("id", help="session id")
    t.add_argument(
        "--roles", required=True, help=f"comma-separated roles, some of: {', '.join(ROLES)}"
    )
    ls = sub.add_parser("layers", help="list a session's layers")
    ls.add_argument("id", help="session id")
    lay = sub.add_parser("layer", help="set, change or remove a layer of a session")
    lay.add_argument("op", choices=("set", "patch", "rm"))
    lay.add_argument("id", help="session id")
    lay.add_argument("name", nargs="?", help="layer name (rm without it: every REST layer)")
    lay.add_argument(
        "fields",
        nargs="*",
        help="the layer: key=value pairs (values as JSON: amount=0.5 target='[0,0,600]') or "
        "one JSON object; kinds: idle (seed, amount, blink_rate...), expression (expression, "
        "faps, amount, envelope, regions), gaze (target: camera, [x,y,z] or {direction}), head "
        "(gesture or pose, amount, repetitions, envelope); protocol/README.md has them all",
    )
    for q in (c, d, sub.choices["list"], t, ls, lay):
        q.add_argument("--url", required=True, help="server URL, e.g. http://127.0.0.1:8000")
        q.add_argument("--admin-key", help="admin key (default: $FACECAST_ADMIN_KEY)")
    for q in (t, ls, lay):
        q.add_argument(
            "--token",
            default=os.environ.get("FACECAST_TOKEN"),
            help="instead of the admin key: the session's producer token (default: "
            "$FACECAST_TOKEN); a scoped token reaches the layers of its roles",
        )


def layer_fields(words: list[str]) -> dict[str, Any]:
    """``["kind=idle", "seed=3"]`` or ``['{"kind": "idle"}']`` -> a layer body (values read as
    JSON where they parse, else as text)."""
    if len(words) == 1 and words[0].lstrip().startswith("{"):
        try:
            body = json.loads(words[0])
        except ValueError as e:
            raise SystemExit(f"facecast session layer: the layer is not JSON: {e}") from None
        if not isinstance(body, dict):
            raise SystemExit("facecast session layer: the layer is a JSON object")
        return body
    out: dict[str, Any] = {}
    for w in words:
        key, eq, value = w.partition("=")
        if not eq or not key:
            raise SystemExit(f"facecast session layer: {w!r} is not key=value")
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    return out


async def _main(args: argparse.Namespace) -> int:
    from ..api import SessionAdmin

    key = args.admin_key or os.environ.get("FACECAST_ADMIN_KEY")
    if args.action in ("token", "layers", "layer") and not args.admin_key and args.token:
        key = args.token  # these routes take the session's producer token too
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
        elif args.action == "token":
            roles = [r.strip() for r in args.roles.split(",") if r.strip()]
            print((await admin.token(args.id, roles)).model_dump_json())
        elif args.action == "layers":
            print((await admin.layers(args.id)).model_dump_json(indent=2))
        elif args.action == "layer":
            await _layer(admin, args)
        else:
            print(json.dumps({"sessions": [s.model_dump() for s in await admin.list()]}, indent=2))
    return 0


async def _layer(admin: Any, args: argparse.Namespace) -> None:
    if args.op == "rm":
        await admin.remove_layer(args.id, args.name)
        print(json.dumps({"removed": args.name or "all"}))
        return
    if not args.name:
        raise SystemExit(f"facecast session layer {args.op}: give the layer's name")
    body = layer_fields(args.fields)
    if args.op == "set":
        info = await admin.set_layer(args.id, args.name, body)
    else:
        info = await admin.patch_layer(args.id, args.name, body)
    print(info.model_dump_json())


def run(args: argparse.Namespace) -> int:
    import logging

    from ..api import LiveError

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise here

    try:
        return asyncio.run(_main(args))
    except LiveError as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
