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
    skin = face.part("skin")
    ids = skin if len(skin) else np.arange(face.n_vertices)
    fp_ids = np.array(list(face.feature_points.values()), dtype=np.int64)
    focus = np.r_[ids, fp_ids]
    lo, hi = v[focus].min(axis=0), v[focus].max(axis=0)
    centre = (lo + hi) / 2
    extent = float(max(np.ptp(v[focus], axis=0))) * 1.1 or 1.0
    ordered = sorted(face.feature_points.items())
    mid_x = float(np.median([v[i, 0] for k, i in ordered])) if ordered else 0.0
    images = []
    for view in ("front", "side"):
        img = render_image(v, face.triangles, size=(size, size), view=view, center=centre, extent=extent)
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
            img[max(0, y - r - 1):y + r + 2, max(0, x - r - 1):x + r + 2] = (20, 20, 20)
            img[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] = _COLOURS[side]
        images.append(img)
    return write_png(path, np.concatenate(images, axis=1))
