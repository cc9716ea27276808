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

#: Most parts an annotation may name (the topology format carries at most 255 names).
MAX_PARTS = 255

AXES = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "+z": (0, 0, 1),
    "-z": (0, 0, -1),
}


def axes_frame(up: str, forward: str) -> np.ndarray:
    """``(3, 3)`` rotation whose rows are MPEG-4 x (face's left), y (up), z (forward) in mesh axes."""
    u, f = np.array(AXES[up], float), np.array(AXES[forward], float)
    return np.stack([np.cross(u, f), u, f])


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
        mesh.merge_vertices(
            merge_tex=True, merge_norm=True
        )  # UV seams, STL corners: one vertex per position
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for unreadable files
        raise InputError(
            f"trimesh cannot read this mesh ({e}); use OBJ, PLY, GLB or STL", where=str(path)
        ) from None
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise InputError("the mesh has no triangles", where=str(path))
    return np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32)


def declared_units(path: Path) -> str | None:
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
            raw = ann_path.read_bytes()
        except OSError as e:
            raise InputError(
                f"cannot read the annotation: {e.strerror}", where=str(ann_path)
            ) from None
        where = str(ann_path)
        annotation = parse_annotation(raw, where=where)
        from .annotate import complete  # a partial annotation: the automatic one fills the rest

        annotation = complete(vertices, triangles, annotation, name=path.name)
    else:
        from .ict import ict_annotation

        annotation = ict_annotation(vertices, triangles)
        where, reason = "built-in ICT FaceKit annotation", ""
        if annotation is None:
            from .annotate import cached_annotation

            try:
                annotation = cached_annotation(
                    vertices, triangles, name=path.name, units=declared_units(path)
                )
                where = "automatic annotation"
            except InputError as e:
                annotation = None
                reason = f"automatic annotation failed ({e}); "
        if annotation is None:
            raise InputError(
                reason
                + f"no annotation found: write {path.with_suffix('.face.json').name} beside the mesh with "
                "'units', 'feature_points' (MPEG-4 FP id -> vertex id) and 'parts' (see facecast docs)",
                where=str(path),
            )
    return face_from_annotation(str(path), vertices, triangles, annotation, where=where)


