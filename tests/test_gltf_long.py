"""glTF morph basis on long clips: the recorded error bound holds on re-import (pygltflib), long clips
stream through ``render_file`` in chunks, and a capped basis says so."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from test_render import XFACE, frames_of, read_glb

from facecast.server import render
from facecast.server.drivers.fap import load as load_fap
from facecast.server.output.fap import write_fap_file
from facecast.server.output.gltf import OutputError, encode_glb, morph_basis, write_glb
from facecast.server.pipeline import Animator
from facecast.server.render import render_file
from facecast.server.state import Animation


@pytest.fixture(scope="module")
def face():
    from facecast.server.faces import load_face

    return load_face("default:2k")


@pytest.fixture(scope="module")
def animator(face):
    return Animator(face, backend="numpy")


def looped(data_dir, n_frames: int) -> Animation:
    """The five XFace FAP files played one after the other, looped to ``n_frames`` frames at 25 fps."""
    clips = [load_fap(data_dir / "xface" / "faps" / name, None) for name in XFACE]
    states = []
    while len(states) < n_frames:
        for clip in clips:
            states.extend(clip.states)
    return Animation(
        25.0, [replace(s, t=i / 25.0) for i, s in enumerate(states[:n_frames])], source="looped"
    )


def reimported_error_mm(path, expected: np.ndarray, mm_per_unit: float) -> tuple[dict, float]:
    glb = read_glb(path)
    shown = frames_of(glb).astype(np.float64)
    return glb, float(np.linalg.norm(shown - expected, axis=2).max()) * mm_per_unit


@pytest.mark.slow
def test_long_clip_streams_through_render_file_within_the_recorded_bound(
    data_dir, face, animator, tmp_path, monkeypatch
):
    """3000 frames (2 minutes) rendered in chunks on each pass (not held in memory) -> .glb whose frames,
    rebuilt from the morph targets and weights, match the animator's frames within the recorded bound."""
    anim = looped(data_dir, 3000)
    src = tmp_path / "long.fap"
    write_fap_file(src, anim)
    monkeypatch.setattr(
        render, "GLB_STREAM_BYTES", 1 << 20
    )  # force the chunked path (3000 x 2k frames: 72 MB)
    calls = []
    summary = render_file(
        src,
        tmp_path / "long.glb",
        face=face,
        backend="numpy",
        progress=lambda d, t: calls.append((d, t)),
    )
    assert calls[-1] == (3000, 3000) and len(calls) == len(set(calls))  # one pass reported, once
    assert calls[0] == (
        64,
        3000,
    )  # in the streaming source's chunks (Animator.render reports every 32)
    expected = animator.render(load_fap(src, face))
    glb, err_mm = reimported_error_mm(tmp_path / "long.glb", expected, face.mm_per_unit)
    rec = glb["extras"]
    assert rec == summary["gltf"] and rec["frames"] == 3000 and len(glb["times"]) == 3000
    assert not rec["capped"] and rec["max_error_mm"] <= rec["tolerance_mm"] == 0.01
    assert err_mm <= rec["error_bound_mm"] + 1e-4  # float32 re-evaluation of the same sum
    assert (
        abs(err_mm - rec["max_error_mm"]) <= 1e-4
    )  # the record is the measured maximum, not a guess
    assert 1 <= rec["targets"] < 128 and np.abs(glb["weights"]).max() <= 1.0 + 1e-6
    # The same frames held in memory give an equally good basis of about the same size.
    _, mem = encode_glb(expected, face.vertices, face.triangles, 25.0, mm_per_unit=face.mm_per_unit)
    assert mem["max_error_mm"] <= 0.01 and abs(mem["targets"] - rec["targets"]) <= max(
        3, rec["targets"] // 10
    )


@pytest.mark.parametrize("name", ["anger.fap", "joy.fap"])
def test_recorded_bound_holds_on_reimport_of_a_real_clip(data_dir, face, animator, tmp_path, name):
    src = data_dir / "xface" / "faps" / name
    render_file(src, tmp_path / "a.glb", face=face, backend="numpy")
    glb, err_mm = reimported_error_mm(
        tmp_path / "a.glb", animator.render(load_fap(src, face)), face.mm_per_unit
    )
    rec = glb["extras"]
    assert err_mm <= rec["error_bound_mm"] + 1e-4 and rec["error_bound_mm"] <= 0.01
    assert abs(err_mm - rec["max_error_mm"]) <= 1e-4
    assert rec["passes"] >= 2 and not rec["capped"]


