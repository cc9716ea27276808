"""End to end: a mocap take rendered by ``facecast render`` onto the ICT head (.fap and .npz)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecast.protocol.fap_file import read_fap
from facecast.server.cli import main
from facecast.server.mocap.io import write_take
from facecast.server.mocap.stabilise import euler_from_matrix
from facecast.server.mocap.synthetic import synthetic_take


@pytest.fixture(scope="module")
def ict_take(tmp_path_factory):
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data

    d = shared_data()
    if d is None or not (d / "ict-facekit").is_dir():
        pytest.skip("../shared/data/ict-facekit is not beside this checkout")
    mesh = d / "ict-facekit" / "generic_neutral_mesh.obj"
    face = load_face(mesh)
    syn = synthetic_take(
        face,
        n_markers=24,
        seconds=1.0,
        fps=60.0,
        seed=5,
        noise_mm=0.1,
        fp_markers=("2.1", "8.3", "8.4"),
    )
    folder = tmp_path_factory.mktemp("mocap")
    write_take(syn.take, folder / "take.c3d")
    (folder / "layout.json").write_text(json.dumps(syn.layout))
    return face, mesh, syn, folder


def render_take(folder, mesh, out, *extra: str) -> int:
    """``facecast render take.c3d --layout layout.json --face MESH -o OUT [extra]``; its exit status."""
    take, layout = folder / "take.c3d", folder / "layout.json"
    return main(
        ["render", str(take), "--layout", str(layout), "--face", str(mesh), *extra, "-o", str(out)]
    )


def test_render_take_to_fap_gives_jaw_and_head_faps(ict_take):
    from facecast.server.mpeg4.fapu import measure_fapu

    face, mesh, syn, folder = ict_take
    out = folder / "out.fap"
    assert render_take(folder, mesh, out) == 0
    fap = read_fap(out.read_text(), where=str(out))
    assert len(fap.frames) == len(syn.take.xyz)
    faps = [f.faps() for f in fap.frames]
    fapu = measure_fapu(face)
    chin = syn.take.names.index("FP2_1")
    drop = -(syn.local[:, chin, 1] - syn.local[0, chin, 1]) / face.mm_per_unit / fapu["MNS"]
    got3 = np.array([f.get(3, 0) for f in faps], dtype=float)
    assert drop.max() > 100  # the take opens the jaw
    np.testing.assert_allclose(got3, np.maximum(drop, 0), atol=0.08 * drop.max())
    yaw = euler_from_matrix(syn.head_r)[:, 1] / 1e-5
    got49 = np.array([f.get(49, 0) for f in faps], dtype=float)
    assert np.abs(yaw).max() > 2000
    np.testing.assert_allclose(got49, yaw, atol=0.05 * np.abs(yaw).max())
    # mouth corners (8.3/8.4) are projected to their stretch FAPs (6/7 or 53/54)
    assert any(f.get(53, 0) or f.get(6, 0) for f in faps)


@pytest.mark.parametrize("engine", ["fp", "shell"])
def test_render_take_to_npz_puts_the_markers_where_they_were(ict_take, engine):
    face, mesh, syn, folder = ict_take
    out = folder / f"out-{engine}.npz"
    assert render_take(folder, mesh, out, "--backend", "numpy", "--engine", engine) == 0
    with np.load(out) as z:
        verts = z["vertices"]
    assert verts.shape == (len(syn.take.xyz), face.n_vertices, 3)
    # the marker vertices of the rendered face follow the captured markers (head motion included)
    got = verts[:, syn.vertices] * face.mm_per_unit
    err = np.linalg.norm(got - syn.clean, axis=2)
    moved = np.linalg.norm(syn.clean - syn.clean[0], axis=2)
    assert moved.max() > 10.0
    assert np.median(err) < 0.5 and err.max() < 2.5


def test_render_without_a_layout_is_refused(ict_take, capsys):
    _, mesh, syn, folder = ict_take
    alone = folder / "alone"
    alone.mkdir(exist_ok=True)
    write_take(syn.take, alone / "take.trc")
    assert (
        main(["render", str(alone / "take.trc"), "--face", str(mesh), "-o", str(alone / "o.fap")])
        == 2
    )
    assert "needs a marker layout" in capsys.readouterr().err


@pytest.mark.slow
def test_generated_take_round_trips_through_the_driver(ict_take, tmp_path):
    from facecast.server.mocap.driver import load
    from facecast.server.mocap.generate import generate, load_expressions, load_truth

    face = ict_take[0]
    paths = generate(tmp_path, n_markers=40, seconds=3.0, fps=120.0, seed=2)
    truth = load_truth(paths["truth"])
    assert len(truth.stable) >= 4
    anim = load(paths["c3d"], face)  # finds take.layout.json beside the take
    assert len(anim) == len(truth.weights) and anim.fps == 120.0
    _, deltas = load_expressions(face)
    d_true = (
        np.einsum("te,emc->tmc", truth.weights, deltas[:, anim.control_vertices]) * face.mm_per_unit
    )
    d = np.stack([s.controls for s in anim.states]) * face.mm_per_unit
    err = np.linalg.norm(d - d_true, axis=2)
    size = np.linalg.norm(d_true, axis=2)
    assert err.mean() < 0.8  # mm, with 0.5 mm capture noise, gaps, spikes and head motion
    assert (size > 2.0).sum() > 100
    assert err[size > 2.0].mean() < 0.3 * size[size > 2.0].mean()
    trc = load(paths["trc"], face, layout=paths["layout"])
    np.testing.assert_allclose(
        np.stack([s.controls for s in trc.states]), d / face.mm_per_unit, atol=1e-3
    )
