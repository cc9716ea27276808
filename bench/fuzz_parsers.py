"""Fuzzing the parsers of client files: C3D, TRC, CSV, FAP, the ``.face.json`` annotation and BML.

    python bench/fuzz_parsers.py [--inputs 3000] [--seed 1] [--parsers c3d,trc,csv,fap,annotation,bml]
    python bench/fuzz_parsers.py --parsers ezc3d    # baseline: the same C3D inputs through ezc3d

Each input is a seed file (generated takes written by facecast's C3D writer and, when installed, by
ezc3d; the Xface ``.fap`` files; the shipped ICT FaceKit annotation) with 1-4 random mutations: bit
flips, interesting bytes and 16/32-bit integers at random offsets, insertions, deletions,
truncations, repeated spans, and for text and JSON a replaced token or value (huge integers, NaN,
infinities, wrong types). Inputs run in a child process with a memory limit, one at a time, with a
per-input timeout, so a crash or hang is counted, not suffered. An outcome is: ``parsed``,
``project_errors`` (the parser's own error), ``other_errors`` (any other exception: a 500 in the
server), ``crashes`` (the child died) or ``hangs`` (no answer within the timeout). Targets (issue
12): crashes 0, hangs 0, other_errors 0. Writes ``bench/out/fuzz_parsers.json`` and a table.

``fuzz_counts(parser_name, n, seed)`` is the reusable entry (bench/robustness.py imports it).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import random
import sys
import time
from functools import cache, lru_cache
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out" / "fuzz_parsers.json"
PARSERS = ("c3d", "trc", "csv", "fap", "annotation", "bml")
#: Seconds one input may take before it counts as a hang (parsers take milliseconds).
TIMEOUT_S = 10.0
#: Address-space limit of the child (bytes): a parser that tries to allocate more fails there.
MEMORY_LIMIT = 4 << 30

INTERESTING_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFF, 0x50, 0x54, 0x55, 0x56, 0x20, 0x0A)
INTERESTING_INTS = (0, 1, -1, 2, 255, 256, 511, 512, 32767, -32768, 65535, 2**31 - 1, -(2**31))
INTERESTING_TOKENS = (
    "nan",
    "-nan",
    "inf",
    "-inf",
    "1e309",
    "-1",
    "0",
    "",
    " ",
    "\t",
    ",",
    "#",
    "9" * 4301,
    "1" * 19,
    "-" * 3,
    "\xff",
    "\x00",
    "0x10",
    "1_000",
    "٣",
)
#: Stands for an integer of 4,301 digits (json.dumps cannot write one; json.loads refuses it).
HUGE_INT = "<4301 digits>"
INTERESTING_JSON = (
    {},
    [],
    0,
    -1,
    1.5,
    True,
    None,
    "x",
    "",
    10**30,
    [0, 1, 2],
    [[0, 10**9]],
    {"a": [1]},
    [[]],
    "+y",
    [True, 0, 0],
    26719,
    -26720,
    HUGE_INT,
)


# ------------------------------------------------------------------------------------------ seeds


@cache
def seeds(parser: str) -> tuple[bytes, ...]:
    """Seed files of ``parser`` (generated or real; never empty)."""
    import numpy as np

    from facecast.protocol.markers_file import MarkerTake, write_c3d, write_csv, write_trc

    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(12, 4, 3)) * 40.0 + [0.0, 1600.0, 0.0]
    xyz[3, 1] = np.nan
    take = MarkerTake(["CHIN", "LIP_L", "LIP_R", "HEAD 1"], xyz, 120.0, "mm")
    if parser in ("c3d", "ezc3d"):
        out = [
            write_c3d(take),
            write_c3d(take, processor="dec", scale=0.1),
            write_c3d(take, processor="mips", scale=-0.5),
        ]
        ez = _ezc3d_bytes(take)
        return tuple(out + ([ez] if ez else []))
    if parser == "trc":
        return (write_trc(take).encode(),)
    if parser == "csv":
        return (write_csv(take).encode(),)
    if parser == "fap":
        from facecast.server.paths import shared_data

        d = shared_data()
        files = sorted((d / "xface" / "faps").glob("*.fap")) if d else []
        if files:
            return tuple(f.read_bytes() for f in files)
        from facecast.protocol.fap_file import FapFile, FapFrame, write_fap

        frames = tuple(
            FapFrame.build(i, {3: 10 * i, 5: -i, 19: 400}, viseme=(1, 2, 30, 0)) for i in range(5)
        )
        return (write_fap(FapFile(name="generated", frames=frames)).encode(),)
    if parser == "annotation":
        from facecast.server.faces.ict import ANNOTATION

        return (ANNOTATION.read_bytes(),)
    if parser == "bml":
        return (BML_SEED,)
    raise ValueError(f"unknown parser {parser!r}; one of {', '.join(PARSERS)}")


def _ezc3d_bytes(take) -> bytes | None:
    """The take as ezc3d writes it (tests/test_c3d.py's writer, 2 analog channels), or None without
    ezc3d."""
    try:
        import ezc3d  # noqa: F401
    except ImportError:
        return None
    import tempfile

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    try:
        from test_c3d import _ezc3d_write
    finally:
        sys.path.pop(0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ez.c3d"
        _ezc3d_write(take, path, analog_channels=2)
        return path.read_bytes()


# -------------------------------------------------------------------------------------- mutations


def mutate(data: bytes, rng: random.Random, kind: str = "binary") -> bytes:
    """``data`` with 1-4 random mutations; ``kind`` (binary, text, json) adds structured ones."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.random()
        if kind == "json" and op < 0.5:
            b = bytearray(_mutate_json(bytes(b), rng))
        elif kind == "text" and op < 0.4:
            b = bytearray(_mutate_token(bytes(b), rng))
        else:
            b = _mutate_bytes(b, rng)
    return bytes(b)


def _mutate_bytes(b: bytearray, rng: random.Random) -> bytearray:
    n = len(b)
    pos = rng.randrange(n) if n else 0
    op = rng.randrange(8)
    if op == 0 and n:
        b[pos] ^= 1 << rng.randrange(8)
    elif op == 1 and n:
        b[pos] = rng.choice(INTERESTING_BYTES)
    elif op in (2, 3) and n >= 4:
        size, order = (2, rng.choice("<>")) if op == 2 else (4, rng.choice("<>"))
        v = rng.choice(INTERESTING_INTS) & ((1 << (8 * size)) - 1)
        pos = min(pos, n - size)
        if rng.random() < 0.5:  # C3D words sit at even offsets
            pos -= pos % 2
        b[pos : pos + size] = v.to_bytes(size, "little" if order == "<" else "big")
    elif op == 4:
        b[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
    elif op == 5 and n:
        del b[pos : pos + rng.randint(1, 64)]
    elif op == 6 and n:
        del b[rng.randrange(n) :]  # truncation
    elif op == 7 and n:
        span = b[pos : pos + rng.randint(1, 256)]
        b[pos:pos] = span * rng.randint(1, 8)
    return b


def _mutate_token(data: bytes, rng: random.Random) -> bytes:
    lines = data.split(b"\n")
    i = rng.randrange(len(lines))
    sep = b"\t" if b"\t" in lines[i] else (b"," if b"," in lines[i] else b" ")
    parts = lines[i].split(sep)
    j = rng.randrange(len(parts))
    parts[j] = rng.choice(INTERESTING_TOKENS).encode("utf-8")
    lines[i] = sep.join(parts)
    if rng.random() < 0.2:  # duplicate or drop a whole line
        k = rng.randrange(len(lines))
        if rng.random() < 0.5:
            lines.insert(k, lines[i])
        else:
            del lines[k]
    return b"\n".join(lines)


def _mutate_json(data: bytes, rng: random.Random) -> bytes:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return data
    nodes: list[tuple[object, object]] = []  # (container, key)

    def walk(x, depth=0):
        if depth > 6 or len(nodes) > 5000:
            return
        items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
        for k, v in items:
            nodes.append((x, k))
            walk(v, depth + 1)

    walk(doc)
    if not nodes:
        return json.dumps(rng.choice(INTERESTING_JSON)).encode()
    container, key = rng.choice(nodes)
    if isinstance(container, dict) and rng.random() < 0.2:  # rename a key
        container[
            rng.choice(["units", "pivots", "parts", "axes", "feature_points", "2.99", ""])
        ] = container.pop(key)
    else:
        container[key] = rng.choice(INTERESTING_JSON)
    return json.dumps(doc).replace(f'"{HUGE_INT}"', "9" * 4301).encode()  # over int()'s limit


#: A BML performance with every supported behaviour and reference form.
BML_SEED = b"""<?xml version="1.0" encoding="UTF-8"?>
<bml xmlns="http://www.bml-initiative.org/bml/bml-1.0" id="bml1" characterId="A">
  <speech id="s1" audio="hello.wav" start="0.3">
    <text>Hello there, <sync id="tm1"/> nice to <sync id="tm2"/> meet you.</text>
  </speech>
  <faceLexeme id="f1" lexeme="JOY" amount="0.8" start="s1:tm1" end="s1:end + 0.5"/>
  <faceFacs id="a1" au="12" side="LEFT" attack="s1:tm2" relax="s1:end-0.2"/>
  <face id="b1" lexeme="raise_brows" start="a1:relax" end="a1:end + 1e-1"/>
  <gaze id="g1" target="camera" influence="HEAD" offsetAngle="10" offsetDirection="UPLEFT"
        start="0" end="s1:tm2"/>
  <gaze id="g2" target="0 12.5 300" ready="g1:end"/>
  <head id="h1" lexeme="NOD" repetition="2" stroke-start="g1:end" amount=".4"/>
  <head id="h2" lexeme="TILT" start="bml1:h1:end"/>
</bml>
"""

KIND = {
    "bml": "text",
    "c3d": "binary",
    "ezc3d": "binary",
    "trc": "text",
    "csv": "text",
    "fap": "text",
    "annotation": "json",
}


def fuzz_input(parser: str, seed: int, i: int) -> bytes:
    """Input ``i`` of the run ``(parser, seed)``: deterministic."""
    rng = random.Random(f"{parser}:{seed}:{i}")
    return mutate(rng.choice(seeds(parser)), rng, KIND[parser])


# ---------------------------------------------------------------------------------------- parsing


@lru_cache(maxsize=1)
def _ict_mesh():
    import numpy as np

    return np.zeros((26719, 3), np.float32), np.array([[0, 1, 2]], np.int32)


def parse(parser: str, data: bytes) -> None:
    """Parse ``data`` as the server does; raises the project's error on malformed input."""
    if parser == "c3d":
        from facecast.protocol.markers_file import read_c3d

        read_c3d(data, where="fuzz.c3d")
    elif parser in ("trc", "csv"):
        from facecast.protocol.markers_file import read_csv, read_trc

        text = data.decode("utf-8", errors="replace")  # as facecast.server.mocap.io reads them
        (read_trc if parser == "trc" else read_csv)(text, where=f"fuzz.{parser}")
    elif parser == "fap":
        from facecast.protocol.fap_file import read_fap

        read_fap(data.decode("utf-8", errors="replace"), where="fuzz.fap")
    elif parser == "annotation":
        from facecast.server.faces.loaders import face_from_annotation, parse_annotation

        vertices, triangles = _ict_mesh()
        face_from_annotation(
            "fuzz",
            vertices,
            triangles,
            parse_annotation(data, where="fuzz.json"),
            where="fuzz.json",
        )
    elif parser == "bml":
        from facecast.protocol.bml import parse_bml

        parse_bml(data, where="fuzz.bml")
    elif parser == "ezc3d":  # the baseline: the native reader the server used before issue 12
        import tempfile

        import ezc3d

        with tempfile.NamedTemporaryFile(suffix=".c3d") as f:
            f.write(data)
            f.flush()
            try:
                ezc3d.c3d(f.name)
            except Exception as e:  # noqa: BLE001 - its RuntimeErrors were caught as input errors
                raise _Refused(str(e)) from None
    else:
        raise ValueError(f"unknown parser {parser!r}")


class _Refused(Exception):
    """ezc3d refused the file with an exception (what the old server turned into a 400)."""


def project_errors() -> tuple[type[Exception], ...]:
    from facecast.server.errors import CLIENT_ERRORS

    return (*CLIENT_ERRORS, _Refused)


def _child(conn, parser: str, seed: int) -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    ours = project_errors()
    seeds(parser)
    conn.send("ready")
    while True:
        i = conn.recv()
        if i is None:
            return
        data = fuzz_input(parser, seed, i)
        t = time.perf_counter()
        try:
            parse(parser, data)
            outcome, detail = "parsed", ""
        except ours:
            outcome, detail = "project_errors", ""
        except Exception as e:  # noqa: BLE001 - counting exactly these is the point
            outcome, detail = "other_errors", f"{type(e).__name__}: {str(e)[:200]}"
        conn.send((outcome, detail, time.perf_counter() - t))


def fuzz_counts(parser_name: str, n: int, seed: int = 1, timeout: float = TIMEOUT_S) -> dict:
    """Fuzz ``parser_name`` with ``n`` mutated inputs; counts of each outcome (see module doc).

    Returns ``dict(parser, inputs, crashes, hangs, project_errors, parsed, other_errors,
    max_seconds, examples)``; ``examples`` lists up to 5 failing inputs as ``(index, outcome,
    detail)``; ``fuzz_input(parser, seed, index)`` rebuilds one.
    """
    if parser_name not in PARSERS + ("ezc3d",):
        raise ValueError(f"unknown parser {parser_name!r}; one of {', '.join(PARSERS)}")
    ctx = mp.get_context("spawn")  # not fork: a caller may have threads (a server client, a loop)
    counts = {
        "parser": parser_name,
        "inputs": 0,
        "crashes": 0,
        "hangs": 0,
        "project_errors": 0,
        "parsed": 0,
        "other_errors": 0,
        "max_seconds": 0.0,
        "examples": [],
    }
    proc = conn = None

    def start():
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_child, args=(child, parser_name, seed), daemon=True)
        p.start()
        if not parent.poll(120) or parent.recv() != "ready":
            raise RuntimeError("the fuzzing child did not start")
        return p, parent

    def stop(p) -> None:
        if p.is_alive():
            p.kill()
        p.join()

    try:
        for i in range(n):
            if proc is None:
                proc, conn = start()
            conn.send(i)
            counts["inputs"] += 1
            outcome = detail = None
            try:
                if conn.poll(timeout):
                    outcome, detail, seconds = conn.recv()
                    counts["max_seconds"] = max(counts["max_seconds"], seconds)
                else:
                    outcome, detail = "hangs", f"no answer in {timeout} s"
            except (EOFError, OSError):
                outcome = None
            if outcome is None:
                proc.join(5)
                outcome, detail = "crashes", f"child exit code {proc.exitcode}"
            if outcome in ("hangs", "crashes"):
                stop(proc)
                proc = None
            counts[outcome] += 1
            if outcome not in ("parsed", "project_errors") and len(counts["examples"]) < 5:
                counts["examples"].append((i, outcome, detail))
    finally:
        if proc is not None:
            try:
                conn.send(None)
            except OSError:
                pass
            proc.join(5)
            stop(proc)
    return counts


# ------------------------------------------------------------------------------------------- main


def _load() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "?"


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--inputs", type=int, default=3000, help="mutated inputs per parser")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--parsers", default=",".join(PARSERS))
    a = p.parse_args(argv)
    results, load_before = [], _load()
    for name in a.parsers.split(","):
        t = time.perf_counter()
        r = fuzz_counts(name.strip(), a.inputs, a.seed)
        r["seconds"] = time.perf_counter() - t
        results.append(r)
    record = {
        "inputs_per_parser": a.inputs,
        "seed": a.seed,
        "timeout_s": TIMEOUT_S,
        "memory_limit_bytes": MEMORY_LIMIT,
        "load_before": load_before,
        "load_after": _load(),
        "cpus": os.cpu_count(),
        "results": results,
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(record, indent=2))
    print(
        f"load average before {load_before}, after {record['load_after']} ({os.cpu_count()} CPUs)\n"
    )
    print(
        "| parser | inputs | parsed | project errors | other errors | crashes | hangs | slowest (ms) | run (s) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in results:
        print(
            f"| {r['parser']} | {r['inputs']} | {r['parsed']} | {r['project_errors']} | {r['other_errors']} "
            f"| {r['crashes']} | {r['hangs']} | {1000 * r['max_seconds']:.1f} | {r['seconds']:.1f} |"
        )
    bad = [r for r in results if r["crashes"] or r["hangs"] or r["other_errors"]]
    for r in bad:
        print(f"{r['parser']}: {r['examples']}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
