"""Feature-point deformation operator (Kshirsagar et al.) and the operator cache, on small synthetic meshes."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.server.deform.build import get_operator
from facecast.server.deform.feature_point import feature_point_operator
from facecast.server.deform.mesh_graph import edge_graph, voronoi
from facecast.server.deform.operator import Operator
from facecast.server.errors import InputError
from facecast.server.faces import load_face
from facecast.server.faces.face import Face


def slit_mesh(n: int = 31, slit: tuple[int, int] = (4, 26)):
    """A flat ``n x n`` grid (unit spacing, z = 0) cut along row ``n // 2`` between columns ``slit``.

    The cut's interior vertices are duplicated: the cells above the cut use the copies, so the two
    "lips" meet only at the slit's corners. Returns ``(vertices, triangles, upper_lip, lower_lip)``
    where the lips are the vertex ids directly above / below the cut's interior.
    """
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    verts = np.c_[xs.ravel(), ys.ravel(), np.zeros(n * n)]
    vid = np.arange(n * n).reshape(n, n)  # [row y, col x]
    mid = n // 2
    cut_cols = np.arange(slit[0] + 1, slit[1])
    copies = np.arange(n * n, n * n + len(cut_cols))
    verts = np.r_[verts, verts[vid[mid, cut_cols]]]
    above = vid.copy()
    above[mid, cut_cols] = copies
    tris = []
    for y in range(n - 1):
        ids = above if y == mid else vid  # cells whose lower edge is the cut row use the copies
        for x in range(n - 1):
            a, b = ids[y, x], ids[y, x + 1]
            c, d = vid[y + 1, x], vid[y + 1, x + 1]
            tris += [[a, b, d], [a, d, c]]
    upper = copies  # the upper lip's edge (on the cut row, owned by the cells above)
    lower = vid[mid, cut_cols]
    return verts, np.array(tris), upper, lower


@pytest.fixture(scope="module")
def grid():
    verts, tris, upper, lower = slit_mesh()
    n = 31
    vid = np.arange(n * n).reshape(n, n)
    lips = [2, 6, 10, 14, 18]  # every 4th vertex along the 21-vertex slit, on both lips
    controls = np.array(
        [vid[y, x] for y in (3, 9, 21, 27) for x in (3, 9, 15, 21, 27)]
        + [lower[i] for i in lips]
        + [upper[i] for i in lips]
    )
    return verts, tris, upper, lower, controls


def random_D(rng, k):
    return rng.normal(size=(k, 3)).astype(np.float32)


@pytest.mark.parametrize("norm", ["paper", "slides", "clamped", "none"])
def test_zero_displacement_gives_zero_motion(grid, norm):
    verts, tris, _, _, controls = grid
    op = feature_point_operator(verts, tris, controls, normalisation=norm)
    assert op.is_sparse and op.nnz > len(controls)
    assert np.all(op.apply(np.zeros((len(controls), 3))) == 0)


@pytest.mark.parametrize("norm", ["paper", "slides", "clamped", "none"])
def test_control_vertex_follows_its_displacement_on_constrained_axes(grid, rng, norm):
    verts, tris, _, _, controls = grid
    constrained = rng.random((len(controls), 3)) < 0.7
    constrained[:, 1] = True
    op = feature_point_operator(verts, tris, controls, constrained=constrained, normalisation=norm)
    D = random_D(rng, len(controls))
    u = op.apply(D)
    got = u[controls]
    np.testing.assert_allclose(got[constrained], D[constrained], rtol=1e-5, atol=1e-6)


def test_unconstrained_axis_moves_like_an_ordinary_vertex(grid):
    verts, tris, _, _, controls = grid
    constrained = np.ones((len(controls), 3), bool)
    free = 6  # a control in the middle of the grid, free on x
    constrained[free, 0] = False
    op = feature_point_operator(
        verts, tris, controls, constrained=constrained, normalisation="slides"
    )
    D = np.zeros((len(controls), 3), np.float32)
    D[:, 0] = 1.0  # every constrained control moves +x
    D[free, 0] = -5.0  # ignored on x: the control is not an FP there
    u = op.apply(D)
    assert u[controls[free], 0] == pytest.approx(1.0, abs=1e-5)
    # ... and its x column is empty
    assert np.all(op.weights[op.indices == free, 0] == 0)


@pytest.mark.parametrize("norm", ["paper", "slides"])
def test_normalised_weights_sum_to_one_where_reached(grid, norm):
    verts, tris, _, _, controls = grid
    op = feature_point_operator(verts, tris, controls, normalisation=norm)
    rows = np.repeat(np.arange(op.n_vertices), np.diff(op.indptr))
    for a in range(3):
        total = np.bincount(rows, weights=op.weights[:, a], minlength=op.n_vertices)
        reached = np.diff(op.indptr) > 0
        assert reached.sum() > 0.5 * op.n_vertices
        np.testing.assert_allclose(total[reached], 1.0, rtol=1e-5)
    assert np.all(op.weights >= 0)


def test_clamped_weights_never_sum_above_one(grid):
    verts, tris, _, _, controls = grid
    op = feature_point_operator(verts, tris, controls, normalisation="clamped")
    rows = np.repeat(np.arange(op.n_vertices), np.diff(op.indptr))
    total = np.bincount(rows, weights=op.weights[:, 1], minlength=op.n_vertices)
    assert total.max() <= 1 + 1e-5
    assert np.isclose(total, 1, atol=1e-5).sum() > 0.3 * op.n_vertices  # where FPs overlap
    assert ((total > 0.01) & (total < 0.99)).sum() > 10  # where a lone FP fades out


@pytest.mark.parametrize("norm", ["slides", "clamped"])
def test_rim_rule_cap_reaches_beyond_the_outer_controls(grid, norm):
    """The grid's corner (0, 0) lies beyond the corner control (3, 3), at 135° from both of its
    neighbours: "skip" (criterion (1) literally) leaves it still, "cap" lets that FP fade out there."""
    verts, tris, _, _, controls = grid
    skip = feature_point_operator(verts, tris, controls, normalisation=norm, no_neighbour="skip")
    cap = feature_point_operator(verts, tris, controls, normalisation=norm, no_neighbour="cap")
    D = np.zeros((len(controls), 3), np.float32)
    D[0] = 1.0  # the control at (3, 3)
    corner = 0  # vertex (0, 0)
    assert np.all(skip.apply(D)[corner] == 0)
    moved = cap.apply(D)[corner]
    assert np.all(moved > 0)
    if norm == "clamped":  # a lone FP's weight fades (with "slides" it is normalised back to 1)
        assert np.all(moved < 1)
    with pytest.raises(InputError):
        feature_point_operator(verts, tris, controls, no_neighbour="sometimes")


@pytest.mark.parametrize("norm", ["slides", "clamped"])
def test_own_blend_makes_the_control_vertex_blend_into_its_ring(grid, rng, norm):
    """Without it the exact control vertex can stick out of its 1-ring (others still weigh in)."""
    verts, tris, _, _, controls = grid
    D = random_D(rng, len(controls))
    ring = {c: np.unique(tris[(tris == c).any(axis=1)]) for c in controls}

    def jump(op):
        u = op.apply(D)
        return np.mean(
            [np.linalg.norm(u[ring[c]] - D[i], axis=1).mean() for i, c in enumerate(controls)]
        )

    plain = feature_point_operator(verts, tris, controls, normalisation=norm, own_blend=0)
    blended = feature_point_operator(verts, tris, controls, normalisation=norm, own_blend=0.5)
    assert jump(blended) < 0.7 * jump(plain)
    u = blended.apply(D)
    np.testing.assert_allclose(u[controls], D, rtol=1e-5, atol=1e-6)


def test_the_normalisations_differ(grid, rng):
    verts, tris, _, _, controls = grid
    D = random_D(rng, len(controls))
    u = {
        n: feature_point_operator(verts, tris, controls, normalisation=n).apply(D)
        for n in ("paper", "slides", "clamped", "none")
    }
    assert np.abs(u["paper"] - u["slides"]).max() > 1e-3
    assert np.abs(u["slides"] - u["clamped"]).max() > 1e-3
    assert np.abs(u["slides"] - u["none"]).max() > 1e-3


def test_locality(grid):
    """A control's influence ends within its largest neighbour distance; a lone control moves only itself."""
    verts, tris, _, _, controls = grid
    op = feature_point_operator(verts, tris, controls)
    g = edge_graph(verts, tris)
    vor = voronoi(g, controls)
    k = 0
    nb = np.r_[vor.pair_distance[vor.pairs[:, 0] == k], vor.pair_distance[vor.pairs[:, 1] == k]]
    from scipy.sparse.csgraph import dijkstra

    d = dijkstra(g, directed=False, indices=controls[k])
    touched = np.unique(np.repeat(np.arange(op.n_vertices), np.diff(op.indptr))[op.indices == k])
    assert len(touched) > 1
    assert d[touched].max() <= nb.max() + 1e-9
    lone = feature_point_operator(verts, tris, controls[:1])
    assert lone.nnz == 1 and lone.indptr[controls[0] + 1] - lone.indptr[controls[0]] == 1


