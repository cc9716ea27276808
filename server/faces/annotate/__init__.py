"""Automatic annotation of any head mesh ("bring your own head").

``annotate_mesh(vertices, triangles)`` fits the built-in head as a template to the mesh and returns a
complete ``.face.json`` annotation (see ``loaders``) with an ``automatic`` report of what it measured
and what it left out. ``cached_annotation`` is what loading a mesh without an annotation uses: the
result is cached under ``cache_dir("annotations")`` keyed by the mesh's hash. ``merge`` lets a user's
partial annotation win over the automatic one, field by field and point by point.
"""

from __future__ import annotations

import hashlib
import json
import logging

import numpy as np

from ...errors import InputError
from ...output.atomic import write_bytes_atomic
from ...paths import cache_dir
from .core import annotate_mesh

__all__ = ["annotate_mesh", "cached_annotation", "merge", "mesh_key"]

log = logging.getLogger(__name__)

#: Bump when a change makes the annotator give different results (invalidates the cache).
VERSION = 10


def mesh_key(vertices: np.ndarray, triangles: np.ndarray) -> str:
    """Hex hash (16 chars) of the mesh as read (float32 vertices, int32 triangles) and ``VERSION``."""
    h = hashlib.blake2b(digest_size=8)
    h.update(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(triangles, dtype=np.int32).tobytes())
    h.update(str(VERSION).encode())
    return h.hexdigest()


def cached_annotation(
    vertices: np.ndarray, triangles: np.ndarray, *, name: str = "mesh", units: str | None = None
) -> dict:
    """The automatic annotation of a mesh, from the cache or computed (and cached, saying so once).

    Raises ``InputError`` when the mesh cannot be annotated (not a head, too small).
    """
    key = mesh_key(vertices, triangles)
    try:
        path = cache_dir("annotations") / f"{key}.face.json"
    except OSError as e:  # an unwritable cache costs a recomputation, not a failure
        log.warning("annotation cache unavailable (%s)", e)
        path = None
    if path is not None and path.is_file():
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            log.warning("cached annotation %s is unreadable; annotating again", path)
    annotation = annotate_mesh(vertices, triangles, units=units)
    report = annotation["automatic"]
    log.warning(
        "%s has no annotation: annotated it automatically in %.1f s (%d of 84 feature points%s)%s; "
        "write a .face.json beside the mesh to correct any of it",
        name,
        report["seconds"],
        len(annotation["feature_points"]),
        f", left out {', '.join(report['left_out'])}" if report["left_out"] else "",
        f", cached as {path}" if path is not None else "",
    )
    if path is not None:
        try:
            write_bytes_atomic(path, json.dumps(annotation, separators=(",", ":")).encode())
        except OSError as e:
            log.warning("could not cache the annotation (%s)", e)
    return annotation


def merge(automatic: dict, user: dict) -> dict:
    """The user's annotation over the automatic one: every field and every feature point, part and
    pivot the user gives wins; an automatic point on a vertex the user gave another point is dropped."""
    out = dict(automatic.items())
    for key in ("units", "axes"):
        if key in user:
            out[key] = user[key]
    fps = user.get("feature_points")
    if isinstance(fps, dict):
        taken = {v for v in fps.values() if isinstance(v, int)}
        out["feature_points"] = {
            **{k: v for k, v in automatic.get("feature_points", {}).items() if v not in taken},
            **fps,
        }
    for key in ("parts", "pivots"):
        if isinstance(user.get(key), dict):
            out[key] = {**automatic.get(key, {}), **user[key]}
        elif key in user:
            out[key] = user[key]  # let validation name the bad field
    return out


def is_partial(annotation) -> bool:
    """True when a user's annotation leaves feature points or parts to the annotator (never for one
    marked ``"final": true``: an uploaded face's annotation, already completed once)."""
    from ..face import FEATURE_POINT_IDS

    if not isinstance(annotation, dict) or annotation.get("final") is True:
        return False
    fps = annotation.get("feature_points")
    return (
        "parts" not in annotation
        or not isinstance(fps, dict)
        or not set(FEATURE_POINT_IDS) <= set(fps)
    )


def complete(vertices: np.ndarray, triangles: np.ndarray, user: dict, *, name: str) -> dict:
    """``user`` completed by the automatic annotation when it is partial (or as is when the mesh
    cannot be annotated automatically: the user's annotation is then all there is)."""
    if not is_partial(user):
        return user
    try:
        auto = cached_annotation(vertices, triangles, name=name)
    except InputError as e:
        log.info("%s: partial annotation kept as is (automatic annotation failed: %s)", name, e)
        return user
    return merge(auto, user)
