"""CPU per frame of the load generator's WebSocket reader (``bench/serve_load.py`` ``Viewer``):
``python bench/serve_reader.py [--against OTHER/bench]``.

The reader is fed a server's byte stream (the upgrade answer, a text hello, then binary frames with
a facecast header) in socket-sized reads, with no network, so its own cost is all that is timed
(``time.process_time``, best of ``--repeats``). ``--against`` times another checkout's reader in the
same run (and its ``bench/serve.py`` ``_LightViewer`` when it still has one): a before/after ratio
robust to a shared machine's load. Prints a table; writes ``bench/out/serve_reader.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import json
import os
import struct
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

HERE = Path(__file__).resolve().parent
#: (payload bytes, read size): FAPS-sized, a 2k-vertex and a 25k-vertex int16 frame.
CASES = ((312, 65536), (12_000, 65536), (150_000, 65536), (150_000, 262144))


def _module(folder: Path, name: str, alias: str) -> ModuleType | None:
    """``folder/name.py`` imported as ``alias`` (None if absent); ``folder`` goes first on the path
    while it loads, so its own imports of its siblings find them."""
    path = folder / f"{name}.py"
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location(alias, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[alias] = mod  # dataclasses look their module up there
    sys.path.insert(0, str(folder))
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(folder))
    return mod


def server_stream(size: int, frames: int) -> bytes:
    """What a viewer's socket receives: the 101 answer, a text hello, ``frames`` binary frames."""

    def frame(payload: bytes, opcode: int) -> bytes:
        n = len(payload)
        if n < 126:
            return struct.pack("!BB", 0x80 | opcode, n) + payload
        if n < 1 << 16:
            return struct.pack("!BBH", 0x80 | opcode, 126, n) + payload
        return struct.pack("!BBQ", 0x80 | opcode, 127, n) + payload

    body = bytearray(size)
    struct.pack_into("<I", body, 8, 7)  # seq
    struct.pack_into("<d", body, 24, 1.5)  # wall
    hello = frame(b'{"type": "hello"}', 1)
    return b"HTTP/1.1 101 Switching Protocols\r\n\r\n" + hello + frame(bytes(body), 2) * frames


class _Transport:
    def write(self, data: bytes) -> None:
        pass

    def close(self) -> None:
        pass

    def get_extra_info(self, name: str) -> Any:
        return None


def cost_us(make: Any, chunks: list[bytes], frames: int, size: int, repeats: int) -> float:
    """Best CPU µs per frame of a reader made by ``make(out)`` over ``chunks``."""
    best = float("inf")
    for _ in range(repeats):
        out: list = []
        proto = make(out)
        proto.connection_made(_Transport())
        t = time.process_time()
        for c in chunks:
            proto.data_received(c)
        dt = time.process_time() - t
        if len(out) != frames or out[-1][1:] != (7, 1.5, size):
            raise RuntimeError(f"{make}: read {len(out)} of {frames} frames, or wrong fields")
        best = min(best, dt)
    return 1e6 * best / frames


async def measure(readers: dict[str, Any], repeats: int) -> list[dict]:
    rows = []
    for size, read in CASES:
        frames = max(200, 3_000_000 // size)
        data = server_stream(size, frames)
        chunks = [data[i : i + read] for i in range(0, len(data), read)]
        row: dict[str, Any] = {"frame_bytes": size, "read_bytes": read}
        for name, make in readers.items():
            row[name] = round(cost_us(make, chunks, frames, size, repeats), 2)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--against", type=Path, help="another checkout's bench/ folder, timed alongside")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=HERE / "out" / "serve_reader.json")
    args = p.parse_args(argv)
    this = _module(HERE, "serve_load", "serve_load_here")
    assert this is not None
    readers: dict[str, Any] = {"Viewer": lambda out: this.Viewer(b"", out)}
    if args.against:
        other = _module(args.against.resolve(), "serve_load", "serve_load_against")
        if other is not None:
            readers["Viewer (against)"] = lambda out: other.Viewer(b"", out)
        serve = _module(args.against.resolve(), "serve", "serve_against")
        light = getattr(serve, "_LightViewer", None)  # bench/serve.py's own reader, before
        if light is not None:
            readers["_LightViewer (against)"] = lambda out: light("/", "h", out, asyncio.Event())
    rows = asyncio.run(measure(readers, args.repeats))
    load = os.getloadavg()
    print(f"WebSocket reader CPU µs per frame (best of {args.repeats}; load {load[0]:.1f})\n")
    print("| frame bytes | read bytes | " + " | ".join(readers) + " |")
    print("|---|---|" + "---|" * len(readers))
    for r in rows:
        cells = " | ".join(str(r[k]) for k in readers)
        print(f"| {r['frame_bytes']} | {r['read_bytes']} | {cells} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows, "loadavg": load}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
