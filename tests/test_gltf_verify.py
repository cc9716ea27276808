"""A written .glb is read back independently (pygltflib + numpy, none of the writer's code): every frame
rebuilt as rest + weights . targets matches the renderer's float vertices within the tolerance the file
records; a clip the writer cannot represent within it is refused (exit 2, no file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
import pytest

from facecast.server.cli import main
from facecast.server.drivers.fap import load as load_fap
from facecast.server.output import gltf
from facecast.server.pipeline import Animator
from facecast.server.render import render_file

_DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}
_WIDTH = {"SCALAR": 1, "VEC3": 3}


def read_back(path: Path) -> dict:
    """``rest (V, 3)``, ``targets (M, V, 3)``, ``weights (T, M)``, ``times (T,)`` (float64), the node's
    ``scale`` and the recorded ``tolerance_mm`` / ``max_error_mm`` of a .glb, by pygltflib alone."""
    g = pygltflib.GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def acc(i: int) -> np.ndarray:
        a = g.accessors[i]
        v = g.bufferViews[a.bufferView]
        n = _WIDTH[a.type]
        dt = np.dtype(_DTYPES[a.componentType])
        assert v.byteStride in (None, 0, n * dt.itemsize)
        data = np.frombuffer(
            blob, dtype=dt, count=a.count * n, offset=v.byteOffset + (a.byteOffset or 0)
        )
        return data.reshape(a.count, n).astype(np.float64)

    mesh = g.meshes[g.nodes[0].mesh]
    prim = mesh.primitives[0]
    targets = np.stack(
        [acc(t["POSITION"] if isinstance(t, dict) else t.POSITION) for t in prim.targets]
    )
    sampler = g.animations[0].samplers[g.animations[0].channels[0].sampler]
    assert (
        g.animations[0].channels[0].target.path == "weights" and sampler.interpolation == "LINEAR"
    )
    times = acc(sampler.input).reshape(-1)
    weights = acc(sampler.output).reshape(len(times), len(targets))
    return {
        "rest": acc(prim.attributes.POSITION),
        "targets": targets,
        "weights": weights,
        "times": times,
        "scale": g.nodes[0].scale,
        "tolerance_mm": g.asset.extras["tolerance_mm"],
        "max_error_mm": g.asset.extras["max_error_mm"],
        "record": g.extras["facecast"],
    }


def max_error_mm(glb: dict, frames: np.ndarray, mm_per_unit: float) -> float:
    """Largest vertex distance (mm) between the frames the file shows at its keyframes and ``frames``."""
    err = 0.0
    for s in range(0, len(frames), 16):
        shown = glb["rest"] + np.einsum("tm,mvc->tvc", glb["weights"][s : s + 16], glb["targets"])
        err = max(err, float(np.linalg.norm(shown - frames[s : s + 16], axis=2).max()))
    return err * mm_per_unit


@pytest.fixture(scope="module")
def face():
    from facecast.server.faces import load_face

    return load_face("default:2k")


def test_joy_glb_read_back_matches_the_renderer_within_its_recorded_tolerance(
    data_dir, face, tmp_path
):
    src = data_dir / "xface" / "faps" / "joy.fap"
    out = tmp_path / "joy.glb"
    render_file(src, out, face=face, backend="numpy")
    glb = read_back(out)
    frames = Animator(face, backend="numpy").render(load_fap(src, face))
    assert glb["weights"].shape[0] == len(frames) == 108
    assert glb["tolerance_mm"] == 0.01 and glb["record"]["verified"] is True
    err = max_error_mm(glb, frames, face.mm_per_unit)
    assert err <= glb["tolerance_mm"]
    assert err == pytest.approx(glb["max_error_mm"], abs=1e-5)  # the recorded error is the real one


def test_many_vertices_in_float32_stay_within_the_tolerance(tmp_path):
    """100k vertices, most of them moving by centimetres: the old frame-norm criterion met float32
    rounding there (LinAlgError at this size; at 300k a 128-target file 133 mm off, written with exit 0)."""
    rng = np.random.default_rng(0)
    V, T = 100_000, 24
    rest = rng.normal(0, 80, (V, 3)).astype(np.float32)
    centres = rest[rng.choice(V, 6)]
    bumps = np.exp(-((rest[:, None] - centres[None]) ** 2).sum(-1) / (2 * 150.0**2))  # (V, 6)
    frames = (rest[None] + np.einsum("vb,tbc->tvc", bumps, rng.normal(0, 10, (T, 6, 3)))).astype(
        np.float32
    )
    out = tmp_path / "big.glb"
    rec = gltf.write_glb(out, frames, rest, np.array([[0, 1, 2]]), 25.0)
    glb = read_back(out)
    assert rec["targets"] == len(glb["targets"]) <= 18  # 6 bumps x 3 axes
    err = max_error_mm(glb, frames, 1.0)
    assert err <= glb["tolerance_mm"] == 0.01
    assert err == pytest.approx(glb["max_error_mm"], abs=1e-5)


def test_a_clip_the_writer_cannot_represent_is_refused_with_exit_2(
    data_dir, tmp_path, monkeypatch, capsys
):
    """With at most 2 targets joy (108 frames) cannot be met: no file, a message saying what to do."""
    monkeypatch.setattr(gltf, "MAX_TARGETS", 2)
    out = tmp_path / "joy.glb"
    code = main(
        [
            "render",
            str(data_dir / "xface" / "faps" / "joy.fap"),
            "-o",
            str(out),
            "--face",
            "default:2k",
            "--backend",
            "numpy",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2 and not out.exists() and not list(tmp_path.iterdir())
    assert err.startswith(f"facecast: {out}: refusing to write a wrong file: 108 frames of a ")
    assert "more than 2 morph targets to stay within 0.01 mm" in err and "write .npz instead" in err


def test_glb_normals_are_the_deform_modules_vertex_normals(tmp_path, rng):
    """The .glb's rest normals (read back by pygltflib) are ``deform.normals.vertex_normals`` of the
    rest mesh in float32, ``+z`` where a vertex is in no triangle; the writer's per-frame normals
    (16 frames per batch) are that function's on each frame alone."""
    from facecast.server.deform.normals import incidence_matrix, vertex_normals

    n = 7  # a bumpy 7 x 7 grid and one vertex in no triangle
    x, y = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    rest = np.stack([x.ravel(), y.ravel(), 0.3 * np.sin(x + 2 * y).ravel()], axis=1)
    rest = np.vstack([rest, [[3.0, 3.0, 5.0]]]).astype(np.float32)
    quads = [
        (i * n + j, i * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)
    ]
    quads += [
        (i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j)
        for i in range(n - 1)
        for j in range(n - 1)
    ]
    tri = np.asarray(quads, dtype=np.int64)
    frames = (rest[None] + rng.normal(0, 0.05, (40, len(rest), 3))).astype(np.float32)

    expected = np.stack([vertex_normals(f, tri, dtype=np.float32) for f in frames])
    expected[:, -1] = (0.0, 0.0, 1.0)
    inc = incidence_matrix(tri.astype(np.int32), len(rest))
    np.testing.assert_array_equal(gltf.unit_normals(frames, tri.astype(np.uint32), inc), expected)

    path = tmp_path / "grid.glb"
    blob, _ = gltf.encode_glb(frames, rest, tri, 30.0)
    path.write_bytes(blob)
    g = pygltflib.GLTF2().load_binary(str(path))
    a = g.accessors[g.meshes[0].primitives[0].attributes.NORMAL]
    v = g.bufferViews[a.bufferView]
    shown = np.frombuffer(
        g.binary_blob(), np.float32, a.count * 3, v.byteOffset + (a.byteOffset or 0)
    ).reshape(-1, 3)
    want = vertex_normals(rest, tri, dtype=np.float32)
    want[-1] = (0.0, 0.0, 1.0)
    np.testing.assert_array_equal(shown, want)
