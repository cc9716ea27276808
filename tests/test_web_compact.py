"""The page's compact decoder (client/web/js/compact.js) under Node: it decodes the bytes the Python
encoder made to the vertices the Python decoder gives, waits out deltas of a missed key frame as
it does, and refuses malformed frames."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from test_protocol_compact import synthetic_stream

from facecast.protocol.compact import CompactDecoder, CompactEncoder

JS = Path(__file__).resolve().parents[1] / "client" / "web" / "js" / "compact.js"

RUNNER = """
import { readFileSync, writeFileSync } from 'node:fs';
import { CompactDecoder } from './compact.mjs';
const dir = process.argv[2];
const m = JSON.parse(readFileSync(`${dir}/manifest.json`));
const buf = (name) => {
  const b = readFileSync(`${dir}/${name}`);
  return b.buffer.slice(b.byteOffset, b.byteOffset + b.length);
};
const dec = new CompactDecoder(new Float32Array(buf('rest.bin')), new Uint8Array(buf('groups.bin')));
const results = [];
const chunks = [];
for (const name of m.frames) {
  try {
    const out = await dec.decode(buf(name));
    if (out === null) results.push({ frame: name, wait: true });
    else {
      results.push({ frame: name, seq: out.seq, t: out.t, key: out.key });
      chunks.push(Buffer.from(out.positions.buffer));
    }
  } catch (e) {
    results.push({ frame: name, error: String(e.message || e) });
  }
}
writeFileSync(`${dir}/positions.bin`, Buffer.concat(chunks));
writeFileSync(`${dir}/results.json`, JSON.stringify(results));
"""


@pytest.fixture(scope="module")
def node() -> str:
    exe = shutil.which("node")
    if exe is None:
        pytest.skip("node is not installed")
    return exe


def _run(
    node: str, tmp: Path, rest, groups, frames: dict[str, bytes], order: list[str]
) -> list[dict]:
    shutil.copy(JS, tmp / "compact.mjs")
    (tmp / "run.mjs").write_text(RUNNER)
    (tmp / "rest.bin").write_bytes(np.ascontiguousarray(rest, "<f4").tobytes())
    (tmp / "groups.bin").write_bytes(np.ascontiguousarray(groups, np.uint8).tobytes())
    for name, b in frames.items():
        (tmp / name).write_bytes(b)
    (tmp / "manifest.json").write_text(json.dumps({"frames": order}))
    subprocess.run([node, str(tmp / "run.mjs"), str(tmp)], check=True, timeout=120, cwd=tmp)
    return json.loads((tmp / "results.json").read_text())


def test_js_decodes_what_python_decodes(node, tmp_path):
    rest, groups, frames, transforms = synthetic_stream(n_vertices=2000, n_frames=30, seed=3)
    enc = CompactEncoder(rest, groups, tolerance=0.1, key_interval=5)
    wire = {
        f"f{i:03d}.bin": enc.encode(v, tr, seq=i, t=i / 60)
        for i, (v, tr) in enumerate(zip(frames, transforms))
    }
    order = [
        n for i, n in enumerate(sorted(wire)) if i not in (3, 9, 10, 11, 19)
    ]  # skips and a missed key (10)
    results = _run(node, tmp_path, rest, groups, wire, order)
    py = CompactDecoder(rest, groups)
    positions = np.frombuffer((tmp_path / "positions.bin").read_bytes(), "<f4").reshape(
        -1, len(rest), 3
    )
    k = 0
    for name, res in zip(order, results):
        expect = py.decode(wire[name])
        assert "error" not in res, res
        if expect is None:
            assert res.get("wait") and name in ("f012.bin", "f013.bin", "f014.bin")
            continue
        h, x = expect
        assert res["seq"] == h.seq and res["t"] == h.t
        js = positions[k]
        k += 1
        assert np.abs(js - x).max() <= 1e-5 * (1 + np.abs(x).max())  # float64 vs float32 arithmetic
        assert np.linalg.norm(js.astype(np.float64) - frames[h.seq], axis=1).max() <= 0.1
    assert k == len(positions) == len(order) - 3


def test_js_refuses_malformed_frames(node, tmp_path):
    rest, groups, frames, transforms = synthetic_stream(n_vertices=300, n_frames=3, seed=4)
    enc = CompactEncoder(rest, groups, tolerance=0.1)
    key = enc.encode(frames[0], transforms[0], seq=0, t=0)
    g, planes, nnz = key[40], key[41], struct.unpack_from("<I", key, 48)[0]
    raw = zlib.decompress(key[52 + 48 * g :])
    nb = -(-len(rest) // 8)

    def rebuild(payload: bytes, k: int = nnz) -> bytes:
        head = bytearray(key[: 52 + 48 * g])
        head[44:48] = struct.pack("<I", len(payload))
        head[48:52] = struct.pack("<I", k)
        return bytes(head) + payload

    def flip(bit: int) -> bytes:
        r = bytearray(raw)
        r[bit // 8] ^= 1 << (bit % 8)
        return bytes(r)

    bits = np.unpackbits(np.frombuffer(raw[: 3 * nb], np.uint8), bitorder="little")
    on, off = int(np.flatnonzero(bits)[0]), int(np.flatnonzero(bits == 0)[0])
    zero = bytearray(raw)
    zero[3 * nb] = 0

    bad = {
        "truncated.bin": key[:-1],
        "trailing.bin": key + b"\0",
        "kind.bin": key[:5] + b"\x02" + key[6:],
        "planes.bin": key[:41] + b"\x05" + key[42:],
        "notzlib.bin": rebuild(b"not a zlib stream"),
        "bomb.bin": rebuild(zlib.compress(bytes(3 * len(rest) * planes * 1000))),
        "short.bin": rebuild(zlib.compress(raw[:-1])),
        "rotation.bin": key[:52] + struct.pack("<f", 7.0) + key[56:],
        "format1.bin": key[:42] + b"\x01\x00" + key[44:],
        "nnz.bin": key[:48] + struct.pack("<I", 3 * len(rest) + 1) + key[52:],
        "bitmore.bin": rebuild(zlib.compress(flip(off))),
        "bitless.bin": rebuild(zlib.compress(flip(on))),
        "bitpast.bin": rebuild(zlib.compress(flip(8 * nb - 1))),
        "fewer.bin": rebuild(zlib.compress(raw[:-1]), nnz - 1),
        "good.bin": key,
    }
    if planes == 1:  # a value the bitmap marks, 0
        bad["zero.bin"] = rebuild(zlib.compress(bytes(zero)))
    order = sorted(bad)
    results = dict(zip(order, _run(node, tmp_path, rest, groups, bad, order)))
    assert "error" not in results["good.bin"] and results["good.bin"]["key"]
    for name in order:
        if name != "good.bin":
            assert "error" in results[name], (name, results[name])
    assert "format 1" in results["format1.bin"]["error"]


INFLATE_RUNNER = """
import { readFileSync, writeFileSync } from 'node:fs';
import { inflateExactly } from './compact.mjs';
const dir = process.argv[2];
const cases = JSON.parse(readFileSync(`${dir}/cases.json`));
const all = readFileSync(`${dir}/cases.bin`);
const out = [];
for (const [start, size, want] of cases) {
  try {
    const got = inflateExactly(new Uint8Array(all.buffer, all.byteOffset + start, size), want);
    out.push(Buffer.from(got).toString('base64'));
  } catch (e) {
    out.push(null);
  }
}
writeFileSync(`${dir}/results.json`, JSON.stringify(out));
"""


def _zlib_cases(rng: np.random.Generator) -> list[tuple[bytes, int]]:
    """(zlib stream, declared size): valid streams of every block type (stored, fixed, dynamic
    Huffman; RLE, LZ77, Huffman-only), from compact-like and random data, and mutations of them
    (bit flips, cuts, trailing bytes, wrong declared size)."""
    datas = [
        bytes(0),
        bytes(3000),
        rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        np.where(rng.random(40000) < 0.93, 0, rng.integers(0, 9, 40000)).astype(np.uint8).tobytes(),
        np.repeat(rng.integers(0, 4, 600), rng.integers(1, 300, 600)).astype(np.uint8).tobytes(),
    ]
    valid = []
    for d in datas:
        for level, strategy in (
            (0, zlib.Z_DEFAULT_STRATEGY),
            (1, zlib.Z_RLE),
            (6, zlib.Z_DEFAULT_STRATEGY),
            (9, zlib.Z_FILTERED),
            (1, zlib.Z_HUFFMAN_ONLY),
            (6, zlib.Z_FIXED),
        ):
            c = zlib.compressobj(level, zlib.DEFLATED, 15, 9, strategy)
            valid.append((c.compress(d) + c.flush(), len(d)))
    cases = list(valid)
    for z, n in valid:
        cases += [
            (z, n + 1),
            (z, max(0, n - 1)),
            (z[:-1], n),
            (z + b"\0", n),
            (z[: len(z) // 2], n),
        ]
        for _ in range(12):
            b = bytearray(z)
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, len(b)))
                b[i] ^= 1 << int(rng.integers(0, 8))
            cases.append((bytes(b), n))
    return cases


def test_js_inflate_agrees_with_zlib(node, tmp_path):
    """compact.js's own inflater accepts exactly the streams zlib accepts (at the declared size) and
    gives the same bytes: valid streams of every block type and a few thousand mutations."""
    import base64

    cases = _zlib_cases(np.random.default_rng(11))
    shutil.copy(JS, tmp_path / "compact.mjs")
    (tmp_path / "run.mjs").write_text(INFLATE_RUNNER)
    (tmp_path / "cases.bin").write_bytes(b"".join(z for z, _ in cases))
    starts = np.cumsum([0] + [len(z) for z, _ in cases])
    (tmp_path / "cases.json").write_text(
        json.dumps([[int(s), len(z), n] for s, (z, n) in zip(starts, cases)])
    )
    subprocess.run([node, str(tmp_path / "run.mjs"), str(tmp_path)], check=True, timeout=120)
    got = json.loads((tmp_path / "results.json").read_text())
    accepted = 0
    for (z, n), js in zip(cases, got):
        d = zlib.decompressobj()
        try:
            raw = d.decompress(z, n)
            ok = len(raw) == n and d.eof and not d.unconsumed_tail and not d.unused_data
        except zlib.error:
            ok = False
        assert (js is not None) == ok, (z.hex()[:80], n, ok)
        if ok:
            accepted += 1
            assert base64.b64decode(js) == raw
    assert accepted >= 30
