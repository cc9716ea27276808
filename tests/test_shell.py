"""Linear-shell operator (Bickel et al.): constraints, energy, slits, rigid parts, both backends."""

from __future__ import annotations

import numpy as np
import pytest
from test_deform_fp import slit_mesh
from test_deform_rbf import bumpy, slit_grid

from facecast.server.deform.build import get_operator
from facecast.server.deform.shell import cotangent_laplacian, shell_matrix, shell_operator
from facecast.server.errors import InputError


@pytest.fixture(scope="module")
def grid():
    return slit_grid()


def test_cotangent_laplacian_of_a_plane():
    """Rows sum to 0, symmetric PSD, a linear function is harmonic inside, areas sum to the area."""
    verts, tris, _, _ = slit_mesh(n=9, slit=(4, 4))
    lap, mass = cotangent_laplacian(verts, tris)
    assert abs(lap - lap.T).max() < 1e-12
    np.testing.assert_allclose(np.asarray(lap.sum(axis=1)).ravel(), 0, atol=1e-12)
    assert np.linalg.eigvalsh(lap.toarray()).min() > -1e-9
    interior = np.flatnonzero(
        (verts[:, 0] > 0) & (verts[:, 0] < 8) & (verts[:, 1] > 0) & (verts[:, 1] < 8)
    )
    f = 2 * verts[:, 0] - 3 * verts[:, 1]
    np.testing.assert_allclose((lap @ f)[interior], 0, atol=1e-9)
    assert mass.sum() == pytest.approx(64.0)


@pytest.mark.parametrize("stretch", [0.0, 1.0, 100.0])
def test_reproduces_controls_and_zero(grid, rng, stretch):
    verts, tris, _, _, controls = grid
    op = shell_operator(verts, tris, controls, stretch=stretch)
    assert not op.is_sparse and op.dense.shape == (len(verts), len(controls))
    D = rng.normal(size=(len(controls), 3))
    np.testing.assert_allclose(op.apply(D)[controls], D, atol=1e-6)
    assert np.all(op.apply(np.zeros_like(D)) == 0)
    # a translation of every control moves everything with it (constants have zero energy)
    np.testing.assert_allclose(op.dense.sum(axis=1), 1.0, atol=1e-4)


def test_solution_minimises_the_energy(grid, rng):
    """u = B·D is the constrained minimum of uᵀAu: no perturbation of free vertices lowers it."""
    verts, tris, _, _, controls = grid
    stretch = 0.5
    op = shell_operator(verts, tris, controls, stretch=stretch)
    spacing = np.median(
        np.sort(np.linalg.norm(verts[controls][:, None] - verts[controls][None], axis=2), axis=1)[
            :, 1
        ]
    )
    a = shell_matrix(verts, tris, ks=stretch / spacing**2, kb=1.0)
    d = rng.normal(size=len(controls))
    u = op.dense.astype(np.float64) @ d
    energy = u @ (a @ u)
    free = np.setdiff1d(np.arange(len(verts)), controls)
    grad = (a @ u)[free]
    assert np.abs(grad).max() < 1e-4 * np.abs(a @ u).max()  # stationary on the free vertices
    for _ in range(5):
        p = np.zeros(len(verts))
        p[free] = rng.normal(scale=0.01, size=len(free))
        assert (u + p) @ (a @ (u + p)) > energy


def test_smooth_field_reproduced_with_dense_controls(rng):
    """A linear field sampled at controls spread over a plane is reproduced closely everywhere."""
    verts, tris, _, _ = slit_mesh(n=21, slit=(10, 10))
    n = 21
    vid = np.arange(n * n).reshape(n, n)
    controls = np.array([vid[y, x] for y in range(0, n, 4) for x in range(0, n, 4)])
    op = shell_operator(verts, tris, controls, stretch=0.0)
    A = rng.normal(scale=0.05, size=(3, 3))
    u = op.apply(verts[controls] @ A.T)
    want = verts @ A.T
    assert np.abs(u - want).max() < 0.05 * np.abs(want).max()


