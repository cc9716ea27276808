"""Marker layouts: which markers a take has, which are stable, and where each sits on the target face.

JSON::

    {"units": "mm",                      # units of the take (optional: declared by the file or detected)
     "face": "path/to/mesh.obj",          # optional: the face its vertex ids are for (named in errors)
     "stable": ["HEAD_L", "HEAD_R", ...],   # markers that move only with the skull (>= 3)
     "neutral_frame": 0,                 # optional: frame holding the actor's neutral face, or "auto"
     "jaw": "CHIN",                      # optional: marker giving jaw opening (default: the one tied to FP 2.1)
     "exaggerate": {"mouth": {"gain": 1.3, "markers": ["LIP_L", "LIP_R"]}},  # optional: per region,
                                         # the region's markers' displacements scaled (the engine
                                         # spreads each gain smoothly over the skin around them)
     "markers": {"CHIN": {"fp": "2.1"},  # tied to an MPEG-4 feature point of the face
                 "LIP_L": {"vertex": 1234},   # tied to a vertex id of the face
                 "CHEEK_L": {},          # placed automatically from the tied markers
                 "JIG_1": {"control": false}}}  # used for stabilisation only, not placed on the face

Automatic placement warps the actor's neutral markers onto the face with an RBF fitted on the tied
markers (as the thesis does from its 11 fiducials), then snaps each to the nearest skin vertex.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...protocol.markers_file import MarkerFileError, normalise_units
from ..errors import InputError
from ..faces.face import Face

log = logging.getLogger(__name__)

__all__ = ["MAX_GAIN", "Layout", "Placement", "load_layout", "marker_gains", "place_markers"]


@dataclass
class Layout:
    """A parsed layout (see module docstring). ``markers`` keeps the file's order."""

    markers: dict[str, dict]
    stable: list[str]
    units: str | None = None
    neutral_frame: int | str | None = None  # a frame, or "auto" (mocap.neutral)
    jaw: str | None = None
    where: str = "layout"
    face: str | None = None
    exaggerate: dict[str, dict] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return list(self.markers)


def load_layout(src: str | Path | dict | Layout) -> Layout:
    """Parse a layout from a path, a JSON string or a dict; InputError naming the field at fault."""
    if isinstance(src, Layout):
        return src
    where = "layout"
    if isinstance(src, (str, Path)) and not (isinstance(src, str) and src.lstrip().startswith("{")):
        path = Path(src)
        where = str(path)
        if not path.is_file():
            raise InputError("no such layout file", where=where)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"not valid JSON ({e})", where=where) from None
    elif isinstance(src, str):
        try:
            data = json.loads(src)
        except json.JSONDecodeError as e:
            raise InputError(f"not valid JSON ({e})", where=where) from None
    else:
        data = src
    if not isinstance(data, dict):
        raise InputError("a layout is a JSON object with 'markers' and 'stable'", where=where)
    unknown = set(data) - {
        "units",
        "stable",
        "markers",
        "neutral_frame",
        "jaw",
        "face",
        "exaggerate",
        "comment",
        "description",
    }
    if unknown:
        raise InputError(
            f"unknown field(s) {', '.join(sorted(unknown))}; expected units, stable, markers, "
            "neutral_frame, jaw, face, exaggerate",
            where=where,
        )
    markers = data.get("markers")
    if not isinstance(markers, dict) or not markers:
        raise InputError(
            "'markers' must be a non-empty object {name: {...}}", where=f"{where}: markers"
        )
    clean: dict[str, dict] = {}
    for name, spec in markers.items():
        w = f"{where}: markers.{name}"
        if spec is None:
            spec = {}
        if not isinstance(spec, dict):
            raise InputError(
                'each marker is {"vertex": id}, {"fp": "2.1"}, {} or {"control": false}', where=w
            )
        bad = set(spec) - {"vertex", "fp", "control"}
        if bad:
            raise InputError(
                f"unknown key(s) {', '.join(sorted(bad))}; use vertex, fp or control", where=w
            )
        if "vertex" in spec and "fp" in spec:
            raise InputError("give either 'vertex' or 'fp', not both", where=w)
        if "vertex" in spec and (
            isinstance(spec["vertex"], bool)
            or not isinstance(spec["vertex"], int)
            or spec["vertex"] < 0
        ):
            raise InputError(
                f"'vertex' must be a non-negative integer, not {spec['vertex']!r}", where=w
            )
        if "fp" in spec and not isinstance(spec["fp"], str):
            raise InputError(f"'fp' must be a string such as \"2.1\", not {spec['fp']!r}", where=w)
        if "control" in spec and not isinstance(spec["control"], bool):
            raise InputError("'control' must be true or false", where=w)
        clean[str(name)] = dict(spec)
    stable = data.get("stable", [])
    if not isinstance(stable, list) or not all(isinstance(s, str) for s in stable):
        raise InputError("'stable' must be a list of marker names", where=f"{where}: stable")
    missing = [s for s in stable if s not in clean]
    if missing:
        raise InputError(
            f"stable marker(s) {', '.join(missing)} are not in 'markers'", where=f"{where}: stable"
        )
    if len(set(stable)) < 3:
        raise InputError(
            f"at least 3 stable head markers are needed to remove head motion, got {len(set(stable))}",
            where=f"{where}: stable",
        )
    try:
        units = (
            normalise_units(data["units"], where=f"{where}: units") if data.get("units") else None
        )
    except MarkerFileError as e:
        raise InputError(str(e)) from None
    nf = data.get("neutral_frame")
    if (
        nf is not None
        and nf != "auto"
        and (isinstance(nf, bool) or not isinstance(nf, int) or nf < 0)
    ):
        raise InputError(
            f"'neutral_frame' must be a frame index >= 0 or \"auto\", not {nf!r}",
            where=f"{where}: neutral_frame",
        )
    jaw = data.get("jaw")
    if jaw is not None and jaw not in clean:
        raise InputError(f"jaw marker {jaw!r} is not in 'markers'", where=f"{where}: jaw")
    if jaw is None:
        jaw = next((n for n, s in clean.items() if s.get("fp") == "2.1"), None)
    made_for = data.get("face")
    if made_for is not None and not isinstance(made_for, str):
        raise InputError(
            "'face' must be a string: the face the vertex ids are for", where=f"{where}: face"
        )
    exaggerate = _exaggeration(data.get("exaggerate", {}), clean, f"{where}: exaggerate")
    return Layout(clean, list(dict.fromkeys(stable)), units, nf, jaw, where, made_for, exaggerate)