def parse_annotation(raw: bytes | str, *, where: str) -> dict:
    """The JSON object of a ``.face.json`` annotation; InputError if it is not UTF-8 JSON."""
    try:
        text = raw.decode("utf-8") if isinstance(raw, (bytes, bytearray)) else raw
        annotation = json.loads(text)
    except UnicodeDecodeError as e:
        raise InputError(f"annotation is not UTF-8 text (byte {e.start})", where=where) from None
    except ValueError as e:  # JSONDecodeError, or an integer over Python's 4,300-digit limit
        raise InputError(f"annotation is not valid JSON: {str(e)[:200]}", where=where) from None
    except RecursionError:
        raise InputError("annotation is nested too deeply", where=where) from None
    if not isinstance(annotation, dict):
        raise InputError("the annotation must be a JSON object", where=where)
    return annotation


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def face_from_annotation(
    name: str, vertices: np.ndarray, triangles: np.ndarray, annotation: dict, *, where: str
) -> Face:
    """Validate ``annotation`` against the mesh and build the ``Face`` (axes turned to MPEG-4's)."""
    if not isinstance(annotation, dict):
        raise InputError("the annotation must be a JSON object", where=where)
    n = len(vertices)
    units = annotation.get("units", "mm")
    if not isinstance(units, str) or units not in UNIT_MM:
        raise InputError(
            f"field 'units': {_show(units)} is not one of {', '.join(UNIT_MM)}", where=where
        )

    fps = _object(annotation, "feature_points", '{"2.1": 966, ...}', where)
    unknown = sorted(set(fps) - set(FEATURE_POINT_IDS))
    if unknown:
        listed = ", ".join(_show(u, 12)[1:-1] for u in unknown[:10]) + (
            ", ..." if len(unknown) > 10 else ""
        )
        raise InputError(
            f"field 'feature_points': unknown MPEG-4 feature point(s) {listed}; "
            "ids run 2.1-2.14, 3.1-3.14, 4.1-4.6, 5.1-5.4, 6.1-6.4, 7.1, 8.1-8.10, 9.1-9.15, "
            "10.1-10.10, 11.1-11.6",
            where=where,
        )
    for fp, vid in fps.items():
        if not _is_int(vid) or not 0 <= vid < n:
            what = (
                f"vertex id {_show(vid)} is outside"
                if _is_int(vid)
                else f"{_show(vid)} must be a vertex id in"
            )
            raise InputError(f"field 'feature_points.{fp}': {what} 0..{n - 1}", where=where)

    parts = {}
    specs = _object(annotation, "parts", '{"skin": [[0, 11247]], ...}', where)
    if len(specs) > MAX_PARTS:
        raise InputError(
            f"field 'parts': {len(specs)} parts; a face has at most {MAX_PARTS}", where=where
        )
    for part, spec in specs.items():
        parts[part] = _part_ids(spec, n, f"parts.{_show(part, 40)[1:-1]}", where)

    pivots = {}
    for key, value in _object(annotation, "pivots", '{"jaw": [0, -1.5, 2.0]}', where).items():
        if (
            not isinstance(value, list)
            or len(value) != 3
            or not all(_is_number(x) for x in value)
            or not np.all(np.isfinite(np.asarray(value, dtype=np.float64)))
        ):
            raise InputError(
                f"field 'pivots.{_show(key, 40)[1:-1]}' must be three finite numbers", where=where
            )
        pivots[key] = np.asarray(value, dtype=np.float64)

    axes = _object(annotation, "axes", '{"up": "+y", "forward": "+z"}', where)
    up, forward = axes.get("up", "+y"), axes.get("forward", "+z")
    if (
        not (isinstance(up, str) and isinstance(forward, str) and up in AXES and forward in AXES)
        or up[1] == forward[1]
    ):
        raise InputError(
            f"field 'axes': up {_show(up)} and forward {_show(forward)} must be two different "
            "axes among +x -x +y -y +z -z",
            where=where,
        )
    if (up, forward) != ("+y", "+z"):
        rot = axes_frame(up, forward)
        vertices = vertices @ rot.T.astype(np.float32)
        pivots = {k: rot @ p for k, p in pivots.items()}

    return Face(
        name=name,
        vertices=vertices,
        triangles=triangles,
        units=units,
        parts=parts,
        feature_points=fps,
        pivots=pivots,
    )


def _show(value, limit: int = 60) -> str:
    """``repr`` of a client's value, cut to ``limit`` characters for an error message."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 4] + "...'"


def _json_type(value) -> str:
    """The JSON name of a decoded value's type."""
    if isinstance(value, bool):
        return "a boolean"
    return {
        int: "a number",
        float: "a number",
        str: "a string",
        list: "an array",
        dict: "an object",
    }.get(type(value), "null")


def _object(annotation: dict, key: str, example: str, where: str) -> dict:
    """Field ``key`` of the annotation as a JSON object (absent or null: empty)."""
    value = annotation.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError(
            f"field '{key}' must be a JSON object like {example}, not {_json_type(value)}",
            where=where,
        )
    return value


def _part_ids(spec, n: int, field: str, where: str) -> np.ndarray:
    if not isinstance(spec, list):
        raise InputError(
            f"field '{field}' must be a list of vertex ids or [first, last] ranges", where=where
        )
    member = np.zeros(
        n, dtype=bool
    )  # a mask: memory is one byte per vertex however the ranges overlap
    for item in spec:
        if isinstance(item, list) and len(item) == 2 and all(_is_int(x) for x in item):
            a, b = item
            if not 0 <= a <= b < n:
                raise InputError(
                    f"field '{field}': range {_show(item)} is outside 0..{n - 1}", where=where
                )
            member[a : b + 1] = True
        elif _is_int(item):
            if not 0 <= item < n:
                raise InputError(
                    f"field '{field}': vertex id {_show(item)} is outside 0..{n - 1}", where=where
                )
            member[item] = True
        else:
            raise InputError(
                f"field '{field}': {_show(item)} is neither a vertex id nor a [first, last] range",
                where=where,
            )
    return np.flatnonzero(member).astype(np.int32)
