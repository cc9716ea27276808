"""Operator build time and per-frame NumPy deform time against vertex count (2k ... 500k).

Faces: the built-in head (``load_face("default:2k")`` ... ``default:500k``) with its MPEG-4 feature
points as controls; while the built-in head is unavailable, a UV sphere of the same vertex count
with 84 synthetic controls spread over its front (a face-sized cap), so the numbers still scale.

Baselines measured in the same run (the machine is shared and noisy, so ratios matter more than
seconds): for the build, one unbounded Dijkstra over the whole surface graph from one source
from a vertex of the largest connected piece (what any surface-distance method pays at least
once); for a frame, one pass ``rest + rest`` over the ``(V, 3) float32`` vertices (a
memory-bandwidth floor).

    python bench/operator_scaling.py [--sizes 2k,25k,100k,500k] [--frames 20] [--rbf-max 100000]

Writes ``bench/out/operator_scaling.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import dijkstra

from facecast.server.backends.numpy_backend import NumpyDeformer
from facecast.server.deform.build import build_operator
from facecast.server.deform.mesh_graph import components, edge_graph
from facecast.server.faces import load_face, parse_count
from facecast.server.faces.face import RIGID_GROUPS, Face


def sphere_face(n_vertices: int, n_controls: int = 84) -> tuple[Face, np.ndarray]:
    """A unit-radius (100 mm) UV sphere of about ``n_vertices`` and controls on its front cap."""
    import trimesh

    lat = max(8, round(np.sqrt(n_vertices / 4)))
    mesh = trimesh.creation.uv_sphere(radius=100.0, count=[lat, 2 * lat])
    face = Face(f"sphere:{len(mesh.vertices)}", mesh.vertices, mesh.faces, units="mm")
    # Fibonacci points on the cap z > 0.3 (the "face"), snapped to the nearest vertex.
    i = np.arange(n_controls) + 0.5
    z = 1 - (1 - 0.3) * i / n_controls
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    pts = 100.0 * np.c_[r * np.cos(phi), r * np.sin(phi), z]
    from scipy.spatial import cKDTree

    controls = np.unique(cKDTree(face.vertices).query(pts)[1])
    return face, controls


def get_face(size: str) -> tuple[Face, np.ndarray, str]:
    try:
        face = load_face(f"default:{size}")
        controls = np.array(sorted({v for v in face.feature_points.values() if face.deformable[v]}))
        if len(controls) >= 4:
            return face, controls, "default head"
    except Exception as e:  # noqa: BLE001 - the built-in head may not exist yet
        print(
            f"default:{size} unavailable ({type(e).__name__}: {e}); using a sphere", file=sys.stderr
        )
    face, controls = sphere_face(parse_count(size))
    return face, controls, "uv sphere"


def timed(fn, *args, repeat: int = 1, **kwargs) -> tuple[float, object]:
    """Best wall time of ``repeat`` calls of ``fn(*args, **kwargs)``, and its result."""
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - t)
    return best, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="2k,25k,100k,500k")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument(
        "--rbf-max",
        type=int,
        default=600_000,
        help="skip the dense RBF operator above this many vertices (memory: 4·V·K bytes)",
    )
    ap.add_argument("--out", default=str(Path(__file__).parent / "out" / "operator_scaling.json"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = []
    for size in args.sizes.split(","):
        face, controls, kind = get_face(size)
        graph = edge_graph(face.vertices, face.triangles, face.deformable)
        label = components(graph)
        source = int(
            np.flatnonzero(label == np.bincount(label).argmax())[0]
        )  # in the largest piece
        t_dijkstra, _ = timed(dijkstra, graph, directed=False, indices=source)
        row = {
            "size": size,
            "face": kind,
            "vertices": face.n_vertices,
            "controls": len(controls),
            "dijkstra_one_source_s": t_dijkstra,
        }
        rest = face.vertices
        t_pass, _ = timed(np.add, rest, rest, repeat=max(5, args.frames))
        row["memory_pass_s"] = t_pass
        transforms = np.tile(np.eye(3, 4, dtype=np.float32), (len(RIGID_GROUPS), 1, 1))
        D = rng.normal(scale=1.0, size=(len(controls), 3)).astype(np.float32)
        engines = [("fp", {})]
        if face.n_vertices <= args.rbf_max:
            engines.append(("rbf", {}))
        for engine, params in engines:
            t_build, op = timed(build_operator, face, controls, engine=engine, **params)
            deformer = NumpyDeformer(face.vertices, face.triangles, face.rigid_group, op)
            deformer.deform(D, transforms)
            t_frame, _ = timed(deformer.deform, D, transforms, repeat=args.frames)
            row[engine] = {
                "build_s": t_build,
                "build_over_dijkstra": t_build / t_dijkstra,
                "nnz": op.nnz,
                "frame_s": t_frame,
                "frame_over_memory_pass": t_frame / t_pass,
            }
            print(
                f"{size:>5s} {kind:12s} V={face.n_vertices:7d} K={len(controls):3d} {engine:3s} "
                f"build {t_build:7.2f}s frame {t_frame * 1e3:8.2f} ms",
                file=sys.stderr,
            )
        rows.append(row)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "machine_loaded": True}, indent=1))
    print(
        "| face | V | K | 1 Dijkstra s | fp build s (× Dijkstra) | fp frame ms (× memory pass) | "
        "rbf build s | rbf frame ms |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        fp, rbf = r["fp"], r.get("rbf")
        rb = f"{rbf['build_s']:.2f} | {rbf['frame_s'] * 1e3:.2f}" if rbf else "– | –"
        print(
            f"| {r['face']} {r['size']} | {r['vertices']} | {r['controls']} | {r['dijkstra_one_source_s']:.3f} | "
            f"{fp['build_s']:.2f} ({fp['build_over_dijkstra']:.1f}×) | {fp['frame_s'] * 1e3:.2f} "
            f"({fp['frame_over_memory_pass']:.1f}×) | {rb} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