@pytest.mark.parametrize("norm", ["paper", "slides", "clamped", "none"])
def test_no_bleeding_across_a_slit(grid, norm):
    verts, tris, upper, lower, controls = grid
    op = feature_point_operator(verts, tris, controls, normalisation=norm)
    lower_ctl = [i for i, c in enumerate(controls) if c in set(lower.tolist())]
    D = np.zeros((len(controls), 3), np.float32)
    D[lower_ctl, 1] = -1.0
    u = op.apply(D)
    inner = slice(6, -6)  # the middle of the mouth, far (around the corners) from the lower lip
    assert np.abs(u[lower[inner], 1]).max() > 0.3  # the lower lip opens
    assert np.all(u[upper[inner]] == 0)  # and the upper lip does not follow
    # the same geometry with Euclidean reach (no slit) would bleed: the lips sit at distance 0
    assert np.allclose(verts[upper], verts[lower])


def test_non_deformable_vertices_get_zero_rows_and_block_paths(grid, rng):
    verts, tris, _, _, controls = grid
    deformable = np.ones(len(verts), bool)
    n = 31
    eye = np.arange(n * n).reshape(n, n)[4:7, 18:21].ravel()  # an "eyeball" patch
    deformable[eye] = False
    op = feature_point_operator(verts, tris, controls, deformable=deformable)
    assert np.all(np.diff(op.indptr)[eye] == 0)
    assert np.all(op.apply(random_D(rng, len(controls)))[eye] == 0)


