"""``--landmarks``: user-given positions of a few feature points, to guide the automatic annotation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..face import FEATURE_POINT_IDS


def parse_landmarks(
    data, n_vertices: int | None = None, *, where: str = "landmarks"
) -> dict[str, np.ndarray]:
    """``{MPEG-4 id: [x, y, z]}`` (mesh units) or ``{id: vertex id}`` -> ``{id: (3,) position or vertex}``.

    Vertex ids are kept as ints (resolved by the caller); at least three points are needed.
    """
    if not isinstance(data, dict) or len(data) < 3:
        raise InputError(
            "landmarks must be a JSON object of at least three MPEG-4 feature points, "
            'e.g. {"9.3": [0, 1.2, 9.8], "3.7": [...], "3.12": [...], "2.1": [...]}',
            where=where,
        )
    out = {}
    for k, p in data.items():
        if k not in FEATURE_POINT_IDS:
            raise InputError(f"{k!r} is not an MPEG-4 feature point id (2.1 ... 11.6)", where=where)
        if (
            isinstance(p, int)
            and not isinstance(p, bool)
            and n_vertices is not None
            and 0 <= p < n_vertices
        ):
            out[k] = p
            continue
        try:
            arr = np.asarray(p, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise InputError(
                f"landmark {k}: give three finite numbers (or a vertex id)", where=where
            )
        out[k] = arr
    return out


def read_landmarks(path: Path, n_vertices: int) -> dict:
    """Landmarks from a JSON file (see ``parse_landmarks``); vertex ids stay ints."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read landmarks: {e}", where=str(path)) from None
    return parse_landmarks(data, n_vertices, where=str(path))
