"""Deformation quality: how smooth and artifact-free is the deformed skin?

Measured in head-local space (``rest + B·D``, the rigid head/jaw/eye transforms left out) over the
*outer skin*: the ``skin`` part without the mouth and eye sockets (the built-in head's skin
includes them; ICT's does not). Per frame:

- ``strain``: ``|edge length / rest length - 1|`` over outer-skin edges (tears, pinches);
- ``dihedral``: change of the dihedral angle of each interior outer-skin edge from the rest mesh,
  in degrees: creases (a sharp fold between two triangles) show up here first;
- ``normal``: angle between each outer-skin vertex normal and its rest normal, in degrees
  (includes the legitimate turning of the skin under an expression);
- ``flips``: outer-skin triangles whose normal turned by more than 90°;
- ``pokes``: mouth-socket vertices lying *outside* the outer skin near the lips. For each socket
  vertex at least 2 edge rings away from the outer skin, the signed distance to the nearest of its
  ``K_NEAR`` nearest rest outer-skin triangles is measured along that triangle's outward normal;
  a vertex pokes through when it is more than ``POKE_TOL_MM`` outside. Only socket vertices inside
  the skin at rest are checked (ICT's socket rim lies within the lips), so at rest the count is 0.

Per frame p99 and max are taken, then the worst frame (max over frames) is reported.

    python bench/deform_quality.py [--engines fp,rbf] [--faces default,ict] [--param k=v ...]

Sources: the built-in demo performance (``server/drivers/demo.py``, 10 fps, one loop) on
``default``, and every ``../shared/data/xface/faps/*.fap`` on ``default`` and on the ICT head.
Writes ``bench/out/deform_quality.json`` and a markdown table.
"""
from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

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


def face_normals(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Unit normals ``(F, 3)`` float64 (0 for degenerate triangles)."""
    p = p.astype(np.float64)
    n = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


def vertex_normals(p: np.ndarray, tri: np.ndarray, n_vertices: int) -> np.ndarray:
    p = p.astype(np.float64)
    fn = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    n = np.zeros((n_vertices, 3))
    for k in range(3):
        np.add.at(n, tri[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


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
    def of(cls, face) -> "QualityMesh":
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
        else:
            cand = np.zeros((0, K_NEAR), np.int64)
        qm = cls(face.mm_per_unit, tri, edges, rest_len, hinge, _dihedral(fn, hinge), verts, vn, fn,
                 sock, cand)
        # only vertices inside the skin at rest are checked (ICT's socket rim sits inside the lips)
        inside = socket_signed_mm(rest, qm) <= 0
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
        t_bc = np.clip(np.where((bc * bc).sum(-1) > 0, (bc * bp).sum(-1) / (bc * bc).sum(-1), 0), 0, 1)
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
    tri = qm.tri[qm.socket_cand]  # (P, K, 3)
    a, b, c = p[tri[..., 0]], p[tri[..., 1]], p[tri[..., 2]]
    x = p[qm.socket][:, None, :]
    q = _closest_on_triangles(np.broadcast_to(x, a.shape), a, b, c)
    d2 = ((q - x) ** 2).sum(-1)
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
        "strain_p99": float(np.percentile(strain, 99)), "strain_max": float(strain.max()),
        "dihedral_p99": float(np.percentile(dih, 99)), "dihedral_max": float(dih.max()),
        "normal_p99": float(np.percentile(ndev, 99)), "normal_max": float(ndev.max()),
        "flips": flips, "pokes": int((sd > POKE_TOL_MM).sum()),
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


def head_local(animator, states) -> np.ndarray:
    """``(T, V, 3)`` rest + B·D for each state (no rigid transforms)."""
    rest = animator.face.vertices
    return np.stack([rest + animator.operator.apply(animator.solve(s)[0]) for s in states])


def run_source(animator, states, qm: QualityMesh, step: int = 1) -> dict:
    frames = [measure(p, qm) for p in head_local(animator, states[::step])]
    s = summarise(frames)
    s["worst_dihedral_frame"] = int(np.argmax([f["dihedral_p99"] for f in frames]) * step)
    return s


def main(argv: list[str] | None = None) -> int:
    from facecast.server.drivers import load_animation
    from facecast.server.drivers.demo import demo_states
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data
    from facecast.server.pipeline import Animator

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--engines", default="fp,rbf")
    ap.add_argument("--faces", default="default,ict")
    ap.add_argument("--param", action="append", default=[], help="engine parameter k=v (python literal)")
    ap.add_argument("--step", type=int, default=1, help="use every N-th frame")
    ap.add_argument("--tag", default="")
    ap.add_argument("--out", default=str(Path(__file__).parent / "out" / "deform_quality.json"))
    args = ap.parse_args(argv)
    params = {k: ast.literal_eval(v) for k, v in (p.split("=", 1) for p in args.param)}
    data = shared_data()
    faps = sorted((data / "xface" / "faps").glob("*.fap")) if data else []
    faces = {}
    for name in args.faces.split(","):
        if name == "ict":
            if data is None:
                print("../shared/data not found: skipping ict", file=sys.stderr)
                continue
            faces["ict"] = load_face(data / "ict-facekit" / "generic_neutral_mesh.obj")
        else:
            faces[name] = load_face(name)
    result = {"tag": args.tag, "params": params, "machine_loaded": True, "rows": []}
    for fname, face in faces.items():
        qm = QualityMesh.of(face)
        for engine in args.engines.split(","):
            t = time.perf_counter()
            anim = Animator(face, engine=engine, backend="numpy", **params)
            build = time.perf_counter() - t
            op = anim.operator
            nnz_row = op.nnz / op.n_vertices
            sources = {}
            if fname != "ict":
                sources["demo"] = list(demo_states(10, loops=1))
            for path in faps:
                sources[path.stem] = load_animation(path, face).states
            rest = measure(face.vertices, qm)
            for sname, states in sources.items():
                s = run_source(anim, states, qm, args.step)
                row = {"face": fname, "engine": engine, "source": sname, "build_s": build, "nnz_row": nnz_row,
                       "rest_pokes": rest["pokes"], **s}
                result["rows"].append(row)
                print(f"{fname:8s} {engine:4s} {sname:10s} dih p99 {s['dihedral_p99']:6.2f} max "
                      f"{s['dihedral_max']:6.1f} strain p99 {s['strain_p99']:.3f} flips {s['flips']} "
                      f"pokes {s['pokes']} ({s['frames_with_pokes']} fr)", file=sys.stderr)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print("\n| face | engine | source | dihedral° p99 (mean/worst) | dihedral° max | normal° p99 | "
          "strain p99 | strain max | flips | pokes (frames) | nnz/row | build s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in result["rows"]:
        print(f"| {r['face']} | {r['engine']} | {r['source']} | {r['dihedral_p99_mean']:.2f}/{r['dihedral_p99']:.2f} "
              f"| {r['dihedral_max']:.1f} | {r['normal_p99']:.1f} | {r['strain_p99']:.3f} | {r['strain_max']:.2f} | "
              f"{r['flips']} | {r['pokes']} ({r['frames_with_pokes']}) | {r['nnz_row']:.1f} | {r['build_s']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