#: The largest exaggeration gain a layout may ask for (beyond it the retargeted skin tears).
MAX_GAIN = 4.0


def _exaggeration(
    data: object, markers: dict[str, dict[str, Any]], where: str
) -> dict[str, dict[str, Any]]:
    """The checked ``exaggerate`` field: ``{region: {"gain": g, "markers": [names]}}``, 0 <= g <=
    ``MAX_GAIN``, each marker in one region at most; InputError naming what is wrong."""
    if not isinstance(data, dict):
        raise InputError(
            '\'exaggerate\' is {"region": {"gain": 1.3, "markers": ["A", "B"]}}', where=where
        )
    out: dict[str, dict[str, Any]] = {}
    owner: dict[str, str] = {}
    for region, spec in data.items():
        w = f"{where}.{region}"
        if not isinstance(spec, dict) or set(spec) != {"gain", "markers"}:
            raise InputError('a region is {"gain": 1.3, "markers": ["A", "B"]}', where=w)
        gain, names = spec["gain"], spec["markers"]
        if (
            isinstance(gain, bool)
            or not isinstance(gain, (int, float))
            or not 0.0 <= gain <= MAX_GAIN
        ):
            raise InputError(
                f"'gain' must be a number from 0 to {MAX_GAIN:g}, not {gain!r}", where=w
            )
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise InputError("'markers' must be a non-empty list of marker names", where=w)
        unknown = [n for n in names if n not in markers]
        if unknown:
            raise InputError(f"marker(s) {', '.join(unknown[:8])} are not in 'markers'", where=w)
        twice = [n for n in names if n in owner]
        if twice:
            raise InputError(f"marker {twice[0]} is already in region {owner[twice[0]]!r}", where=w)
        owner.update({n: str(region) for n in names})
        out[str(region)] = {"gain": float(gain), "markers": list(dict.fromkeys(names))}
    return out


def marker_gains(layout: Layout, names: list[str]) -> np.ndarray:
    """``(len(names),)`` the exaggeration gain of each named marker (1 outside every region)."""
    gain = {n: r["gain"] for r in layout.exaggerate.values() for n in r["markers"]}
    return np.array([gain.get(n, 1.0) for n in names], dtype=np.float32)


