"""Quality of a deformed face: strain, creases (dihedral change), normal turn, flipped triangles and
mouth-socket poke-through, over the *outer skin* (the ``skin`` part without the socket parts).

- ``strain``: ``|edge length / rest length - 1|`` over outer-skin edges (tears, pinches);
- ``dihedral``: change of the dihedral angle of each interior outer-skin edge from the rest mesh,
  in degrees: creases (a sharp fold between two triangles) show up here first;
- ``normal``: angle between each outer-skin vertex normal and its rest normal, in degrees
  (includes the legitimate turning of the skin under an expression);
- ``flips``: outer-skin triangles whose normal turned by more than 90°;
- ``pokes``: mouth-socket vertices lying *outside* the outer skin. For each socket vertex at least
  2 edge rings away from the outer skin, the signed distance to the nearest of its ``K_NEAR``
  nearest rest outer-skin triangles that it lies behind at rest (not the inner lip surfaces, which
  face the socket) is measured along that triangle's outward normal; a vertex pokes through when
  it is more than ``POKE_TOL_MM`` outside. Only socket vertices inside the skin at rest are
  checked (ICT's socket rim lies within the lips), so at rest the count is 0.

Used by ``bench/deform_quality.py`` and the tests; positions are head-local (``rest + B·D``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .normals import face_normals, vertex_normals

#: How far outside the skin (mm) a socket vertex must be to count as poking through.
POKE_TOL_MM = 0.2
#: Candidate skin triangles per socket vertex (nearest by centroid in the rest pose).
K_NEAR = 24


def _sockets(face) -> np.ndarray:
    ids = [face.parts[p] for p in face.parts if "socket" in p]
    return np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)


def outer_skin_mask(face) -> np.ndarray:
    """``(V,) bool``: the ``skin`` part without socket parts (mouth, eyes)."""
    m = np.zeros(face.n_vertices, bool)
    m[face.parts["skin"]] = True
    m[_sockets(face)] = False
    return m


@dataclass
class QualityMesh:
    """Rest-pose data of the outer skin of a face, for ``measure``."""

    mm: float
    tri: np.ndarray  # (F, 3) outer-skin triangles
    edges: np.ndarray  # (E, 2)
    rest_len: np.ndarray  # (E,)
    hinge: np.ndarray  # (H, 2) triangle pairs sharing an interior edge
    rest_dihedral: np.ndarray  # (H,) radians
    verts: np.ndarray  # (S,) outer-skin vertices in some triangle
    rest_vn: np.ndarray  # (S, 3)
    rest_fn: np.ndarray  # (F, 3)
    socket: np.ndarray  # (P,) socket vertices checked for poke-through
    socket_cand: np.ndarray  # (P, K_NEAR) candidate triangle ids into tri

    @classmethod
    def of(cls, face) -> QualityMesh:
        skin = outer_skin_mask(face)
        tri = face.triangles[skin[face.triangles].all(axis=1)].astype(np.int64)
        rest = face.vertices.astype(np.float64)
        e = np.sort(np.r_[tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1)
        fid = np.tile(np.arange(len(tri)), 3)
        key = e[:, 0] * face.n_vertices + e[:, 1]
        order = np.argsort(key, kind="stable")
        key, fid = key[order], fid[order]
        uniq, start, count = np.unique(key, return_index=True, return_counts=True)
        two = count == 2
        hinge = np.stack([fid[start[two]], fid[start[two] + 1]], axis=1)
        edges = np.stack([uniq // face.n_vertices, uniq % face.n_vertices], axis=1)
        rest_len = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
        fn = face_normals(rest, tri)
        verts = np.unique(tri)
        vn = vertex_normals(rest, tri, face.n_vertices)[verts]
        # socket vertices >= 2 rings from the outer skin
        sock = _sockets(face)
        sock = sock[face.deformable[sock]] if len(sock) else sock
        near = skin.copy()
        for _ in range(2):
            a = face.triangles[near[face.triangles].any(axis=1)]
            near[a.ravel()] = True
        mouth = face.parts.get("mouth_socket", np.zeros(0, np.int64))
        sock = np.intersect1d(mouth, sock[~near[sock]])
        if len(sock):
            cent = rest[tri].mean(axis=1)
            _, cand = cKDTree(cent).query(rest[sock], k=min(K_NEAR, len(tri)))
            cand = np.atleast_2d(cand)
            # keep the triangles the vertex lies behind at rest (not the inner lips facing it)
            side = np.einsum("ikj,ikj->ik", rest[sock][:, None, :] - rest[tri[cand, 0]], fn[cand])
            cand = np.where(side < 0, cand, -1)
        else:
            cand = np.zeros((0, K_NEAR), np.int64)
        qm = cls(
            face.mm_per_unit,
            tri,
            edges,
            rest_len,
            hinge,
            _dihedral(fn, hinge),
            verts,
            vn,
            fn,
            sock,
            cand,
        )
        # only vertices inside the skin at rest are checked (ICT's socket rim sits inside the lips)
        inside = (socket_signed_mm(rest, qm) <= 0) & (cand >= 0).any(axis=1)
        qm.socket, qm.socket_cand = sock[inside], cand[inside]
        return qm


def _dihedral(fn: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    c = np.einsum("ij,ij->i", fn[hinge[:, 0]], fn[hinge[:, 1]])
    return np.arccos(np.clip(c, -1.0, 1.0))


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points to ``p (..., 3)`` on triangles ``a, b, c (..., 3)`` (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + ab * v[..., None] + ac * w[..., None]  # interior
        # edges
        t_ab = np.clip(np.where((ab * ab).sum(-1) > 0, d1 / (ab * ab).sum(-1), 0), 0, 1)
        t_ac = np.clip(np.where((ac * ac).sum(-1) > 0, d2 / (ac * ac).sum(-1), 0), 0, 1)
        bc = c - b
        t_bc = np.clip(
            np.where((bc * bc).sum(-1) > 0, (bc * bp).sum(-1) / (bc * bc).sum(-1), 0), 0, 1
        )
    q_ab = a + ab * t_ab[..., None]
    q_ac = a + ac * t_ac[..., None]
    q_bc = b + bc * t_bc[..., None]
    inside = (va >= 0) & (vb >= 0) & (vc >= 0)
    best = np.where(inside[..., None], out, q_ab)
    for q in (q_ab, q_ac, q_bc):
        closer = ((q - p) ** 2).sum(-1) < ((best - p) ** 2).sum(-1)
        best = np.where((closer & ~inside)[..., None], q, best)
    return best


def socket_signed_mm(points: np.ndarray, qm: QualityMesh) -> np.ndarray:
    """Signed distance (mm, + = outside) of the checked socket vertices to the nearby outer skin."""
    if not len(qm.socket):
        return np.zeros(0)
    p = points.astype(np.float64)
    tri = qm.tri[np.maximum(qm.socket_cand, 0)]  # (P, K, 3)
    a, b, c = p[tri[..., 0]], p[tri[..., 1]], p[tri[..., 2]]
    x = p[qm.socket][:, None, :]
    q = _closest_on_triangles(np.broadcast_to(x, a.shape), a, b, c)
    d2 = np.where(qm.socket_cand >= 0, ((q - x) ** 2).sum(-1), np.inf)
    k = d2.argmin(axis=1)
    rows = np.arange(len(k))
    n = np.cross(b - a, c - a)[rows, k]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    s = ((x[:, 0] - q[rows, k]) * n).sum(-1)
    return s * qm.mm


def measure(points: np.ndarray, qm: QualityMesh) -> dict:
    """Quality numbers of one deformed frame ``points (V, 3)`` (head-local)."""
    p = points.astype(np.float64)
    length = np.linalg.norm(p[qm.edges[:, 0]] - p[qm.edges[:, 1]], axis=1)
    strain = np.abs(length / np.maximum(qm.rest_len, 1e-30) - 1)
    fn = face_normals(p, qm.tri)
    dih = np.degrees(np.abs(_dihedral(fn, qm.hinge) - qm.rest_dihedral))
    vn = vertex_normals(p, qm.tri, len(p))[qm.verts]
    ndev = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", vn, qm.rest_vn), -1, 1)))
    flips = int((np.einsum("ij,ij->i", fn, qm.rest_fn) < 0).sum())
    sd = socket_signed_mm(p, qm)
    return {
        "strain_p99": float(np.percentile(strain, 99)),
        "strain_max": float(strain.max()),
        "dihedral_p90": float(np.percentile(dih, 90)),
        "dihedral_p99": float(np.percentile(dih, 99)),
        "dihedral_max": float(dih.max()),
        "normal_p99": float(np.percentile(ndev, 99)),
        "normal_max": float(ndev.max()),
        "flips": flips,
        "pokes": int((sd > POKE_TOL_MM).sum()),
        "poke_max_mm": float(sd.max()) if len(sd) else 0.0,
    }


def summarise(frames: list[dict]) -> dict:
    """Worst frame of each number (max over frames), plus the mean of the per-frame p99s."""
    out = {k: max(f[k] for f in frames) for k in frames[0]}
    for k in ("strain_p99", "dihedral_p99", "normal_p99"):
        out[k + "_mean"] = float(np.mean([f[k] for f in frames]))
    out["frames"] = len(frames)
    out["frames_with_pokes"] = int(sum(f["pokes"] > 0 for f in frames))
    return out
