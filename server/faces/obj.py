"""A fast Wavefront OBJ reader that keeps the file's vertex order (texture seams do not split vertices)."""

from __future__ import annotations

import lzma
from pathlib import Path

import numpy as np

from ..errors import InputError


def read_obj(source: str | Path, *, text: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read positions and polygons from an OBJ file (``.obj`` or ``.obj.xz``).

    Polygons are fan-triangulated; only the position index of each ``v/vt/vn`` corner is used, so
    vertex ids are exactly the file's ``v`` lines in order (what blend-shape sets rely on).

    Returns:
        ``vertices (V, 3) float32`` and ``triangles (F, 3) int32``.
    """
    where = str(source)
    if text is None:
        path = Path(source)
        opener = lzma.open if path.suffix == ".xz" else open
        try:
            with opener(path, "rt", encoding="utf-8", errors="replace") as f:
                text = f.read()
        except (OSError, lzma.LZMAError) as e:
            raise InputError(f"cannot read OBJ file: {e}", where=where) from None
    verts: list[str] = []
    tris: list[list[int]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            verts.append(line[2:])
        elif line.startswith("f "):
            try:
                corner = [int(tok.split("/", 1)[0]) for tok in line[2:].split()]
            except ValueError:
                raise InputError(
                    f"line {lineno}: face with a non-integer vertex index", where=where
                ) from None
            if len(corner) < 3:
                raise InputError(f"line {lineno}: face with fewer than 3 corners", where=where)
            n = len(verts)
            corner = [c - 1 if c > 0 else n + c for c in corner]
            tris.extend([corner[0], corner[i], corner[i + 1]] for i in range(1, len(corner) - 1))
    if not verts:
        raise InputError("no vertices ('v' lines) found", where=where)
    try:
        vertices = np.array(" ".join(verts).split(), dtype=np.float64).reshape(len(verts), -1)[
            :, :3
        ]
    except ValueError:
        raise InputError("a 'v' line does not hold three numbers", where=where) from None
    triangles = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise InputError(f"a face refers to a vertex outside 1..{len(vertices)}", where=where)
    return vertices.astype(np.float32), triangles.astype(np.int32)