def test_paths_do_not_cross_rigid_groups(grid, rng):
    """A "jaw" band of the grid (its own rigid group) is neither moved by the others' controls nor moves them."""
    verts, tris, _, _, controls = grid
    group = (verts[:, 1] >= 20).astype(np.uint8)  # rows 20.. ride the "jaw"
    op = feature_point_operator(verts, tris, controls, rigid_group=group)
    jaw_ctl = group[controls] == 1
    D = np.zeros((len(controls), 3), np.float32)
    D[jaw_ctl] = rng.normal(size=(jaw_ctl.sum(), 3))
    u = op.apply(D)
    assert np.abs(u[group == 1]).max() > 0.1
    assert np.all(u[group == 0] == 0)
    D = np.zeros((len(controls), 3), np.float32)
    D[~jaw_ctl] = rng.normal(size=((~jaw_ctl).sum(), 3))
    assert np.all(op.apply(D)[group == 1] == 0)


def test_controls_on_non_deformable_vertices_are_ignored(grid, rng):
    verts, tris, _, _, controls = grid
    deformable = np.ones(len(verts), bool)
    deformable[controls[0]] = False  # e.g. an FP on an eyeball (3.5, the pupil)
    op = feature_point_operator(verts, tris, controls, deformable=deformable)
    assert not np.any(op.indices == 0)
    u = op.apply(random_D(rng, len(controls)))
    assert np.all(u[controls[0]] == 0)


