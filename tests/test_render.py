"""Batch rendering: real .fap files -> .glb/.npz/.fap, re-imported with pygltflib; CLI errors; atomic output."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from test_mpeg4 import synthetic_face

from facecast.protocol.fap_file import read_fap
from facecast.server.drivers.fap import load as load_fap
from facecast.server.errors import InputError
from facecast.server.output.atomic import atomic_path
from facecast.server.output.gltf import encode_glb
from facecast.server.output.npz import read_npz
from facecast.server.pipeline import Animator
from facecast.server.render import render_file

XFACE = ["anger.fap", "beg.fap", "disgust.fap", "happy-for.fap", "joy.fap"]
MOUTH_FPS = ("2.2", "2.3", "8.1", "8.2", "8.3", "8.4")
BROW_FPS = ("4.1", "4.2", "4.3", "4.4", "4.5", "4.6")


@pytest.fixture(scope="module")
def small_face():
    """The small test face (``default:2k`` once the built-in head exists, else a synthetic head)."""
    from facecast.server.faces import load_face

    try:
        return load_face("default:2k")
    except ModuleNotFoundError:
        return synthetic_face()


@pytest.fixture(scope="module")
def animator(small_face):
    return Animator(small_face, backend="numpy")


def read_glb(path: Path) -> dict:
    """Decode a .glb with pygltflib into plain arrays (rest, targets, times, weights, extras)."""
    g = pygltflib.GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def acc(i: int) -> np.ndarray:
        a = g.accessors[i]
        v = g.bufferViews[a.bufferView]
        dtype = {5126: np.float32, 5125: np.uint32}[a.componentType]
        n = {"SCALAR": 1, "VEC3": 3}[a.type]
        off = v.byteOffset + (a.byteOffset or 0)
        return (
            np.frombuffer(blob, dtype=dtype, count=a.count * n, offset=off)
            .reshape(a.count, n)
            .squeeze()
        )

    prim = g.meshes[0].primitives[0]
    sampler = g.animations[0].samplers[0]
    targets = np.stack(
        [acc(t["POSITION"] if isinstance(t, dict) else t.POSITION) for t in prim.targets]
    )
    times = acc(sampler.input).reshape(-1)
    weights = acc(sampler.output).reshape(len(times), len(targets))
    return {
        "gltf": g,
        "rest": acc(prim.attributes.POSITION),
        "normals": acc(prim.attributes.NORMAL),
        "indices": acc(prim.indices).reshape(-1, 3),
        "targets": targets,
        "times": times,
        "weights": weights,
        "extras": g.extras["facecast"],
    }


def frames_of(glb: dict) -> np.ndarray:
    """``(T, V, 3)`` vertices the glTF animation shows at its keyframes."""
    return glb["rest"][None] + np.einsum("tm,mvc->tvc", glb["weights"], glb["targets"])


def _fp_motion(face, frames, fps_ids) -> float:
    ids = [face.feature_points[p] for p in fps_ids if p in face.feature_points]
    return float(np.linalg.norm(frames[:, ids] - face.vertices[ids], axis=2).max())


@pytest.mark.parametrize("name", XFACE)
def test_real_fap_file_renders_to_a_glb_that_pygltflib_reads(
    data_dir, small_face, animator, tmp_path, name
):
    src = data_dir / "xface" / "faps" / name
    fap = read_fap(src.read_text(), where=name)
    out = tmp_path / (src.stem + ".glb")
    calls = []
    summary = render_file(
        src, out, face=small_face, backend="numpy", progress=lambda d, t: calls.append((d, t))
    )
    assert calls[-1] == (len(fap), len(fap))
    glb = read_glb(out)
    assert glb["gltf"].asset.version == "2.0"
    assert len(glb["times"]) == len(fap) == glb["extras"]["frames"] == summary["frames"]
    assert glb["times"][-1] == pytest.approx((len(fap) - 1) / 25.0)
    np.testing.assert_array_equal(glb["indices"], small_face.triangles)
    shown = frames_of(glb)
    assert np.isfinite(shown).all()
    # The glTF shows what the animator computes, within the recorded error bound.
    expected = animator.render(load_fap(src, small_face))
    err_mm = np.linalg.norm(shown - expected, axis=2).max() * small_face.mm_per_unit
    assert err_mm <= glb["extras"]["error_bound_mm"] + 1e-3
    assert glb["extras"]["max_error_mm"] <= glb["extras"]["tolerance_mm"] + 1e-6
    # Mouth always moves; brows move when the file drives them (joy and happy-for leave them alone).
    assert _fp_motion(small_face, shown, MOUTH_FPS) * small_face.mm_per_unit > 1.0
    brow_max = max(abs(fr.faps().get(k, 0)) for fr in fap.frames for k in range(31, 37))
    if brow_max:  # brow control displacements (head-local, before the head pose) follow FAPs 31-36
        brow_d = [animator.solve(s)[0] for s in load_fap(src, small_face).states]
        idx = [i for i, n in enumerate(animator.rig.fp_ids) if set(n.split("+")) & set(BROW_FPS)]
        assert max(np.abs(d[idx, 1]).max() for d in brow_d) == pytest.approx(
            brow_max * animator.rig.fapu["ENS"], rel=1e-3
        )


@pytest.fixture(scope="module")
def ict_face(data_dir):
    from facecast.server.faces import load_face

    return load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")


@pytest.mark.slow
@pytest.mark.parametrize("name", XFACE)
def test_glb_of_ict_head(data_dir, ict_face, tmp_path, name):
    """The scanned head in centimetres: node scaled to metres, jaw opens, lower teeth follow."""
    face = ict_face
    src = data_dir / "xface" / "faps" / name
    fap = read_fap(src.read_text(), where=name)
    out = tmp_path / "out.glb"
    render_file(src, out, face=face, backend="numpy")
    glb = read_glb(out)
    assert glb["gltf"].nodes[0].scale == pytest.approx([0.01] * 3)
    assert len(glb["times"]) == len(fap)
    shown = frames_of(glb)
    assert np.isfinite(shown).all()
    teeth = face.part("teeth_lower")
    drop = (face.vertices[teeth, 1] - shown[:, teeth, 1]).mean(axis=1)
    jaw = max(fr.faps().get(3, 0) for fr in fap.frames)
    assert (
        drop.max() > 0.5 * jaw / 1024 * 2.12
    )  # cm: the jaw opens by about FAP 3 x MNS (MNS0 2.12 cm)
    assert _fp_motion(face, shown, MOUTH_FPS) > 0.3


def test_npz_and_fap_outputs(data_dir, small_face, animator, tmp_path):
    src = data_dir / "xface" / "faps" / "beg.fap"
    render_file(src, tmp_path / "beg.npz", face=small_face, backend="numpy")
    vertices, faces, fps = read_npz(tmp_path / "beg.npz")
    assert vertices.shape == (107, small_face.n_vertices, 3) and vertices.dtype == np.float32
    np.testing.assert_array_equal(faces, small_face.triangles)
    assert fps == 25.0
    np.testing.assert_allclose(
        vertices[40], animator.frame(load_fap(src, small_face).states[40]), atol=1e-5
    )
    render_file(src, tmp_path / "beg.fap", face=small_face)
    again = load_fap(tmp_path / "beg.fap", small_face)
    orig = load_fap(src, small_face)
    assert again.fps == orig.fps and len(again) == len(orig)
    np.testing.assert_array_equal(
        np.array([s.faps for s in again.states]), np.array([s.faps for s in orig.states])
    )


def test_masked_faps_hold_their_previous_value(tmp_path):
    mask = lambda *k: " ".join("1" if i in k else "0" for i in range(1, 69))  # noqa: E731
    p = tmp_path / "m.fap"
    p.write_text(f"2.1 m 10 3\n{mask(3, 19)}\n0 100 50\n{mask(3)}\n1 120\n{mask(19)}\n2 7\n")
    hold = load_fap(p, None)
    assert [(s.faps[3], s.faps[19]) for s in hold.states] == [(100, 50), (120, 50), (120, 7)]
    zero = load_fap(p, None, masked="zero")
    assert [(s.faps[3], s.faps[19]) for s in zero.states] == [(100, 50), (120, 0), (0, 7)]
    assert [s.t for s in hold.states] == [0.0, 0.1, 0.2]


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


MASK = " ".join(["0", "0", "1"] + ["0"] * 65)
BAD_FILES = {
    "truncated.fap": (f"2.1 t 25 2\n{MASK}\n0 5\n{MASK}\n", 4),
    "shortmask.fap": ("2.1 t 25 1\n" + " ".join(["0"] * 60) + "\n0\n", 2),
    "nonnumeric.fap": (f"2.1 t 25 1\n{MASK}\n0 x5\n", 3),
}


def test_cli_reports_malformed_fap_with_file_and_line_and_leaves_no_output(tmp_path):
    for name, (text, line) in BAD_FILES.items():
        (tmp_path / name).write_text(text)
        r = _cli(
            "render",
            name,
            "-o",
            "out.glb",
            "--face",
            "default:2k",
            "--backend",
            "numpy",
            cwd=tmp_path,
        )
        assert r.returncode == 2, r.stderr
        msg = r.stderr.strip().splitlines()[-1]
        assert msg.startswith(f"facecast: {name}:{line}:"), msg
        assert not (tmp_path / "out.glb").exists() and not list(tmp_path.glob(".out.glb*"))
    r = _cli("render", "truncated.fap", "-o", "out.obj", cwd=tmp_path)
    assert r.returncode == 2 and "unsupported output type '.obj'" in r.stderr


@pytest.mark.slow
def test_cli_renders_and_faces_describes(data_dir, tmp_path):
    r = _cli("render", str(data_dir / "xface" / "faps" / "joy.fap"), "-o", "joy.fap", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(read_fap((tmp_path / "joy.fap").read_text())) == 108
    assert "it/s" not in r.stderr and "frame/s" not in r.stderr  # no progress bar off a terminal
    r = _cli("faces", cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("default")
    r = _cli("faces", str(data_dir / "ict-facekit" / "generic_neutral_mesh.obj"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "26719 vertices" in r.stdout and "84 of 84" in r.stdout and "IRISD0" in r.stdout
    r = _cli("faces", "default:2k", "--json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    info = __import__("json").loads(r.stdout)
    assert (
        info["feature_points"] == 84 and info["fapu_mm"]["MW0"] > 20 and info["parts"]["tongue"] > 0
    )


def test_failed_writes_leave_nothing_and_keep_the_old_file(tmp_path, small_face):
    target = tmp_path / "x.glb"
    target.write_bytes(b"old")
    with pytest.raises(ValueError):  # noqa: PT012 - the failure is inside the atomic write
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise ValueError("boom")
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["x.glb"]
    bad = np.full((2, small_face.n_vertices, 3), np.nan, np.float32)
    with pytest.raises(ValueError, match="NaN"):
        encode_glb(bad, small_face.vertices, small_face.triangles, 25)
    with pytest.raises(InputError, match="input file not found"):
        render_file(tmp_path / "missing.fap", tmp_path / "y.glb", face=small_face)
    assert not (tmp_path / "y.glb").exists()


def test_glb_basis_is_exact_for_a_short_clip_and_bounded_for_a_long_one(small_face, rng):
    V = small_face.n_vertices
    T = 5
    frames = small_face.vertices + rng.normal(0, 1.0, (T, V, 3)).astype(np.float32)
    _, rec = encode_glb(frames, small_face.vertices, small_face.triangles, 10, tolerance_mm=0.01)
    assert rec["targets"] == T and rec["max_error_mm"] < 0.01
    # 120 frames of a 3-dimensional motion: 3 targets suffice.
    basis = rng.normal(0, 1.0, (3, V, 3)).astype(np.float32)
    w = np.sin(np.arange(120)[:, None] * np.array([0.05, 0.11, 0.23]))
    frames = small_face.vertices + np.einsum("tm,mvc->tvc", w, basis).astype(np.float32)
    _data, rec = encode_glb(
        frames, small_face.vertices, small_face.triangles, 30, tolerance_mm=0.01
    )
    assert rec["targets"] == 3 and rec["frames"] == 120 and rec["max_error_mm"] <= 0.01


def test_preview_pngs_of_joy_show_the_mouth_moving(data_dir, small_face, animator, artifacts):
    """Writes tests/artifacts/joy_frame_*.png for a person to look at; checks the mouth region changes."""
    from facecast.server.output.preview import render_image, write_png

    anim = load_fap(data_dir / "xface" / "faps" / "joy.fap", small_face)
    mouth = small_face.fp_position("2.2")
    images = []
    for t in (0, 24, 56):
        img = render_image(
            animator.frame(anim.states[t]),
            small_face.triangles,
            size=(160, 160),
            center=mouth,
            extent=80.0 / small_face.mm_per_unit,
        )
        write_png(artifacts / f"joy_frame_{t:03d}.png", img)
        images.append(img.astype(np.int16))
    assert np.abs(images[1] - images[0]).mean() > 1.0  # mouth open vs neutral
    assert (artifacts / "joy_frame_024.png").stat().st_size > 1000


@pytest.mark.opencl
def test_opencl_backend_renders_the_same_frames(data_dir, small_face, animator):
    from facecast.server.errors import FacecastError

    try:
        cl = Animator(small_face, backend="opencl", operator=animator.operator)
    except (FacecastError, ImportError) as e:
        pytest.skip(f"no OpenCL device: {e}")
    anim = load_fap(data_dir / "xface" / "faps" / "anger.fap", small_face)
    np.testing.assert_allclose(cl.render(anim), animator.render(anim), atol=1e-3)


@pytest.mark.slow
def test_cli_render_on_a_server(data_dir, server, tmp_path):
    env_key = {"FACECAST_ADMIN_KEY": server.admin_key}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "render",
            str(data_dir / "xface" / "faps" / "happy-for.fap"),
            "-o",
            "remote.glb",
            "--face",
            "default:2k",
            "--server",
            server.url,
        ],
        cwd=tmp_path,
        env={**os.environ, **env_key},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    glb = read_glb(tmp_path / "remote.glb")
    assert len(glb["times"]) == 107 and np.isfinite(frames_of(glb)).all()
    assert "HTTP Request" not in r.stderr