@dataclass
class Placement:
    """Where a layout's markers sit on a face.

    Attributes:
        names: the control markers (in layout order; ``{"control": false}`` ones excluded).
        vertices: ``(K,) int32`` face vertex of each.
        how: per marker ``"vertex" | "fp" | "auto"``.
    """

    names: list[str]
    vertices: np.ndarray
    how: list[str] = field(default_factory=list)


def place_markers(
    layout: Layout,
    face: Face,
    neutral: dict[str, np.ndarray] | None = None,
    *,
    face_units_per_take_unit: float = 1.0,
) -> Placement:
    """Resolve every control marker to a face vertex.

    ``neutral`` maps marker name -> actor's neutral position ``(3,)`` (needed only for automatic
    placement; in any units, as the warp includes scale). InputError when a vertex id is out of
    range, an FP is unknown to the face, or automatic placement lacks 4 tied markers.
    """
    names, verts, how = [], [], []
    auto: list[str] = []
    for name, spec in layout.markers.items():
        if spec.get("control") is False:
            continue
        w = f"{layout.where}: markers.{name}"
        if "vertex" in spec:
            v = spec["vertex"]
            if v >= face.n_vertices:
                raise InputError(
                    f"vertex {v} is out of range: the face {face.name!r} has {face.n_vertices} "
                    "vertices (is the layout for another mesh?)",
                    where=w,
                )
            names.append(name), verts.append(v), how.append("vertex")
        elif "fp" in spec:
            fp = spec["fp"]
            if fp not in face.feature_points:
                raise InputError(
                    f"the face {face.name!r} has no feature point {fp}; it has "
                    f"{len(face.feature_points)} ({', '.join(sorted(face.feature_points)[:12])}...)",
                    where=w,
                )
            names.append(name), verts.append(face.feature_points[fp]), how.append("fp")
        else:
            names.append(name), verts.append(-1), how.append("auto")
            auto.append(name)
    if auto:
        tied = [n for n, h in zip(names, how) if h != "auto"]
        if neutral is None:
            raise InputError(
                "automatic marker placement needs the actor's neutral frame", where=layout.where
            )
        tied = [n for n in tied if n in neutral and np.isfinite(neutral[n]).all()]
        if len(tied) < 4:
            raise InputError(
                f"{len(auto)} marker(s) ({', '.join(auto[:5])}...) ask for automatic placement, which "
                f"needs at least 4 markers tied to a vertex or FP and visible in the neutral frame; "
                f"found {len(tied)}",
                where=layout.where,
            )
        from .retarget import RBFMap

        idx = {n: i for i, n in enumerate(names)}
        src = np.array([neutral[n] for n in tied])
        dst = face.vertices[[verts[idx[n]] for n in tied]].astype(np.float64)
        warp = RBFMap(src, dst, kernel="imq", mu=0.5)
        skin = _skin_vertices(face)
        tree = cKDTree(face.vertices[skin])
        used = {v for v in verts if v >= 0}
        for n in auto:
            if n not in neutral or not np.isfinite(neutral[n]).all():
                raise InputError(
                    f"marker {n} asks for automatic placement but is not visible in the neutral frame",
                    where=f"{layout.where}: markers.{n}",
                )
            _, js = tree.query(warp(neutral[n][None])[0], k=min(16, len(skin)))
            free = [int(skin[j]) for j in np.atleast_1d(js) if int(skin[j]) not in used]
            verts[idx[n]] = free[0] if free else int(skin[np.atleast_1d(js)[0]])
            used.add(verts[idx[n]])
        log.info("placed %d markers automatically from %d tied ones", len(auto), len(tied))
    vs = np.asarray(verts, dtype=np.int32)
    if len(set(vs.tolist())) < len(vs):
        seen: dict[int, str] = {}
        for n, v in zip(names, vs.tolist()):
            if v in seen:
                raise InputError(
                    f"markers {seen[v]} and {n} sit on the same vertex {v}", where=layout.where
                )
            seen[v] = n
    return Placement(names, vs, how)


def _skin_vertices(face: Face) -> np.ndarray:
    """Vertex ids a marker may be snapped to: the skin part, else every deformable vertex."""
    skin = face.part("skin")
    if len(skin):
        return skin
    return np.flatnonzero(face.deformable).astype(np.int32)