def test_chunk_source_equals_array_input(face, rng):
    """A callable yielding chunks (any sizes) gives the same basis as the array; a source that yields a
    different clip on its second pass is refused."""
    V = face.n_vertices
    basis = rng.normal(0, 1.0, (5, V, 3)).astype(np.float32)
    w = np.sin(np.arange(700)[:, None] * np.array([0.01, 0.03, 0.07, 0.13, 0.31]))
    frames = face.vertices + np.einsum("tm,mvc->tvc", w, basis).astype(np.float32)
    a = morph_basis(frames, face.vertices, 0.01, chunk=100)
    b = morph_basis(lambda: (frames[s : s + 100] for s in range(0, 700, 100)), face.vertices, 0.01)
    assert a.targets.shape == b.targets.shape == (5, V, 3)
    np.testing.assert_array_equal(a.weights, b.weights)
    assert a.max_error == b.max_error <= 0.01 and a.passes == 2
    calls = []

    def shrinking():
        calls.append(1)
        n = 700 if len(calls) == 1 else 600
        return (frames[s : min(s + 100, n)] for s in range(0, n, 100))

    with pytest.raises(ValueError, match="second pass"):
        morph_basis(shrinking, face.vertices, 0.01)


def test_a_basis_that_misses_the_tolerance_is_refused_not_written(face, rng, caplog, tmp_path):
    """Noise needs as many targets as frames: with a cap of 4 the encoder refuses (OutputError naming
    the size, the tolerance, the error and what to do; no file), and the capped basis it found
    reports its measured error."""
    T, V = 40, face.n_vertices
    frames = face.vertices + rng.normal(0, 0.5, (T, V, 3)).astype(np.float32)
    out = tmp_path / "noise.glb"
    with caplog.at_level(logging.WARNING, logger="facecast.server.output.gltf"):
        with pytest.raises(OutputError) as e:
            write_glb(out, frames, face.vertices, face.triangles, 25.0, max_targets=4)
    msg = str(e.value)
    assert str(out) in msg and f"{T} frames of a {V:,}-vertex face" in msg and "0.01 mm" in msg
    assert "more than 4 morph targets" in msg and ".npz" in msg and "smaller --face" in msg
    assert not out.exists() and not list(tmp_path.iterdir())
    assert any("capped at 4 targets" in r.getMessage() for r in caplog.records)
    mb = morph_basis(frames, face.vertices, 0.01, max_targets=4)
    assert mb.capped and mb.targets.shape[0] == 4 and mb.max_error > 0.01
    rebuilt = face.vertices + np.einsum("tm,mvc->tvc", mb.weights.astype(np.float64), mb.targets)
    assert np.linalg.norm(rebuilt - frames, axis=2).max() == pytest.approx(mb.max_error, rel=1e-9)
    # Uncapped, the same clip is exact with one target per frame.
    _, rec = encode_glb(frames, face.vertices, face.triangles, 25.0)
    assert not rec["capped"] and rec["targets"] == T and rec["max_error_mm"] <= 0.01


def test_exact_per_frame_targets_when_the_decomposition_falls_short(face, rng):
    """A clip of no more frames than the cap always has a verified file: one target per frame."""
    T = 6
    frames = face.vertices + rng.normal(0, 0.5, (T, face.n_vertices, 3)).astype(np.float32)
    # a first basis far too coarse (per-vertex slack 100 mm) and no second round: the decomposition misses
    mb = morph_basis(frames, face.vertices, 0.01, max_targets=8, basis_slack=1e4, rounds=1)
    assert (
        mb.method == "exact" and not mb.capped and mb.targets.shape[0] == T and mb.max_error < 1e-4
    )
    rebuilt = face.vertices + np.einsum("tm,mvc->tvc", mb.weights.astype(np.float64), mb.targets)
    assert np.linalg.norm(rebuilt - frames, axis=2).max() == pytest.approx(mb.max_error, rel=1e-9)
    np.testing.assert_array_equal(mb.weights, np.eye(T))


def test_still_clip_gives_one_zero_target(face):
    frames = np.repeat(face.vertices[None], 30, axis=0)
    _, rec = encode_glb(frames, face.vertices, face.triangles, 25.0)
    assert rec["targets"] == 1 and rec["max_error_mm"] == 0.0 and not rec["capped"]


def test_target_count_grows_until_the_measured_bound_holds(data_dir, face, animator):
    """A coarse first basis (per-frame slack 30x the tolerance) is not enough: the encoder measures,
    gathers finer directions and passes over the frames again until every vertex is within 0.01 mm."""
    frames = animator.render(load_fap(data_dir / "xface" / "faps" / "anger.fap", face))
    coarse = morph_basis(frames, face.vertices, 0.01, basis_slack=30.0)
    assert coarse.passes > 2 and not coarse.capped and coarse.max_error <= 0.01
    rebuilt = face.vertices + np.einsum(
        "tm,mvc->tvc", coarse.weights.astype(np.float64), coarse.targets
    )
    assert np.linalg.norm(rebuilt - frames, axis=2).max() == pytest.approx(
        coarse.max_error, rel=1e-9
    )
