"""The face model: a neutral mesh with its parts, MPEG-4 feature points, units and rigid groups."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ...protocol.units import UNIT_MM  # millimetres per mesh unit (also imported from here)

#: Rigid groups, in the order of the per-frame transform array ``(G, 3, 4)``. Every vertex belongs
#: to exactly one: the head carries everything; the jaw also carries the lower teeth, lower gums and
#: tongue; each eyeball turns about its own centre.
RIGID_GROUPS: tuple[str, ...] = ("head", "jaw", "eye_l", "eye_r")

#: Parts that ride on the jaw (when the face has them).
JAW_PARTS: tuple[str, ...] = ("teeth_lower", "gums_lower", "tongue")


#: The 84 MPEG-4 feature point ids, by group (ISO/IEC 14496-2 FDP groups 2-11).
FP_GROUP_SIZES: dict[int, int] = {2: 14, 3: 14, 4: 6, 5: 4, 6: 4, 7: 1, 8: 10, 9: 15, 10: 10, 11: 6}
FEATURE_POINT_IDS: tuple[str, ...] = tuple(
    f"{g}.{i}" for g, n in FP_GROUP_SIZES.items() for i in range(1, n + 1)
)

#: Part names with a fixed meaning. Other names (eyelashes, mouth_socket, hair, ...) are allowed.
KNOWN_PARTS: tuple[str, ...] = (
    "skin",
    "eye_l",
    "eye_r",
    "teeth_upper",
    "teeth_lower",
    "gums_upper",
    "gums_lower",
    "tongue",
)


@dataclass(eq=False)
class Face:
    """A neutral face mesh and what facecast knows about it.

    Attributes:
        name: built-in name or mesh path it was loaded from.
        vertices: ``(V, 3) float32`` neutral positions in ``units``; axes as MPEG-4 (y up, z out of
            the face, x to the face's left).
        triangles: ``(F, 3) int32`` vertex ids.
        units: ``"mm" | "cm" | "m" | "in"``.
        parts: part name -> sorted ``int32`` vertex ids (``skin`` is the deformable surface; see
            ``KNOWN_PARTS``). Vertices in no part are treated as skin.
        feature_points: MPEG-4 feature point id (``"2.1"``) -> vertex id.
        pivots: optional ``(3,)`` rotation centres, keys ``head`` (FP 7.1), ``jaw`` (the jaw hinge),
            ``eye_l``, ``eye_r``; missing ones are estimated by ``pivot()``.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    units: str = "mm"
    parts: dict[str, np.ndarray] = field(default_factory=dict)
    feature_points: dict[str, int] = field(default_factory=dict)
    pivots: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        self.parts = {
            k: _sorted_unique(np.asarray(v, dtype=np.int32)) for k, v in self.parts.items()
        }
        self.feature_points = {str(k): int(v) for k, v in self.feature_points.items()}
        self.pivots = {k: np.asarray(v, dtype=np.float64) for k, v in self.pivots.items()}
        if self.units not in UNIT_MM:
            raise ValueError(f"units must be one of {sorted(UNIT_MM)}, not {self.units!r}")

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def mm_per_unit(self) -> float:
        """Millimetres per mesh unit (10 for a centimetre mesh)."""
        return UNIT_MM[self.units]

    @cached_property
    def mesh_hash(self) -> str:
        """Content hash of the neutral vertices and triangles (hex, 16 chars): the operator cache key."""
        h = hashlib.blake2b(digest_size=8)
        h.update(self.vertices.tobytes())
        h.update(self.triangles.tobytes())
        return h.hexdigest()

    def fp_position(self, fp: str) -> np.ndarray:
        """``(3,) float64`` neutral position of feature point ``fp`` (KeyError if the face lacks it)."""
        return self.vertices[self.feature_points[fp]].astype(np.float64)

    def part(self, name: str) -> np.ndarray:
        """Vertex ids of a part (empty if the face has no such part)."""
        return self.parts.get(name, np.zeros(0, dtype=np.int32))

    @cached_property
    def rigid_group(self) -> np.ndarray:
        """``(V,) uint8`` index into ``RIGID_GROUPS`` for every vertex."""
        g = np.zeros(self.n_vertices, dtype=np.uint8)
        for p in JAW_PARTS:
            g[self.part(p)] = RIGID_GROUPS.index("jaw")
        g[self.part("eye_l")] = RIGID_GROUPS.index("eye_l")
        g[self.part("eye_r")] = RIGID_GROUPS.index("eye_r")
        return g

    @cached_property
    def deformable(self) -> np.ndarray:
        """``(V,) bool``: vertices a deformation operator may move (all but eyeballs and teeth)."""
        mask = np.ones(self.n_vertices, dtype=bool)
        for p in ("eye_l", "eye_r", "teeth_upper", "teeth_lower"):
            mask[self.part(p)] = False
        return mask

    def pivot(self, name: str) -> np.ndarray:
        """``(3,) float64`` rotation centre of a rigid group (given, or estimated from the mesh)."""
        if name in self.pivots:
            return self.pivots[name]
        if name in ("eye_l", "eye_r"):
            ids = self.part(name)
            if len(ids):
                return _sphere_centre(self.vertices[ids].astype(np.float64))
            fp = "3.5" if name == "eye_l" else "3.6"
            return self.fp_position(fp) if fp in self.feature_points else np.zeros(3)
        lo, hi = (
            self.vertices.min(axis=0).astype(np.float64),
            self.vertices.max(axis=0).astype(np.float64),
        )
        if name == "head":
            if "7.1" in self.feature_points:
                return self.fp_position("7.1")
            return np.array(
                [
                    (lo[0] + hi[0]) / 2,
                    lo[1] + 0.25 * (hi[1] - lo[1]),
                    lo[2] + 0.35 * (hi[2] - lo[2]),
                ]
            )
        if name == "jaw":
            # The hinge sits just in front of the ears, a little below the eyes.
            ears = [
                self.fp_position(f)
                for f in ("10.9", "10.10", "10.7", "10.8")
                if f in self.feature_points
            ]
            if ears:
                c = np.mean(ears, axis=0)
                return np.array([(lo[0] + hi[0]) / 2, c[1], c[2]])
            return np.array(
                [
                    (lo[0] + hi[0]) / 2,
                    lo[1] + 0.55 * (hi[1] - lo[1]),
                    lo[2] + 0.45 * (hi[2] - lo[2]),
                ]
            )
        raise KeyError(name)


def _sorted_unique(ids: np.ndarray) -> np.ndarray:
    """``np.unique`` for int ids (numpy 2.4's hash-based unique takes ~1 s for 400k ids; sorting takes ms)."""
    s = np.sort(ids.ravel())
    return s[np.concatenate([[True], s[1:] != s[:-1]])] if len(s) else s


def _sphere_centre(points: np.ndarray) -> np.ndarray:
    """Least-squares sphere centre of ``(N, 3)`` points (falls back to the centroid)."""
    if len(points) < 4:
        return points.mean(axis=0)
    a = np.c_[2 * points, np.ones(len(points))]
    b = (points**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:3]
    if (
        not np.all(np.isfinite(centre))
        or np.linalg.norm(centre - points.mean(axis=0)) > np.ptp(points, axis=0).max()
    ):
        return points.mean(axis=0)
    return centre
