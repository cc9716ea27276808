"""Generated takes unlike facecast's own: other layouts, headbands, capture axes, units, motion.

``generate`` makes one kind of take (a technician's layout sheet, five stable markers, a Z-up lab in
mm, a half-second neutral hold). Real takes differ in all of these, so the benchmarks and tests also
run on ``VARIANTS``: evenly spread, sparse and dense layouts, 3-6 headband markers, Y-up or Z-up
capture axes in mm or m, motion from the first frame, the neutral hold at the end (not the start),
head rotations about the neck or the nose, larger and faster expressions. ``folds`` splits the ICT
expressions so that a take's truth is drawn only from shapes held out of whatever a prior was
fitted on.

``make_take(variant, out, seed, expressions)`` writes ``take.{c3d,trc,csv}``, ``take.layout.json``
and returns a ``VariantTruth`` whose ``posed(face)`` rebuilds the true vertices, head motion
included, in the face's axes and units (what ``facecast render`` should write).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from ...protocol.markers_file import MarkerTake
from ...protocol.units import UNIT_MM
from ..faces.face import Face
from .io import write_take
from .sampling import farthest_points
from .stabilise import matrix_from_euler

__all__ = [
    "PROTOCOLS",
    "VARIANTS",
    "Variant",
    "VariantTruth",
    "choose_layout",
    "family",
    "fold_protocol",
    "folds",
    "make_take",
]

#: Capture axes: face axes (x left, y up, z forward) -> lab axes.
AXES = {
    "yup": np.eye(3),  # optical-capture default: Y up, the actor facing +z
    "zup": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),  # Z up, facing -y
    "yup-side": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),  # Y up, facing +x
}


@dataclass(frozen=True)
class Variant:
    """One kind of take. Lengths in mm, angles in degrees, times in seconds."""

    name: str
    placement: str = "even"  # even | technician | motion
    markers: int = 64  # face markers plus headband markers
    stable: int = 4
    axes: str = "yup"
    units: str = "mm"  # mm | m (as written to the file)
    hold: float = 0.0  # neutral hold at the start
    neutral_last: bool = (
        False  # the take runs backwards: it starts on an expression, the hold ends it
    )
    pivot: str = "head"  # head | neck | nose: the point the head turns about
    head_deg: tuple[float, float, float] = (8.0, 12.0, 5.0)  # pitch, yaw, roll amplitude
    head_mm: tuple[float, float, float] = (12.0, 8.0, 10.0)
    expr_max: float = 1.0  # largest expression weight
    expr_period: tuple[float, float] = (0.25, 0.7)  # seconds between expression keys
    noise: float = 0.5
    lab_origin: tuple[float, float, float] = (120.0, 1600.0, -300.0)


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("issue16"),  # the take: 64 even markers, 4 headband, Y-up mm, no hold
        Variant("sparse30", markers=30, stable=3, axes="zup"),
        Variant("dense100", markers=100, stable=6, units="m", axes="yup-side"),
        Variant("technician", placement="technician", markers=60, stable=5, axes="zup", hold=0.5),
        Variant("neck-pivot", pivot="neck", head_deg=(15.0, 25.0, 8.0), stable=5, units="m"),
        Variant("neutral-last", hold=0.5, neutral_last=True, axes="zup"),  # no neutral at frame 0
        Variant(
            "fast-large",
            expr_max=1.0,
            expr_period=(0.12, 0.3),
            head_deg=(12.0, 20.0, 8.0),
            pivot="nose",
            stable=4,
            axes="zup",
        ),
    )
}


@dataclass
class VariantTruth:
    """The ground truth of a variant take. ``weights (T, E)`` over ``expressions`` (indices into the
    ICT expressions); ``r (T, 3, 3)``, ``trans (T, 3)`` mm: posed = ``R (x - pivot) + pivot + trans``
    in face axes (mm); ``stable`` the headband marker names; ``vertices`` the marker vertex ids."""

    variant: Variant
    fps: float
    names: list[str]
    vertices: np.ndarray
    stable: list[str]
    expressions: np.ndarray
    weights: np.ndarray
    r: np.ndarray
    trans: np.ndarray
    pivot_mm: np.ndarray
    paths: dict[str, Path] = field(default_factory=dict)

    def local(self, face: Face, deltas: np.ndarray, frames: np.ndarray | None = None) -> np.ndarray:
        """``(F, V, 3) float32`` true vertices without head motion (face units)."""
        w = self.weights if frames is None else self.weights[frames]
        d = deltas[self.expressions].reshape(len(self.expressions), -1)
        return (face.vertices[None] + (w.astype(np.float32) @ d).reshape(len(w), -1, 3)).astype(
            np.float32
        )

    def head(self, face: Face, frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(R (F, 3, 3), t (F, 3))`` the true head transform in face units: ``x' = R x + t``."""
        sl = slice(None) if frames is None else frames
        r, tr = self.r[sl], self.trans[sl]
        p = self.pivot_mm / face.mm_per_unit
        return r, p - np.einsum("tij,j->ti", r, p) + tr / face.mm_per_unit

    def posed(self, face: Face, deltas: np.ndarray, frames: np.ndarray | None = None) -> np.ndarray:
        """``(F, V, 3)`` true vertices with head motion (face units): what ``render`` should write."""
        r, t = self.head(face, frames)
        return (np.einsum("tij,tvj->tvi", r, self.local(face, deltas, frames)) + t[:, None]).astype(
            np.float32
        )


