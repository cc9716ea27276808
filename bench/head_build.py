"""Build time of the built-in procedural head against vertex count (2k ... 500k).

For each size: a cold build (in-process memo cleared, disk cache bypassed), a disk-cache load (for
sizes that are cached on disk), the vertex count reached versus the request, and the largest
feature-point drift from the 25k head. Baseline measured in the same run (the machine is shared and
noisy, so ratios matter more than seconds): sampling a bare two-pole sphere grid with the same
number of vertices with the same helpers (``closed_surface``) — the floor of "sample a parametric
surface and triangulate it".

    python bench/head_build.py [--sizes 2k,10k,25k,100k,250k,500k] [--repeat 2] [--previews]

Writes ``bench/out/head_build.json`` and prints a markdown table; ``--previews`` also writes PNGs of
the head (front, three-quarter, side, mouth and eye close-ups, 2k and 25k) to ``bench/out/head_previews/``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from facecast.server.faces import parse_count
from facecast.server.faces.procedural import head as procedural
from facecast.server.faces.procedural.mesh import closed_surface


def _sphere(n: int) -> int:
    rings = max(4, int(round(np.sqrt(n / 2))))
    seg = max(8, int(round(n / rings)))

    def pts(t, w):
        a = np.pi * t
        return 100 * np.stack([np.sin(a) * np.cos(w), np.sin(a) * np.sin(w), np.cos(a)], -1)

    v, _ = closed_surface(pts, (np.arange(rings) + 0.5) / rings, seg)
    return len(v)


def _best(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def write_previews(folder: Path) -> None:
    from facecast.server.output.preview import render_png

    folder.mkdir(parents=True, exist_ok=True)
    for n in (2_000, 25_000):
        f = procedural.build_default_head(n)
        col = procedural.head_colors(f)
        k = f"{n // 1000}k"
        for view in ("front", "three_quarter", "side"):
            render_png(
                f.vertices, f.triangles, folder / f"head_{k}_{view}.png", colors=col, view=view
            )
        render_png(
            f.vertices,
            f.triangles,
            folder / f"head_{k}_mouth.png",
            colors=col,
            view=20,
            center=f.fp_position("2.2"),
            extent=80,
        )
        eyes = (f.fp_position("3.5") + f.fp_position("3.6")) / 2
        render_png(
            f.vertices,
            f.triangles,
            folder / f"head_{k}_eyes.png",
            colors=col,
            size=(640, 320),
            center=eyes,
            extent=120,
        )
    print(f"previews in {folder}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="2k,10k,25k,100k,250k,500k")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=str(Path(__file__).parent / "out" / "head_build.json"))
    ap.add_argument("--previews", action="store_true", help="also write preview PNGs")
    args = ap.parse_args(argv)
    if args.previews:
        write_previews(Path(args.out).parent / "head_previews")
    sizes = [parse_count(s) for s in args.sizes.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["FACECAST_CACHE"] = tmp  # cold builds never read the user's cache
        ref = procedural.build_default_head(25_000)
        # A cold build needs the in-memory memo emptied; the head module offers no public way.
        clear_memo = procedural._build.cache_clear  # noqa: SLF001 - white-box bench of the memo

        def cold(n):
            clear_memo()
            for f in Path(tmp).rglob("*.npz"):
                f.unlink()
            return procedural.build_default_head(n)

        for n in sizes:
            t_build, face = _best(lambda n=n: cold(n), args.repeat)
            t_base, nv_base = _best(lambda nv=face.n_vertices: _sphere(nv), args.repeat)
            t_disk = None
            if n >= procedural.DISK_CACHE_MIN_VERTICES:

                def from_disk(n=n):
                    clear_memo()
                    return procedural.build_default_head(n)

                t_disk, _ = _best(from_disk, args.repeat)
            clear_memo()
            t_memo, _ = _best(lambda n=n: procedural.build_default_head(n), 1)
            t_memo, _ = _best(lambda n=n: procedural.build_default_head(n), args.repeat)
            drift = max(
                float(np.linalg.norm(face.fp_position(k) - ref.fp_position(k)))
                for k in ref.feature_points
            )
            rows.append(
                {
                    "requested": n,
                    "vertices": face.n_vertices,
                    "triangles": len(face.triangles),
                    "count_error": face.n_vertices / n - 1,
                    "build_s": t_build,
                    "baseline_sphere_s": t_base,
                    "baseline_vertices": nv_base,
                    "ratio_to_baseline": t_build / t_base,
                    "disk_load_s": t_disk,
                    "memo_s": t_memo,
                    "fp_drift_mm_vs_25k": drift,
                }
            )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"bench": "head_build", "cpu_count": os.cpu_count(), "rows": rows}, indent=2)
    )
    print(
        "| requested | vertices | count err | cold build s | sphere baseline s | ratio "
        "| disk load s | memo s | FP drift mm |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        disk = f"{r['disk_load_s']:.3f}" if r["disk_load_s"] is not None else "—"
        print(
            f"| {r['requested']} | {r['vertices']} | {100 * r['count_error']:+.1f}% | {r['build_s']:.3f} | "
            f"{r['baseline_sphere_s']:.4f} | {r['ratio_to_baseline']:.0f}x | {disk} | {r['memo_s']:.4f} | "
            f"{r['fp_drift_mm_vs_25k']:.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
