"""What drivers produce: the state of a face at one media time, and animations as sequences of them."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import numpy as np

#: Number of MPEG-4 FAPs (2 high-level + 66 low-level).
N_FAPS = 68


def zero_faps() -> np.ndarray:
    """``(69,) float64`` FAP vector; index k holds FAP k (1..68), index 0 is unused."""
    return np.zeros(N_FAPS + 1, dtype=np.float64)


@dataclass
class FaceState:
    """The face at media time ``t`` (seconds from the start of the stream).

    Attributes:
        t: media time in seconds.
        faps: ``(69,) float64``, index k = low-level FAP k in its FAPU (angles in AU = 1e-5 rad);
            indices 0, 1, 2 are unused (high-level FAPs live in ``viseme`` / ``expression``).
        viseme: FAP 1 as ``(select1, select2, blend)``: ids 0-14, blend 0-63 (weight of select1 =
            blend/63), or None.
        expression: FAP 2 as ``(select1, intensity1, select2, intensity2)``: ids 0-6, intensities
            0-63, or None.
        controls: ``(K, 3) float32`` displacements of an explicit control set (e.g. retargeted mocap
            markers) in mesh units, added to what the FAPs give; None for pure FAP input.
        head: ``(3, 4)`` rigid head transform ``[R | t]`` (mesh units) that replaces FAPs 48-50, or None.
        shapes: per-vertex shapes mixed in by ``shape_weights`` (``Shapes``; e.g. a mocap face prior's
            fit, ``mocap.prior``), added to what the controls give before the rigid transforms, or
            None.
        shape_weights: ``(E,)`` the weights of ``shapes``' deltas.
    """

    t: float = 0.0
    faps: np.ndarray = field(default_factory=zero_faps)
    viseme: tuple[int, int, int] | None = None
    expression: tuple[int, int, int, int] | None = None
    controls: np.ndarray | None = None
    head: np.ndarray | None = None
    shapes: Shapes | None = None
    shape_weights: np.ndarray | None = None

    def offsets(self) -> np.ndarray | None:
        """``(n, 3) float32`` this state's per-vertex displacements at ``shapes.vertices`` (None without)."""
        if self.shapes is None or self.shape_weights is None or not np.any(self.shape_weights):
            return None
        return self.shapes.mix(self.shape_weights)


@dataclass(frozen=True, eq=False)
class Shapes:
    """Per-vertex shapes a ``FaceState`` mixes in: ``deltas (E, n, 3) float32`` at the face's
    ``vertices (n,) int`` (distinct; face units, the face's rest frame: the rigid transforms move
    them as they move the vertices). One object is shared by every state of a stream."""

    vertices: np.ndarray
    deltas: np.ndarray

    def mix(self, weights: np.ndarray) -> np.ndarray:
        """``(n, 3) float32``: the deltas weighted by ``weights (E,)`` (its zeros skipped). One
        shape at a time, not a BLAS product: on a loaded machine OpenBLAS's threads made that
        ~12 ms (p50) where this loop takes 0.2 ms for 20 shapes over 17k vertices."""
        w = np.asarray(weights, dtype=np.float32).reshape(-1)
        out = np.zeros(self.deltas.shape[1:], dtype=np.float32)
        tmp = np.empty_like(out)  # one scratch row, not a fresh product per shape
        for i in np.flatnonzero(w):
            out += np.multiply(self.deltas[i], w[i], out=tmp)
        return out

    @cached_property
    def flat(self) -> np.ndarray:
        """``(3n,) int64``: the rows' coordinates in a flattened ``(V, 3)`` array (a 1-D index
        adds ~4x faster than a row gather and scatter)."""
        v = np.asarray(self.vertices, dtype=np.int64)
        return (v[:, None] * 3 + np.arange(3)).ravel()


@dataclass
class Animation:
    """A batch input decoded into face states at a fixed frame rate.

    Attributes:
        fps: frames per second of ``states``.
        states: one ``FaceState`` per frame, ``states[i].t == i / fps``.
        control_vertices: ``(K,) int32`` vertex ids of the face that ``FaceState.controls`` move
            (mocap markers placed on the face), or None when only FAPs drive the face.
        source: what it was decoded from (file name), for messages.
    """

    fps: float
    states: list[FaceState]
    control_vertices: np.ndarray | None = None
    source: str = ""

    def __len__(self) -> int:
        return len(self.states)


class LiveDriver(Protocol):
    """Turns a live producer's input (PCM chunks, marker frames) into face states, incrementally.

    ``control_vertices`` is as in ``Animation``. ``push`` takes one chunk: PCM samples ``(n,) float32``
    in [-1, 1] at the driver's declared rate, or markers ``(M, 3) float32`` (NaN = occluded), with the
    media time ``t`` of its first sample / of the frame; it returns the face states that became
    final, oldest first (possibly none, with the look-ahead a driver needs).
    """

    control_vertices: np.ndarray | None

    def push(self, data: np.ndarray, t: float) -> list[FaceState]: ...
