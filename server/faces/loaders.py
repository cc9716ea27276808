"""User meshes: any format trimesh reads, plus a ``<mesh>.face.json`` annotation.

The annotation (JSON object)::

    {
      "units": "cm",                                   # mm | cm | m | in
      "axes": {"up": "+y", "forward": "+z"},           # the mesh's up and face-forward axes (optional)
      "feature_points": {"2.1": 966, "3.5": 22600},    # MPEG-4 FP id -> vertex id (0-based)
      "parts": {"skin": [[0, 11247]], "eye_l": [[21451, 23020]], "tongue": [1, 2, 3]},
      "pivots": {"jaw": [0, -1.5, 2.0]}                # optional rotation centres, in mesh units
    }

Parts take inclusive ``[first, last]`` ranges or plain vertex-id lists. The ICT FaceKit topology is
recognised without an annotation (``ict.py``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from .face import FEATURE_POINT_IDS, UNIT_MM, Face
from .obj import read_obj

AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


def annotation_path(mesh: Path) -> Path | None:
    """``head.face.json`` or ``head.obj.face.json`` beside ``head.obj``, if either exists."""
    for candidate in (mesh.with_suffix(".face.json"), mesh.with_name(mesh.name + ".face.json")):
        if candidate.is_file():
            return candidate
    return None


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3) float32`` vertices and ``(F, 3) int32`` triangles, in the file's vertex order."""
    if path.suffix.lower() == ".obj" or path.name.lower().endswith(".obj.xz"):
        return read_obj(path)
    import trimesh

    try:
        mesh = trimesh.load(path, process=False, force="mesh")
        mesh.merge_vertices(merge_tex=True, merge_norm=True)  # UV seams, STL corners: one vertex per position
    except Exception as e:  # trimesh raises many types for unreadable files
        raise InputError(f"trimesh cannot read this mesh ({e}); use OBJ, PLY, GLB or STL", where=str(path)) from None
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise InputError("the mesh has no triangles", where=str(path))
    return np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32)


def _declared_units(path: Path) -> str | None:
    """Units a format fixes: glTF is in metres by its specification."""
    return "m" if path.suffix.lower() in (".glb", ".gltf") else None


def load_mesh_face(path: str | Path) -> Face:
    """A ``Face`` from a mesh file and its annotation (or the built-in ICT FaceKit annotation)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such mesh file", where=str(path))
    vertices, triangles = read_mesh(path)
    ann_path = annotation_path(path)
    if ann_path is not None:
        try:
            annotation = json.loads(ann_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise InputError(f"annotation is not valid JSON: {e}", where=str(ann_path)) from None
        where = str(ann_path)
        from .annotate import complete  # a partial annotation: the automatic one fills the rest

        annotation = complete(vertices, triangles, annotation, name=path.name)
    else:
        from .ict import ict_annotation

        annotation = ict_annotation(vertices, triangles)
        where, reason = "built-in ICT FaceKit annotation", ""
        if annotation is None:
            from .annotate import cached_annotation

            try:
                annotation = cached_annotation(vertices, triangles, name=path.name, units=_declared_units(path))
                where = "automatic annotation"
            except InputError as e:
                annotation = None
                reason = f"automatic annotation failed ({e}); "
        if annotation is None:
            raise InputError(reason +
                f"no annotation found: write {path.with_suffix('.face.json').name} beside the mesh with "
                "'units', 'feature_points' (MPEG-4 FP id -> vertex id) and 'parts' (see facecast docs)",
                where=str(path))
    return face_from_annotation(str(path), vertices, triangles, annotation, where=where)


def face_from_annotation(name: str, vertices: np.ndarray, triangles: np.ndarray, annotation: dict,
                         *, where: str) -> Face:
    """Validate ``annotation`` against the mesh and build the ``Face`` (axes turned to MPEG-4's)."""
    if not isinstance(annotation, dict):
        raise InputError("the annotation must be a JSON object", where=where)
    n = len(vertices)
    units = annotation.get("units", "mm")
    if units not in UNIT_MM:
        raise InputError(f"field 'units': {units!r} is not one of {', '.join(UNIT_MM)}", where=where)

    fps = annotation.get("feature_points", {})
    if not isinstance(fps, dict):
        raise InputError("field 'feature_points' must map FP ids to vertex ids", where=where)
    unknown = sorted(set(fps) - set(FEATURE_POINT_IDS))
    if unknown:
        raise InputError(f"field 'feature_points': unknown MPEG-4 feature point(s) {', '.join(unknown)}; "
                         "ids run 2.1-2.14, 3.1-3.14, 4.1-4.6, 5.1-5.4, 6.1-6.4, 7.1, 8.1-8.10, 9.1-9.15, "
                         "10.1-10.10, 11.1-11.6", where=where)
    for fp, vid in fps.items():
        if not isinstance(vid, int) or not 0 <= vid < n:
            raise InputError(f"field 'feature_points.{fp}': vertex id {vid!r} is outside 0..{n - 1}", where=where)

    parts = {}
    for part, spec in (annotation.get("parts") or {}).items():
        parts[part] = _part_ids(spec, n, f"parts.{part}", where)

    pivots = {}
    for key, value in (annotation.get("pivots") or {}).items():
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise InputError(f"field 'pivots.{key}' must be three finite numbers", where=where)
        pivots[key] = arr

    axes = annotation.get("axes") or {}
    up, forward = axes.get("up", "+y"), axes.get("forward", "+z")
    if up not in AXES or forward not in AXES or up[1] == forward[1]:
        raise InputError(f"field 'axes': up {up!r} and forward {forward!r} must be two different axes "
                         "among +x -x +y -y +z -z", where=where)
    if (up, forward) != ("+y", "+z"):
        u, f = np.array(AXES[up], float), np.array(AXES[forward], float)
        rot = np.stack([np.cross(u, f), u, f])  # rows: MPEG-4 x (face's left), y (up), z (forward)
        vertices = vertices @ rot.T.astype(np.float32)
        pivots = {k: rot @ p for k, p in pivots.items()}

    return Face(name=name, vertices=vertices, triangles=triangles, units=units, parts=parts,
                feature_points=fps, pivots=pivots)


def _part_ids(spec, n: int, field: str, where: str) -> np.ndarray:
    if not isinstance(spec, list):
        raise InputError(f"field '{field}' must be a list of vertex ids or [first, last] ranges", where=where)
    chunks = []
    for item in spec:
        if isinstance(item, list) and len(item) == 2 and all(isinstance(x, int) for x in item):
            a, b = item
            if not 0 <= a <= b < n:
                raise InputError(f"field '{field}': range {item} is outside 0..{n - 1}", where=where)
            chunks.append(np.arange(a, b + 1))
        elif isinstance(item, int):
            if not 0 <= item < n:
                raise InputError(f"field '{field}': vertex id {item} is outside 0..{n - 1}", where=where)
            chunks.append(np.array([item]))
        else:
            raise InputError(f"field '{field}': {item!r} is neither a vertex id nor a [first, last] range",
                             where=where)
    return np.concatenate(chunks).astype(np.int32) if chunks else np.zeros(0, np.int32)
