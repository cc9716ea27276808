"""RBF warp operator: interpolation, affine exactness, constraints, and bleeding across a slit."""

from __future__ import annotations

import numpy as np
import pytest
from test_deform_fp import slit_mesh

from facecast.server.deform.build import get_operator
from facecast.server.deform.rbf import rbf_matrix, rbf_operator
from facecast.server.errors import InputError
from facecast.server.faces.face import Face


def bumpy(verts: np.ndarray) -> np.ndarray:
    """Lift the flat slit grid into 3-D (so an affine map is not degenerate)."""
    v = verts.copy()
    v[:, 2] = 0.1 * (v[:, 0] - 15) ** 2 / 15 + 0.05 * v[:, 1]
    return v


def slit_grid():
    """``(verts, tris, upper, lower, controls)``: the bumpy slit grid and controls round and on the lips."""
    verts, tris, upper, lower = slit_mesh()
    n = 31
    vid = np.arange(n * n).reshape(n, n)
    lips = [2, 6, 10, 14, 18]
    controls = np.array(
        [vid[y, x] for y in (3, 9, 21, 27) for x in (3, 9, 15, 21, 27)]
        + [lower[i] for i in lips]
        + [upper[i] for i in lips]
    )
    return bumpy(verts), tris, upper, lower, controls


@pytest.fixture(scope="module")
def grid():
    return slit_grid()


CASES = [
    {"kernel": "imq", "distance": "euclidean"},
    {"kernel": "imq", "distance": "surface"},
    {"kernel": "r", "distance": "euclidean"},
    {"kernel": "imq", "distance": "euclidean", "affine": False},
]


@pytest.mark.parametrize("params", CASES)
def test_reproduces_control_displacements(grid, rng, params):
    verts, tris, upper, _, controls = grid
    if params["distance"] == "euclidean":  # the lips' controls coincide in space: keep one lip
        controls = controls[~np.isin(controls, upper)]
    op = rbf_operator(verts, tris, controls, **params)
    assert not op.is_sparse and op.dense.shape == (len(verts), len(controls))
    D = rng.normal(size=(len(controls), 3))
    np.testing.assert_allclose(op.apply(D)[controls], D, atol=2e-4)
    assert np.all(op.apply(np.zeros_like(D)) == 0)


@pytest.mark.parametrize("params", CASES[:3])
def test_reproduces_an_affine_motion(grid, rng, params):
    verts, tris, _, _, controls = grid
    op = rbf_operator(
        verts, tris, controls, affine=True, **{k: v for k, v in params.items() if k != "affine"}
    )
    A = np.eye(3) * 0.02 + rng.normal(scale=0.02, size=(3, 3))
    b = rng.normal(size=3)
    D = verts[controls] @ A.T + b
    want = verts @ A.T + b
    np.testing.assert_allclose(op.apply(D), want, atol=2e-3 * np.abs(want).max())


def test_planar_controls_still_reproduce_affine_motion(rng):
    verts, _, _, _ = slit_mesh(n=12, slit=(3, 8))
    controls = np.arange(0, len(verts), 7)
    B = rbf_matrix(verts, verts[controls], kernel="r")
    A = rng.normal(scale=0.1, size=(3, 3))
    A[:, 2] = 0  # flat mesh: z is constant, so only the in-plane part is determined
    D = verts[controls] @ A.T + 1.0
    np.testing.assert_allclose(B @ D, verts @ A.T + 1.0, atol=1e-3)


def test_per_axis_constraints_make_a_sparse_operator(grid, rng):
    verts, tris, _, _, controls = grid
    constrained = np.ones((len(controls), 3), bool)
    constrained[::3, 0] = False
    op = rbf_operator(verts, tris, controls, constrained=constrained, distance="surface")
    assert op.is_sparse
    D = rng.normal(size=(len(controls), 3)).astype(np.float32)
    u = op.apply(D)
    np.testing.assert_allclose(u[controls][constrained], D[constrained], atol=2e-4)
    D2 = D.copy()
    D2[::3, 0] += 10  # unconstrained values are ignored
    np.testing.assert_allclose(op.apply(D2), u, atol=1e-5)


def test_coincident_centres_share_their_displacement(grid, rng):
    verts, tris, upper, lower, controls = grid
    op = rbf_operator(verts, tris, controls, distance="euclidean")
    D = rng.normal(size=(len(controls), 3))
    u = op.apply(D)
    i_lo, i_up = (np.flatnonzero(controls == lower[2])[0], np.flatnonzero(controls == upper[2])[0])
    np.testing.assert_allclose(u[lower[2]], (D[i_lo] + D[i_up]) / 2, atol=2e-4)
    # surface distance keeps them apart, so each lip follows its own control
    u = rbf_operator(verts, tris, controls, distance="surface").apply(D)
    np.testing.assert_allclose(u[[lower[2], upper[2]]], D[[i_lo, i_up]], atol=2e-4)


def test_surface_distance_stops_bleeding_across_the_slit(grid):
    """Both lips carry controls (as a face's FPs do); only the lower lip's move."""
    verts, tris, upper, lower, controls = grid
    lower_ctl = [i for i, c in enumerate(controls) if c in set(lower.tolist())]
    D = np.zeros((len(controls), 3))
    D[lower_ctl, 1] = -1.0
    inner = slice(6, -6)
    bleed = {}
    for distance in ("euclidean", "surface"):
        u = rbf_operator(verts, tris, controls, distance=distance, affine=False).apply(D)
        bleed[distance] = np.abs(u[upper[inner]]).max()
        if distance == "surface":
            assert np.abs(u[lower[inner], 1]).min() > 0.9  # the lower lip opens
    # Euclidean: the upper lip sits at distance 0 from the lower lip and is dragged along
    assert bleed["euclidean"] > 0.3
    assert bleed["surface"] < 0.1 * bleed["euclidean"]


def test_non_deformable_vertices_do_not_move(grid, rng):
    verts, tris, _, _, controls = grid
    deformable = np.ones(len(verts), bool)
    deformable[:40] = False
    controls = controls[~np.isin(controls, np.arange(40))]
    op = rbf_operator(verts, tris, controls, deformable=deformable)
    assert np.all(op.dense[:40] == 0)


def test_bad_parameters_are_input_errors(grid):
    verts, tris, _, _, controls = grid
    with pytest.raises(InputError):
        rbf_operator(verts, tris, controls, kernel="gauss")
    with pytest.raises(InputError):
        rbf_operator(verts, tris, controls, kernel="r", distance="surface")


def test_get_operator_caches_dense_operators(grid, tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAST_CACHE", str(tmp_path))
    verts, tris, _, _, controls = grid
    face = Face("slit", verts, tris)
    a = get_operator(face, controls, engine="rbf")
    b = get_operator(face, controls, engine="rbf")
    assert not b.is_sparse and np.array_equal(a.dense, b.dense)
    get_operator(face, controls, engine="rbf", kernel="r", distance="euclidean")
    assert len(list((tmp_path / "operators").glob("*.npz"))) == 2
