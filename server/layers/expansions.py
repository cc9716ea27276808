"""Arrays of a layer that depend only on the layer and the face, remembered with the face's
``Geometry`` (its ``expansions``): what an expression overlay adds and its region mask, a gaze
target's vector. The NumPy batch path (``batch``) and the compiled one (``kernel``) read them."""

from __future__ import annotations

import numpy as np

from .mix import _offsets
from .model import Contribution, GazeTarget, Geometry, region_mask
from .overlay import ExpressionLayer

_UNSEEN = object()  # (not in a cache)


def overlay_offsets(layer: ExpressionLayer, geo: Geometry) -> np.ndarray | None:
    """``(69,)`` what ``layer`` adds at full weight (``_offsets`` of its contribution), remembered
    with the geometry's expansions (read-only; one array for the overlays of one expression and
    amount without FAPs of their own)."""
    key = ("overlay", layer.expression, layer.amount) if layer.faps is None else (layer, "offsets")
    hit = geo.expansions.get(key, _UNSEEN)
    if hit is not _UNSEEN:
        return hit

    def make() -> np.ndarray | None:
        c = Contribution(
            faps=layer.faps,
            amount=layer.amount,
            expression=(layer.expression, 63, 0, 0) if layer.expression else None,
        )
        x = _offsets(c, geo)
        return None if x is None else np.array(x, dtype=np.float64)

    return geo.remember(key, make)


def overlay_mask(layer: ExpressionLayer, geo: Geometry) -> np.ndarray:
    """``(69,)`` the region mask of ``layer`` (``region_mask(regions)``), remembered."""
    return geo.remember(("mask", layer.regions), lambda: region_mask(layer.regions or ()))


def gaze_q(target: GazeTarget, geo: Geometry) -> np.ndarray:
    """``(3,)`` a target's point minus the head pivot, or its direction; remembered with the
    geometry's expansions (read-only)."""
    hit = geo.expansions.get((target, "q"))
    if hit is not None:
        return hit

    def make() -> np.ndarray:
        q = target.direction if target.point is None else target.point - geo.head_pivot
        return np.array(q, dtype=np.float64)

    return geo.remember((target, "q"), make)


def overlay_at(layer: ExpressionLayer, t: float, geo: Geometry) -> tuple[float, np.ndarray] | None:
    """``(envelope, offsets (69,))`` of an expression overlay at time ``t`` (s): its envelope and
    ``overlay_offsets``; None when it adds nothing then (envelope 0, or no offsets)."""
    e = layer.envelope(t)
    if e <= 0.0:
        return None
    x = overlay_offsets(layer, geo)
    return None if x is None else (e, x)
