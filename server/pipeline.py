"""The per-face animation pipeline: FaceState -> rig -> D, transforms -> deformer -> vertices."""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable

import numpy as np

from .mpeg4.rig import FapRig
from .state import Animation, FaceState, Shapes

log = logging.getLogger(__name__)

#: Frames deformed per ``deform_batch`` call in ``Animator.render``.
CHUNK = 32


def turn(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``(n, 3) float32``: ``points (n, 3) float32`` turned by ``rotation (3, 3)`` (``p @ R.T``),
    column by column: einsum's loop over three-long rows took 0.25-0.3 ms for 17k points, a BLAS
    product threads (and stalls on a loaded machine) on larger faces; this takes ~0.05 ms."""
    out = np.empty_like(points)
    tmp = np.empty(len(points), dtype=points.dtype)
    for r in range(3):
        col = out[:, r]
        np.multiply(points[:, 0], rotation[r, 0], out=col)
        col += np.multiply(points[:, 1], rotation[r, 1], out=tmp)
        col += np.multiply(points[:, 2], rotation[r, 2], out=tmp)
    return out


class Animator:
    """Animates one face: builds its FAP rig, its deformation operator and a deformer.

    Args:
        face: the ``Face``.
        engine: deformation engine (``fp`` | ``rbf`` | ``shell``), see ``server.deform.build``.
        backend: ``auto`` | ``numpy`` | ``opencl``; ``device``: OpenCL device selector.
        control_vertices: ``(K,)`` explicit control vertices (mocap); None = the face's FAP controls.
        operator: a ready ``Operator`` for these controls (skips ``get_operator``).
        per_axis: FAP-driven feature points constrained only on their FAP axes (``mpeg4.rig``).
        **engine_params: passed to ``get_operator``.
    """

    def __init__(
        self,
        face,
        *,
        engine: str = "fp",
        backend: str = "auto",
        device: str | None = None,
        control_vertices: np.ndarray | None = None,
        operator=None,
        per_axis: bool = False,
        **engine_params,
    ):
        from .backends import make_deformer

        self.face = face
        #: per ``Shapes`` of a stream: its vertices' rigid groups and whether they are one group
        self._shape_groups: weakref.WeakKeyDictionary[Shapes, tuple[np.ndarray, bool]] = (
            weakref.WeakKeyDictionary()
        )
        self.rig = FapRig(face, control_vertices, per_axis=per_axis)
        if operator is None:
            from .deform.build import get_operator

            operator = get_operator(
                face,
                self.rig.control_vertices,
                engine=engine,
                constrained=self.rig.constrained,
                **engine_params,
            )
        if operator.n_controls != self.rig.n_controls or operator.n_vertices != face.n_vertices:
            raise ValueError(
                f"operator is {operator.n_vertices}x{operator.n_controls}, face/controls need "
                f"{face.n_vertices}x{self.rig.n_controls}"
            )
        self.operator = operator
        self.deformer = make_deformer(face, operator, backend, device)
        log.debug(
            "animator for %s: %d controls, engine %s, backend %s",
            face.name,
            self.rig.n_controls,
            engine,
            getattr(self.deformer, "name", type(self.deformer).__name__),
        )

    def solve(self, state: FaceState) -> tuple[np.ndarray, np.ndarray]:
        """``(D (K, 3) float32, transforms (G, 3, 4) float32)`` of one state."""
        return self.rig.solve(state)

    def solve_batch(self, states: list[FaceState]) -> tuple[np.ndarray, np.ndarray]:
        """``(D (T, K, 3) float32, transforms (T, G, 3, 4) float32)`` of ``T`` states: the same
        bits as ``solve`` of each, about 10x less CPU per state in batches of 20 or more."""
        return self.rig.solve_batch(states)

    def frame(self, state: FaceState) -> np.ndarray:
        """Deformed vertices ``(V, 3) float32`` of one state."""
        D, T = self.solve(state)
        out = np.asarray(self.deformer.deform(D, T), dtype=np.float32)
        self.add_shapes(out[None], [state], T[None])
        return out

    def add_shapes(
        self, verts: np.ndarray, states: list[FaceState], transforms: np.ndarray
    ) -> None:
        """Add each state's per-vertex shapes (``FaceState.shapes``), turned by its rigid
        transforms ``(T, G, 3, 4)`` as the deformer turns the rest shape, to its deformed
        ``verts (T, V, 3)`` in place."""
        group = self.face.rigid_group
        for v, s, T in zip(verts, states, transforms):
            off = s.offsets()
            if off is None or s.shapes is None:
                continue
            R = np.asarray(T, dtype=np.float32)[:, :, :3]
            hit = self._shape_groups.get(s.shapes)
            if hit is None:  # once per stream, not per frame
                g = group[s.shapes.vertices]
                hit = self._shape_groups[s.shapes] = (g, bool((g == g[0]).all()))
            g, one = hit  # one rigid group (the usual case): one rotation
            off = turn(off, R[g[0]]) if one else np.einsum("nij,nj->ni", R[g], off)
            if v.flags.c_contiguous:
                flat = v.reshape(-1)  # a view
                flat[s.shapes.flat] += off.reshape(-1)
            else:
                v[s.shapes.vertices] += off

    def render(
        self, animation: Animation, progress: Callable[[int, int], None] | None = None
    ) -> np.ndarray:
        """All frames of ``animation``: ``(T, V, 3) float32``; ``progress(done, total)`` after each chunk."""
        total = len(animation.states)
        out = np.empty((total, self.face.n_vertices, 3), dtype=np.float32)
        for start in range(0, total, CHUNK):
            states = animation.states[start : start + CHUNK]
            D, T = self.solve_batch(states)
            self.deformer.deform_batch(D, T, out=out[start : start + len(states)])
            self.add_shapes(out[start : start + len(states)], states, T)
            if progress is not None:
                progress(start + len(states), total)
        return out