def test_floating_component_copies_nearest_reached_vertex(grid):
    verts, tris, _, _, controls = grid
    n_before = len(verts)
    # an "eyelash": a small triangle hovering 0.5 above the grid next to control 6
    base = verts[controls[6]]
    lash = base + np.array([[0.1, 0.1, 0.5], [0.9, 0.1, 0.5], [0.1, 0.9, 0.5]])
    v2 = np.r_[verts, lash]
    t2 = np.r_[tris, [[n_before, n_before + 1, n_before + 2]]]
    op = feature_point_operator(v2, t2, controls, attach_distance=1.0)
    D = np.zeros((len(controls), 3), np.float32)
    D[6] = (0, 0, 1)
    u = op.apply(D)
    assert u[n_before, 2] == pytest.approx(1.0)  # nearest reached vertex is the control itself
    assert np.all(u[n_before:, 2] > 0)
    far = feature_point_operator(v2, t2, controls, attach_distance=0.1)
    assert np.all(np.diff(far.indptr)[n_before:] == 0)


def test_duplicate_controls_share_their_vertex(grid, rng):
    verts, tris, _, _, controls = grid
    ctl = np.r_[controls, controls[:1]]
    op = feature_point_operator(verts, tris, ctl)
    D = random_D(rng, len(ctl))
    u = op.apply(D)
    np.testing.assert_allclose(u[ctl[0]], (D[0] + D[-1]) / 2, rtol=1e-5, atol=1e-6)


def test_bad_input_is_an_input_error(grid):
    verts, tris, _, _, controls = grid
    with pytest.raises(InputError):
        feature_point_operator(verts, tris, [len(verts) + 5])
    with pytest.raises(InputError):
        feature_point_operator(verts, tris, controls, normalisation="eq5")
    with pytest.raises(InputError):
        feature_point_operator(verts, tris, controls, constrained=np.ones((2, 3), bool))


# -- get_operator and its disk cache ------------------------------------------------------------


@pytest.fixture
def face(grid):
    verts, tris, _, _, _ = grid
    return Face("slit", verts, tris, units="mm")


def _same(a: Operator, b: Operator) -> bool:
    return (
        (a.n_vertices, a.n_controls) == (b.n_vertices, b.n_controls)
        and np.array_equal(a.indptr, b.indptr)
        and np.array_equal(a.indices, b.indices)
        and np.array_equal(a.weights, b.weights)
    )


