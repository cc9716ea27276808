"""Deformation speed against the memory-bandwidth bound: runs ``facecast bench deform --json``,
writes ``bench/out/deform.json`` and prints a markdown table plus the issue's targets.

    python bench/deform.py [--vertices 25k 100k 500k] [any other `facecast bench deform` option]

Targets (issue 3, 2-core machine): 500k vertices with the feature-point operator at most 3 ms per
frame including read-back, within 1.5x of the bandwidth bound, at least 3x faster than SciPy's CSR
product; batch rendering of a 25k-vertex face at 25 fps at least 100x faster than real time.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out" / "deform.json"


def targets(records: list[dict]) -> list[str]:
    """One line per target: measured value, target, met or not."""
    lines = []
    big = [r for r in records if r["backend"] == "opencl" and r["vertices"] >= 400_000]
    for r in big:
        lines.append(
            f"- {r['vertices']} vertices, opencl: {r['ms_per_frame']:.3f} ms/frame (target <= 3): "
            f"{'met' if r['ms_per_frame'] <= 3 else 'NOT met'}; {r['x_bound']:.2f}x the copy bound "
            f"(target <= 1.5): {'met' if r['x_bound'] <= 1.5 else 'NOT met'}; "
            f"{r.get('speedup_vs_scipy', float('nan')):.1f}x SciPy (target >= 3): "
            f"{'met' if r.get('speedup_vs_scipy', 0) >= 3 else 'NOT met'}"
        )
    for r in records:
        if r["backend"] == "opencl-batch":
            lines.append(
                f"- batch, {r['vertices']} vertices, {r['frames']} frames at 25 fps: "
                f"{r['realtime_factor']:.0f}x real time (target >= 100): "
                f"{'met' if r['realtime_factor'] >= 100 else 'NOT met'}"
            )
    return lines


def main(argv: list[str]) -> int:
    cmd = [sys.executable, "-m", "facecast.server.cli", "bench", "deform", "--json", *argv]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=False)
    if proc.returncode != 0:
        return proc.returncode
    records = json.loads(proc.stdout)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(records, indent=1) + "\n")
    from facecast.server.bench.deform import markdown_table

    print(markdown_table(records))
    print()
    print("\n".join(targets(records)))
    print(f"\n(wrote {OUT})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