def folds(
    n_expressions: int, k: int = 5, seed: int = 0, usable: np.ndarray | None = None
) -> list[np.ndarray]:
    """``k`` disjoint held-out index sets over the expressions (``usable`` ones only)."""
    idx = np.arange(n_expressions) if usable is None else np.asarray(usable)
    perm = np.random.default_rng(seed).permutation(idx)
    return [np.sort(perm[i::k]) for i in range(k)]


#: Expression fold protocols (``fold_protocol``).
PROTOCOLS = ("random", "strict", "mirror")


def family(name: str) -> str:
    """An expression's family: its name without the side (``browDown_L`` -> ``browDown``;
    ``mouthLeft``/``mouthRight`` -> ``mouthLeftRight``)."""
    if name in ("mouthLeft", "mouthRight"):
        return "mouthLeftRight"
    return name[:-2] if name.endswith(("_L", "_R")) else name


def fold_protocol(
    names: list[str], protocol: str, k: int = 3, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(held_out, prior_shapes)]`` index pairs into ``names`` for a fold protocol:

    - ``random``: ``folds`` (k folds); the prior may hold a held-out shape's other side;
    - ``strict``: k folds of whole families: neither a held-out shape nor its other side (nor a
      mirror of either) is in the prior: the expressions it has never seen in any form;
    - ``mirror``: the left sides of the two-sided families, then the right sides; the prior has every
      other shape, the held-out one's other side included: a shape known only by its mirror image
      (as the ICT FaceKit ships only one side of several pairs).
    """
    use = usable_expressions(names)
    if protocol == "random":
        return [(h, np.setdiff1d(use, h)) for h in folds(len(names), k, seed, use)]
    fams = sorted({family(names[i]) for i in use})
    if protocol == "strict":
        perm = np.random.default_rng(seed).permutation(fams)
        out = []
        for j in range(k):
            held = np.array([i for i in use if family(names[i]) in set(perm[j::k])])
            out.append((held, np.setdiff1d(use, held)))
        return out
    if protocol == "mirror":
        two = {f for f in fams if sum(family(names[i]) == f for i in use) == 2}
        out = []
        for side in ("_L", "_R"):
            held = np.array(
                [
                    i
                    for i in use
                    if family(names[i]) in two
                    and (
                        names[i].endswith(side)
                        or names[i] == f"mouth{'Left' if side == '_L' else 'Right'}"
                    )
                ]
            )
            out.append((held, np.setdiff1d(use, held)))
        return out
    raise ValueError(f"unknown fold protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")


def usable_expressions(names: list[str]) -> np.ndarray:
    """Expressions a take may show (not pupil dilation, which moves no skin)."""
    return np.array([i for i, n in enumerate(names) if not n.startswith("Pupil")])


def choose_layout(
    face: Face, deltas: np.ndarray, v: Variant
) -> tuple[list[str], np.ndarray, dict, list[str]]:
    """``(names, vertex ids, layout markers, stable names)`` for a variant. ``even``: headband plus
    face markers spread evenly (farthest points, unweighted) over the front skin; else ``generate``'s
    placements."""
    from .generate import choose_markers

    if v.placement != "even":
        return choose_markers(face, deltas, v.markers, v.stable, v.placement)
    import trimesh

    verts = face.vertices.astype(np.float64)
    skin = face.part("skin")
    motion = np.linalg.norm(deltas, axis=2).max(axis=0) * face.mm_per_unit
    eye_y = (face.fp_position("3.5")[1] + face.fp_position("3.6")[1]) / 2
    chin_y = face.fp_position("2.1")[1]
    nose_z = face.fp_position("9.3")[2]
    mw = abs(face.fp_position("8.3")[0] - face.fp_position("8.4")[0])
    still = skin[(motion[skin] < 0.01) & (verts[skin, 1] > eye_y)]
    st = still[farthest_points(verts[still], v.stable)]
    normals = trimesh.Trimesh(face.vertices, face.triangles, process=False).vertex_normals
    lids = np.concatenate(
        [
            np.flatnonzero(np.linalg.norm(verts - face.pivot(e), axis=1) < 0.45 * mw)
            for e in ("eye_l", "eye_r")
        ]
    )
    cand = skin[
        (normals[skin, 2] > 0.3)
        & (verts[skin, 2] > nose_z - 1.6 * mw)
        & (np.abs(verts[skin, 0]) < 1.5 * mw)
        & (verts[skin, 1] < eye_y + 1.5 * mw)
        & (verts[skin, 1] > chin_y - 0.1 * mw)
    ]
    cand = np.setdiff1d(cand, np.r_[lids, st])
    pick = cand[farthest_points(verts[cand], v.markers - len(st), seed_points=verts[st])]
    names = [f"HB{i + 1}" for i in range(len(st))] + [f"F{j + 1:03d}" for j in range(len(pick))]
    ids = np.r_[st, pick].astype(np.int64)
    spec = {n: {"vertex": int(i)} for n, i in zip(names, ids)}
    return names, ids, spec, names[: len(st)]


def _curve(
    rng, n: int, fps: float, amp: float, period: tuple[float, float], hold: int
) -> np.ndarray:
    """A smooth random curve in [-amp, amp], 0 at frame 0 (the head's rest: the face frame) and
    through the hold, moving from frame 0 without one."""
    keys = [0.0] + ([hold / fps] if hold else [])
    while keys[-1] < n / fps + 1:
        keys.append(keys[-1] + rng.uniform(*period))
    vals = rng.uniform(-amp, amp, len(keys))
    vals[: 1 + (hold > 0)] = 0.0
    return PchipInterpolator(keys, vals)(np.arange(n) / fps)


def _weights(
    rng, usable: np.ndarray, n_expr: int, n: int, fps: float, hold: int, v: Variant
) -> np.ndarray:
    keys = [0] + ([hold] if hold else [])
    while keys[-1] < n + int(fps):
        keys.append(keys[-1] + max(1, int(rng.uniform(*v.expr_period) * fps)))
    kv = np.zeros((len(keys), n_expr))
    for k in range(1 + (hold > 0), len(keys)):
        act = rng.choice(usable, size=min(len(usable), int(rng.integers(2, 5))), replace=False)
        kv[k, act] = rng.uniform(0.3 * v.expr_max, v.expr_max, len(act))
        if rng.random() < 0.1:
            kv[k] = 0.0
    return np.clip(
        PchipInterpolator(np.asarray(keys) / fps, kv, axis=0)(np.arange(n) / fps), 0.0, 1.0
    )


def make_take(
    variant: Variant | str,
    out: str | Path,
    *,
    seed: int = 1,
    seconds: float = 3.0,
    fps: float = 120.0,
    expressions: np.ndarray | None = None,
    formats: tuple[str, ...] = ("c3d", "trc", "csv"),
    gaps: bool = True,
    face: Face | None = None,
) -> VariantTruth:
    """Write a take of ``variant`` into ``out`` (see the module docstring); ``expressions``: the ICT
    expression indices the truth blends (default: every usable one)."""
    from .generate import load_expressions, load_ict

    v = VARIANTS[variant] if isinstance(variant, str) else variant
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    face = face or load_ict()
    enames, deltas = load_expressions(face)
    expr = usable_expressions(enames) if expressions is None else np.asarray(expressions)
    names, verts, spec, stable = choose_layout(face, deltas, v)
    n = max(2, round(seconds * fps))
    hold = min(n - 1, round(v.hold * fps))
    w = _weights(rng, np.arange(len(expr)), len(expr), n, fps, hold, v)
    mm = face.mm_per_unit
    d = deltas[expr][:, verts].astype(np.float64)
    local = (face.vertices[verts][None].astype(np.float64) + np.einsum("te,emc->tmc", w, d)) * mm
    ang = np.stack([_curve(rng, n, fps, a, (0.6, 1.5), hold) for a in np.radians(v.head_deg)], -1)
    tr = np.stack([_curve(rng, n, fps, a, (0.8, 2.0), hold) for a in v.head_mm], -1)
    if v.neutral_last:
        w, local = w[::-1].copy(), local[::-1].copy()
        ang, tr = ang[::-1].copy(), tr[::-1].copy()
    r = matrix_from_euler(ang)
    if v.pivot == "neck":
        pivot = face.pivot("head") * mm + np.array([0.0, -90.0, -20.0])
    elif v.pivot == "nose":
        pivot = face.fp_position("9.3") * mm
    else:
        pivot = face.pivot("head") * mm
    posed = np.einsum("tij,tmj->tmi", r, local - pivot) + pivot + tr[:, None]
    lab = posed @ AXES[v.axes].T + np.asarray(v.lab_origin)
    noisy = lab + rng.normal(0.0, v.noise, lab.shape)
    if gaps:
        for j in range(len(names)):
            if names[j] in stable and j % 2 == 0:
                continue
            for _ in range(int(rng.integers(0, 3))):
                length = int(rng.integers(3, max(4, int(0.3 * fps))))
                start = int(rng.integers(hold + 1, max(hold + 2, n - length)))
                start = n - length - start if v.neutral_last else start
                noisy[start : start + length, j] = np.nan
    scale = 1.0 / UNIT_MM[v.units]  # the noisy positions are in mm
    take = MarkerTake(names, noisy * scale, float(fps), v.units)
    paths: dict[str, Path] = {}
    for fmt in formats:
        paths[fmt] = write_take(take, out / f"take.{fmt}")
    paths["layout"] = out / "take.layout.json"
    paths["layout"].write_text(
        json.dumps({"units": v.units, "stable": stable, "markers": spec}, indent=1) + "\n"
    )
    return VariantTruth(v, float(fps), names, verts, stable, expr, w, r, tr, pivot, paths)