def test_cache_returns_an_equal_operator_and_is_keyed(face, grid, tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAST_CACHE", str(tmp_path))
    controls = grid[4]
    first = get_operator(face, controls, engine="fp")
    files = list((tmp_path / "operators").glob("*.npz"))
    assert len(files) == 1 and files[0].name.startswith(face.mesh_hash)
    stamp = files[0].stat().st_mtime_ns
    again = get_operator(face, controls, engine="fp")
    assert _same(first, again)
    assert files[0].stat().st_mtime_ns == stamp  # read, not rebuilt
    assert _same(first, get_operator(face, controls, engine="fp", cache=False))
    # every input that changes the result makes a new entry
    get_operator(face, controls, engine="fp", normalisation="none")
    get_operator(face, controls[:-1], engine="fp")
    c = np.ones((len(controls), 3), bool)
    c[0, 2] = False
    get_operator(face, controls, engine="fp", constrained=c)
    assert len(list((tmp_path / "operators").glob("*.npz"))) == 4
    other = Face("slit2", face.vertices * 2, face.triangles, units="mm")
    get_operator(other, controls, engine="fp")
    assert len(list((tmp_path / "operators").glob("*.npz"))) == 5
    assert not list((tmp_path / "operators").glob("*.tmp*"))


def test_corrupt_cache_file_is_rebuilt(face, grid, tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAST_CACHE", str(tmp_path))
    controls = grid[4]
    first = get_operator(face, controls)
    (path,) = (tmp_path / "operators").glob("*.npz")
    path.write_bytes(b"not an npz file")
    again = get_operator(face, controls)
    assert _same(first, again)
    assert Operator.load(path).nnz == first.nnz  # the file was replaced by a good one


def test_unwritable_cache_still_builds(face, grid, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("FACECAST_CACHE", str(blocker))  # cache_dir() cannot create folders here
    op = get_operator(face, grid[4])
    assert _same(op, get_operator(face, grid[4], cache=False))


def test_unknown_engine_or_parameter_is_an_input_error(face, grid):
    with pytest.raises(InputError):
        get_operator(face, grid[4], engine="ffd", cache=False)
    with pytest.raises(InputError):
        get_operator(face, grid[4], engine="fp", cache=False, kernel="imq")


# -- the real ICT FaceKit head --------------------------------------------------------------------

LOWER_LIP_FPS = ("2.3", "2.8", "2.9", "8.2", "8.7", "8.8")
UPPER_EYELID_FPS = ("3.1", "3.2", "3.13", "3.14")


def test_ict_lips_and_eyelids_do_not_bleed(data_dir):
    from scipy.sparse.csgraph import dijkstra

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    names = [k for k, v in face.feature_points.items() if face.deformable[v]]
    controls = np.array([face.feature_points[k] for k in names])
    op = get_operator(face, controls, engine="fp", cache=False)
    D = np.zeros((len(controls), 3), np.float32)
    D[[names.index(k) for k in LOWER_LIP_FPS], 1] = -0.5  # lower lip 5 mm down
    D[[names.index(k) for k in UPPER_EYELID_FPS], 1] = -0.5  # upper lids 5 mm down (a blink)
    u = np.linalg.norm(op.apply(D), axis=1)
    g = edge_graph(face.vertices, face.triangles, face.deformable)
    near_upper_lip = (
        dijkstra(g, directed=False, indices=face.feature_points["2.2"], limit=0.3) < 0.3
    )
    near_lower_lip = (
        dijkstra(g, directed=False, indices=face.feature_points["2.3"], limit=0.3) < 0.3
    )
    # the upper lip lies within a millimetre of the lower one (a closed mouth) ...
    gap = np.linalg.norm(face.fp_position("2.2") - face.fp_position("2.3"))
    assert gap < 0.2
    assert u[near_lower_lip].mean() > 0.3  # ... the lower lip moves ...
    assert np.all(u[near_upper_lip] == 0)  # ... and the upper lip stays
    eyes = np.r_[
        face.part("eye_l"), face.part("eye_r"), face.part("teeth_upper"), face.part("teeth_lower")
    ]
    assert len(eyes) > 1000 and np.all(u[eyes] == 0)  # eyelids do not pull the eyeballs
    assert (u > 0.4).sum() > 20  # lid and lip skin follow their controls


def test_bounded_distances_are_exact_and_chunking_does_not_matter(grid):
    from scipy.sparse.csgraph import dijkstra

    from facecast.server.deform.mesh_graph import bounded_distances

    verts, tris, _, _, controls = grid
    g = edge_graph(verts, tris)
    limits = np.linspace(1.0, 9.0, len(controls))
    whole = bounded_distances(g, controls, limits)
    chunked = bounded_distances(g, controls, limits, budget=1)  # one source per Dijkstra call
    full = dijkstra(g, directed=False, indices=controls)
    for (ids, d), (ids2, d2), row, lim in zip(whole, chunked, full, limits):
        assert np.array_equal(ids, ids2) and np.array_equal(d, d2)
        assert np.array_equal(ids, np.flatnonzero(row < lim))
        np.testing.assert_allclose(d, row[ids])


def test_no_controls_give_an_empty_operator(grid):
    from facecast.server.deform.rbf import rbf_operator

    verts, tris, _, _, _ = grid
    for build in (feature_point_operator, rbf_operator):
        op = build(verts, tris, np.zeros(0, int))
        assert op.n_controls == 0 and op.n_vertices == len(verts)
        assert np.all(op.apply(np.zeros((0, 3))) == 0)
