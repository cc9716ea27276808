"""Recognising the ICT FaceKit topology and supplying facecast's annotation for it (never the mesh)."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from .ict_annotate import topology_hash

ANNOTATION = Path(__file__).with_name("data") / "ict_facekit.face.json"


@lru_cache(maxsize=1)
def _shipped() -> dict:
    return json.loads(ANNOTATION.read_text())


def is_ict_topology(vertices: np.ndarray, triangles: np.ndarray) -> bool:
    """True when the mesh has ICT FaceKit's vertex count and triangle list (any identity or expression)."""
    topo = _shipped()["topology"]
    return (
        len(vertices) == topo["vertices"]
        and len(triangles) == topo["triangles"]
        and topology_hash(triangles) == topo["hash"]
    )


def ict_annotation(vertices: np.ndarray, triangles: np.ndarray) -> dict | None:
    """facecast's annotation for an ICT FaceKit mesh, or None if the mesh is something else."""
    return _shipped() if is_ict_topology(vertices, triangles) else None
