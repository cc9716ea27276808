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
    g, planes = key[40], key[41]
    raw = zlib.decompress(key[48 + 48 * g :])

    def rebuild(payload: bytes) -> bytes:
        head = bytearray(key[: 48 + 48 * g])
        head[44:48] = struct.pack("<I", len(payload))
        return bytes(head) + payload

    bad = {
        "truncated.bin": key[:-1],
        "trailing.bin": key + b"\0",
        "kind.bin": key[:5] + b"\x02" + key[6:],
        "planes.bin": key[:41] + b"\x05" + key[42:],
        "notzlib.bin": rebuild(b"not a zlib stream"),
        "bomb.bin": rebuild(zlib.compress(bytes(3 * len(rest) * planes * 1000))),
        "short.bin": rebuild(zlib.compress(raw[:-1])),
        "rotation.bin": key[:48] + struct.pack("<f", 7.0) + key[52:],
        "good.bin": key,
    }
    order = sorted(bad)
    results = dict(zip(order, _run(node, tmp_path, rest, groups, bad, order)))
    assert "error" not in results["good.bin"] and results["good.bin"]["key"]
    for name in order:
        if name != "good.bin":
            assert "error" in results[name], (name, results[name])
