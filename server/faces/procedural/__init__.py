"""The built-in procedural head ``default`` (``build_default_head``), a parametric adult head in
millimetres, in the spirit of Parke's parametric face.

- ``head``: the head assembled from its parts, feature points, caches, preview colours;
- ``layout``: conformation parameters and the landmarks derived from them;
- ``skin``: the skin surface, its slits, mouth pocket and eye sacs;
- ``parts``: eyeballs, teeth, gums, tongue and ears;
- ``mesh``: graded parameter axes, grid triangulation, closed parametric surfaces.
"""

from __future__ import annotations

from .head import (
    DISK_CACHE_MIN_VERTICES,
    MAX_VERTICES,
    MIN_VERTICES,
    SKIN_SUBSETS,
    build_default_head,
    head_colors,
)
from .layout import Conformation

__all__ = [
    "DISK_CACHE_MIN_VERTICES",
    "MAX_VERTICES",
    "MIN_VERTICES",
    "SKIN_SUBSETS",
    "Conformation",
    "build_default_head",
    "head_colors",
]