def test_slit_does_not_couple_the_lips(grid):
    """Only the lower lip's controls move: the upper lip stays (apart from near the corners)."""
    verts, tris, upper, lower, controls = grid
    lower_ctl = [i for i, c in enumerate(controls) if c in set(lower.tolist())]
    D = np.zeros((len(controls), 3))
    D[lower_ctl, 1] = -1.0
    u = shell_operator(verts, tris, controls).apply(D)
    inner = slice(4, -4)
    assert np.abs(u[lower[inner], 1]).min() > 0.5  # the lower lip opens
    assert np.abs(u[upper[inner]]).max() < 0.1
    # without the slit, the row just above the same lower-lip controls is dragged along
    v2, t2, _, _ = slit_mesh(slit=(15, 16))
    n = 31
    vid = np.arange(n * n).reshape(n, n)
    lower2 = vid[n // 2, np.arange(5, 26)]
    ctl2 = np.array([c if c < n * n else vid[n // 2 + 0, 0] for c in controls])
    ctl2 = np.r_[controls[:20], lower2[[2, 6, 10, 14, 18]]]
    D2 = np.zeros((len(ctl2), 3))
    D2[20:, 1] = -1.0
    u2 = shell_operator(bumpy(v2), t2, ctl2).apply(D2)
    above = vid[n // 2 + 1, np.arange(5, 26)][inner]
    assert np.abs(u2[above, 1]).max() > 0.5


def test_non_deformable_vertices_and_unconstrained_axes(grid, rng):
    verts, tris, _, _, controls = grid
    deformable = np.ones(len(verts), dtype=bool)
    deformable[:40] = False  # the first row and a bit: a rigid part
    deformable[controls] = True
    op = shell_operator(verts, tris, controls, deformable=deformable)
    assert np.all(op.dense[~deformable] == 0)
    constrained = np.ones((len(controls), 3), dtype=bool)
    constrained[0, 2] = False
    sp_op = shell_operator(verts, tris, controls, constrained=constrained)
    assert sp_op.is_sparse
    D = rng.normal(size=(len(controls), 3))
    u = sp_op.apply(D)
    np.testing.assert_allclose(u[controls[1:]], D[1:], atol=1e-5)
    np.testing.assert_allclose(u[controls[0], :2], D[0, :2], atol=1e-5)
    D2 = D.copy()
    D2[0, 2] += 5.0  # an unconstrained axis is ignored
    np.testing.assert_allclose(sp_op.apply(D2), u, atol=1e-5)


def test_bad_stretch_is_refused(grid):
    verts, tris, _, _, controls = grid
    with pytest.raises(InputError):
        shell_operator(verts, tris, controls, stretch=-1.0)


@pytest.fixture(scope="module")
def head():
    from facecast.server.faces import load_face
    from facecast.server.mpeg4 import fap_controls

    face = load_face("default:2k")
    _, vertex_ids, constrained = fap_controls(face, per_axis=True)
    assert not constrained.all()
    return face, vertex_ids, constrained


def test_builtin_head_rigid_parts_untouched_and_cached(head, rng):
    face, vertex_ids, _ = head
    op = get_operator(face, vertex_ids, engine="shell")
    again = get_operator(face, vertex_ids, engine="shell")
    assert np.array_equal(op.dense, again.dense)
    D = rng.normal(scale=0.5, size=(len(vertex_ids), 3))
    u = op.apply(D)
    assert np.all(u[~face.deformable] == 0)  # eyeballs and teeth follow their rigid groups only
    usable = face.deformable[vertex_ids]
    np.testing.assert_allclose(u[vertex_ids[usable]], D[usable], atol=1e-5)
    assert np.isfinite(u).all()
    with pytest.raises(InputError):
        get_operator(face, vertex_ids, engine="shell", nonsense=1)


@pytest.mark.opencl
def test_numpy_and_opencl_agree(head, rng):
    cl = pytest.importorskip("facecast.server.backends.opencl")
    from facecast.server.backends import NumpyDeformer

    ctx = cl.default_context()
    if ctx is None:
        pytest.skip("no working OpenCL device (install pocl-opencl-icd)")
    face, vertex_ids, constrained = head
    for cons in (None, constrained):  # dense, and sparse per-axis when the FAP axes differ
        op = get_operator(face, vertex_ids, engine="shell", constrained=cons)
        assert op.is_sparse == (cons is not None)
        ref = NumpyDeformer(face.vertices, face.triangles, face.rigid_group, op)
        dev = cl.OpenCLDeformer(face.vertices, face.triangles, face.rigid_group, op, context=ctx)
        D = rng.normal(scale=0.3, size=(len(vertex_ids), 3)).astype(np.float32)
        T = np.tile(np.eye(3, 4, dtype=np.float32), (4, 1, 1))
        T[1, :, 3] = [0.0, -0.5, 0.2]
        scale = float(np.abs(face.vertices).max())
        np.testing.assert_allclose(
            dev.deform(D, T), ref.deform(D, T), rtol=0, atol=scale * 2e-6 + 1e-5
        )


@pytest.mark.slow
def test_ict_lips_are_not_coupled_across_the_slit(data_dir):
    """On the ICT head only the lower lip's markers move: the upper lip stays, the socket follows."""
    from facecast.server.faces import load_face
    from facecast.server.mpeg4 import fap_controls

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    fps, vertex_ids, _ = fap_controls(face)
    op = get_operator(face, vertex_ids, engine="shell")
    lower = [
        i
        for i, f in enumerate(fps)
        if set(f.split("+")) & {"8.2", "8.7", "8.8", "2.3", "2.8", "2.9"}
    ]
    D = np.zeros((len(vertex_ids), 3), np.float32)
    D[lower, 1] = -1.0 / face.mm_per_unit  # 1 mm down
    u = op.apply(D) * face.mm_per_unit
    v = face.vertices
    mouth = (face.fp_position("8.1") + face.fp_position("8.2")) / 2
    width = np.linalg.norm(face.fp_position("8.3") - face.fp_position("8.4"))
    skin = face.part("skin")
    lips = skin[
        (np.abs(v[skin, 0] - mouth[0]) < 0.25 * width)
        & (np.abs(v[skin, 1] - mouth[1]) < 0.3 * width)
        & (v[skin, 2] > mouth[2] - 0.3 * width)
    ]
    upper, below = (
        lips[v[lips, 1] > face.fp_position("2.2")[1]],
        lips[v[lips, 1] < face.fp_position("2.3")[1]],
    )
    assert len(upper) > 20 and len(below) > 20
    assert np.abs(u[upper]).max() < 0.1
    assert -u[below, 1].mean() > 0.5
    assert np.all(u[~face.deformable] == 0)
