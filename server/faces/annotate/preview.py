"""A picture to check an annotation: the mesh from the front and the side with its feature points.

Points on the face's left are green, on its right red, on the midline yellow (the project's own
rasteriser, ``output.preview``; no imaging library).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...output.preview import render_image, view_rotation, write_png

_COLOURS = {1: (60, 220, 90), -1: (235, 70, 60), 0: (250, 220, 50)}


def annotation_preview(face, path: str | Path, *, size: int = 480) -> Path:
    """Write ``path`` (PNG): front and side views of ``face`` (MPEG-4 axes) with its feature points."""
    v = face.vertices.astype(np.float64)
    fp_ids = np.array(list(face.feature_points.values()), dtype=np.int64)
    # The head: the feature points' box with a margin (a body's feet stay out of the picture).
    lo, hi = v[fp_ids].min(axis=0), v[fp_ids].max(axis=0)
    centre = (lo + hi) / 2
    extent = float(max(hi - lo)) * 1.35 or 1.0
    ordered = sorted(face.feature_points.items())
    mid_x = float(np.median([v[i, 0] for k, i in ordered])) if ordered else 0.0
    other = np.zeros(face.n_vertices, bool)
    other[face.part("other")] = True  # clothing, hair cards: not what the points sit on
    tri = face.triangles[~other[face.triangles].all(axis=1)]
    images = []
    for view in ("front", "side"):
        img = render_image(v, tri, size=(size, size), view=view, center=centre, extent=extent)
        rot = view_rotation(view)
        cam = v @ rot.T
        mid = rot @ centre
        span = extent / size
        depth_order = np.argsort(cam[fp_ids, 2])  # far points first, near ones drawn over them
        for k in depth_order:
            vid = fp_ids[k]
            x = int((cam[vid, 0] - mid[0]) / span + size / 2)
            y = int((mid[1] - cam[vid, 1]) / span + size / 2)
            side = 0 if abs(v[vid, 0] - mid_x) < 0.01 * extent else int(np.sign(v[vid, 0] - mid_x))
            r = max(2, size // 160)
            img[max(0, y - r - 1) : y + r + 2, max(0, x - r - 1) : x + r + 2] = (20, 20, 20)
            img[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1] = _COLOURS[side]
        images.append(img)
    return write_png(path, np.concatenate(images, axis=1))
