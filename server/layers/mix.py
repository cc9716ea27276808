"""Mixing a primary face state with layers into one ``FaceState`` per frame, and a session's ``Mixer``.

The rules (Kshirsagar et al. and Kähler's combining slide, ``research/seed-000-B.md`` §2.2), in the
order they apply to one frame:

1. **Primary**: the producer's state, high-level FAPs expanded with the face's tables.
2. **Head pose**: contributions with a ``head`` pose replace the primary's head (FAPs 48-50, or
   its ``head`` transform) by their weight (several: averaged by weight).
3. **Offsets add**: each role's ``faps`` (plus its expanded viseme/expression) are added; inside
   one role, FAPs two layers weigh on are averaged by weight, ``Σ w·x / max(1, Σ w)`` (one layer at
   weight w adds ``w·x``; two at full weight give their mean).
4. **Closures**: where the primary holds the lips together (a /p b m/, silence: a lip pair's gap
   near or below contact) the offsets' lip-opening part is taken out, shared by both lips (their
   common shift, the corners and the spreading stay), and so is their jaw opening.
5. **Overrides** (``override``): absolute FAP values replace the result by their weight (blinks).
6. **Gaze**: eye yaw/pitch (FAPs 23-26) turned to the target from the eye centres under the final
   head pose, replacing the eyes' rotation by the weight.

The result keeps the primary's viseme, expression and controls: its ``faps`` are the mixed
low-level values minus the primary's high-level expansion, so the rig's ``expand`` gives the mix.
With no layers the primary is returned as it is.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterable, Sequence

import numpy as np

from ..errors import Conflict, InputError, NotFound
from ..state import FaceState
from .model import Contribution, GazeTarget, Geometry, Layer, Role

#: Lip pairs (upper lip FAP, + down; lower lip FAP, + up): inner mid, left, right; outer the same.
#: A pair's gap (FAPU MNS, 0 = the neutral closed mouth) is ``-(upper + lower)``.
LIP_PAIRS: np.ndarray = np.array([[4, 5], [8, 10], [9, 11], [51, 52], [55, 57], [56, 58]])
#: Primary lip gap (MNS) at and below which the lips count as closed, and above which as open;
#: in between the overlay may open them in proportion.
CLOSED_GAP, OPEN_GAP = 30.0, 150.0
_AU = 1e-5
_DEFAULT_GEOMETRY = Geometry()


def _expand(
    viseme: tuple[int, int, int] | None,
    expression: tuple[int, int, int, int] | None,
    geo: Geometry,
) -> np.ndarray | None:
    """``(69,)`` low-level FAPs of FAP 1/2 with the geometry's tables (None when both are None)."""
    if viseme is None and expression is None:
        return None
    from ..mpeg4.highlevel import expand

    return expand(FaceState(viseme=viseme, expression=expression), geo.visemes, geo.expressions)


def _rot(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """``Ry(yaw) · Rx(pitch) · Rz(roll)`` (radians), the rig's head rotation."""
    cp, sp, cy, sy, cr, sr = (
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
        np.cos(roll),
        np.sin(roll),
    )
    return np.array(
        [
            [cy * cr + sy * sp * sr, -cy * sr + sy * sp * cr, sy * cp],
            [cp * sr, cp * cr, -sp],
            [-sy * cr + cy * sp * sr, sy * sr + cy * sp * cr, cy * cp],
        ]
    )


def head_angles(head: np.ndarray, pivot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A head transform ``[R | t] (3, 4)`` as ``(pitch, yaw, roll)`` in AU (``R = Ry·Rx·Rz``) and
    the translation left over after rotating about ``pivot`` (mesh units)."""
    M = np.asarray(head, dtype=np.float64).reshape(3, 4)
    R = M[:, :3]
    pitch = float(np.arcsin(np.clip(-R[1, 2], -1.0, 1.0)))
    yaw = float(np.arctan2(R[0, 2], R[2, 2]))
    roll = float(np.arctan2(R[1, 0], R[1, 1]))
    rest = M[:, 3] - (pivot - R @ pivot)
    return np.array([pitch, yaw, roll]) / _AU, rest


def head_transform(
    angles: np.ndarray, pivot: np.ndarray, rest: np.ndarray | None = None
) -> np.ndarray:
    """``(3, 4)`` head transform of ``(pitch, yaw, roll)`` AU about ``pivot``, then ``rest``."""
    R = _rot(*(float(a) * _AU for a in angles))
    out = np.empty((3, 4))
    out[:, :3] = R
    out[:, 3] = pivot - R @ pivot + (0.0 if rest is None else rest)
    return out


def eye_angles(direction: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
    """``(yaw, pitch)`` radians with ``Ry(yaw) · Rx(pitch) · axis`` along ``direction`` (head-local;
    ``axis`` the eyeball's unit neutral forward axis)."""
    d = direction / np.linalg.norm(direction)
    ax, ay, az = (float(v) for v in axis)
    r = float(np.hypot(ay, az))
    phi = float(np.arctan2(az, ay))
    pitch = float(np.arccos(np.clip(d[1] / r, -1.0, 1.0))) - phi
    uz = ay * np.sin(pitch) + az * np.cos(pitch)
    yaw = float(np.arctan2(d[0], d[2]) - np.arctan2(ax, uz))
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    return yaw, pitch


def gaze_faps(target: GazeTarget, geo: Geometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(4,)`` FAPs 23-26 (AU) turning both eyes to ``target`` (a ``GazeTarget``) under the head
    transform ``[R | t]``: the eye centres move with the head, the target stays put."""
    out = np.empty(4)
    for i in range(2):
        if target.point is not None:
            d_world = target.point - (R @ geo.eye_pivots[i] + t)
        else:
            assert target.direction is not None
            d_world = target.direction
        yaw, pitch = eye_angles(R.T @ d_world, geo.eye_axes[i])
        out[i], out[2 + i] = yaw / _AU, pitch / _AU
    return out


def closure_factor(F: np.ndarray) -> np.ndarray:
    """``(6,)`` how closed each lip pair of the FAPs ``F (69,)`` is: 1 at or below ``CLOSED_GAP``,
    0 from ``OPEN_GAP``."""
    gap = -(F[LIP_PAIRS[:, 0]] + F[LIP_PAIRS[:, 1]])
    x = np.clip((gap - CLOSED_GAP) / (OPEN_GAP - CLOSED_GAP), 0.0, 1.0)
    return 1.0 - x * x * (3.0 - 2.0 * x)


def keep_closures(F: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Offsets ``A (69,)`` with the lip opening they would add to the primary's FAPs ``F`` taken out
    where ``F`` holds the lips closed (``closure_factor``); corners, spreading and the lips' common
    shift stay. Returns a new array."""
    c = closure_factor(F)
    if not np.any(c > 0):
        return A
    A = A.copy()
    top, bottom = LIP_PAIRS[:, 0], LIP_PAIRS[:, 1]
    opening = np.maximum(-(A[top] + A[bottom]), 0.0) * c
    A[top] += opening / 2
    A[bottom] += opening / 2
    if A[3] > 0:
        A[3] *= 1.0 - c[0]
    return A


def combine(
    primary: FaceState | None,
    items: Sequence[tuple[Role, Contribution]],
    t: float | None = None,
    *,
    geometry: Geometry | None = None,
    closures: bool = True,
) -> FaceState:
    """Mix ``primary`` with the layers' contributions (``(role, contribution)`` pairs) by the
    module's rules into one ``FaceState`` at ``t`` (default: the primary's time).

    ``primary`` None is the neutral face (and no closures to keep); ``closures`` False lets
    overlays open the lips whatever the primary does (a primary that does not speak).
    ``geometry``: the face's (``Geometry.of_rig``); needed for gaze and for head poses over a
    primary ``head`` transform (the default has no eyes).
    """
    if primary is None:
        primary, closures = FaceState(t=0.0 if t is None else t), False
    t = primary.t if t is None else float(t)
    if not items:
        return primary if t == primary.t else dataclasses.replace(primary, t=t)
    geo = _DEFAULT_GEOMETRY if geometry is None else geometry
    low = np.array(primary.faps, dtype=np.float64).reshape(-1)
    if low.shape != (69,):
        raise ValueError(f"FaceState.faps must have shape (69,), not {low.shape}")
    low[:3] = 0.0
    high = _expand(primary.viseme, primary.expression, geo)
    F = low if high is None else low + high

    # 2. head pose over the primary's
    head_out = primary.head
    rest: np.ndarray | None = None
    poses = [(c.head, c.head_weight) for _, c in items if c.head is not None and c.head_weight > 0]
    head_touched = bool(poses) or any(c.gaze is not None or _touches_head(c) for _, c in items)
    if primary.head is not None and head_touched:
        F[48:51], rest = head_angles(primary.head, geo.head_pivot)
    if poses:
        wsum = sum(w for _, w in poses)
        target = sum(np.asarray(p, dtype=np.float64) * w for p, w in poses) / wsum
        W = min(1.0, wsum)
        F[48:51] += W * (target - F[48:51])
        if rest is not None:
            rest = rest * (1.0 - W)

    # 3. offsets, averaged by weight inside a role
    sums: dict[Role, list[np.ndarray | float]] = {}
    for role, c in items:
        x = c.faps
        h = _expand(c.viseme, c.expression, geo)
        if h is not None:
            x = h if x is None else x + h
        if x is None:
            continue
        if c.amount != 1.0:
            x = c.amount * x
        w = c.weight
        acc = sums.get(role)
        if acc is None:
            sums[role] = [w * x, w]
        else:
            acc[0] = acc[0] + w * x
            acc[1] = acc[1] + w
    if sums:
        A = np.zeros(69)
        for num, den in sums.values():
            A += np.asarray(num) / np.maximum(1.0, den)
        A[:3] = 0.0
        if closures:
            A = keep_closures(F, A)
        F = F + A

    # 5. overrides
    num_o: np.ndarray | None = None
    den_o: np.ndarray | float = 0.0
    for _, c in items:
        if c.override is not None:
            w = c.override_weight
            num_o = w * c.override if num_o is None else num_o + w * c.override
            den_o = den_o + np.broadcast_to(w, (69,))
    if num_o is not None:
        den = np.asarray(den_o, dtype=np.float64)
        on = den > 0
        target = np.divide(num_o, den, out=np.zeros(69), where=on)
        W = np.minimum(1.0, den)
        F = np.where(on, F + W * (target - F), F)

    # head transform of the mix
    if rest is not None:
        head_out = head_transform(F[48:51], geo.head_pivot, rest)
        F[48:51] = 0.0

    # 6. gaze
    gazes = [(c.gaze, c.gaze_weight) for _, c in items if c.gaze is not None and c.gaze_weight > 0]
    if gazes:
        if head_out is not None:
            H = np.asarray(head_out, dtype=np.float64).reshape(3, 4)
        else:
            H = head_transform(F[48:51], geo.head_pivot)
        wsum = sum(w for _, w in gazes)
        eyes = sum(gaze_faps(g, geo, H[:, :3], H[:, 3]) * w for g, w in gazes) / wsum
        W = min(1.0, wsum)
        F[23:27] += W * (eyes - F[23:27])

    out = F if high is None else F - high
    out[:3] = 0.0
    return FaceState(
        t=t,
        faps=out,
        viseme=primary.viseme,
        expression=primary.expression,
        controls=primary.controls,
        head=head_out,
    )


def _touches_head(c: Contribution) -> bool:
    """Whether ``c`` moves FAPs 48-50 (offsets or overrides)."""
    return any(v is not None and bool(np.any(v[48:51] != 0)) for v in (c.faps, c.override))


def mix(
    primary: FaceState | None,
    layers: Iterable[Layer],
    t: float | None = None,
    *,
    geometry: Geometry | None = None,
    closures: bool = True,
) -> FaceState:
    """Sample every layer at ``t`` (default: the primary's time) and ``combine`` them with
    ``primary``: the one pure entry point of a frame's mix."""
    if t is None:
        t = 0.0 if primary is None else primary.t
    items = [(layer.role, layer.sample(t)) for layer in layers]
    return combine(primary, items, t, geometry=geometry, closures=closures)


class Mixer:
    """A session's active layers by name, mixed with the primary of each frame.

    Thread-safe: ``set`` / ``remove`` / ``change`` may run on any thread while another mixes
    (``mix`` works on a snapshot taken under the lock). Layers whose ``end`` has passed are
    dropped as frames pass it.

    Args:
        geometry: the face's ``Geometry`` (gaze, head poses over transforms, high-level tables).
        closures: keep the primary's lip closures (False when the primary does not speak).
        max_layers: most layers held at once (``TooMany``... ``Conflict`` beyond it).
    """

    def __init__(
        self, geometry: Geometry | None = None, *, closures: bool = True, max_layers: int = 32
    ) -> None:
        self.geometry = geometry
        self.closures = closures
        self.max_layers = max_layers
        self._lock = threading.Lock()
        self._layers: dict[str, Layer] = {}

    @staticmethod
    def _check_name(name: str) -> str:
        if not isinstance(name, str) or not 0 < len(name) <= 64 or not name.isprintable():
            raise InputError("a layer name is 1-64 printable characters")
        return name

    def set(self, name: str, layer: Layer) -> None:
        """Add ``layer`` as ``name``, replacing a layer of that name. ``Conflict`` when full."""
        if not isinstance(layer, Layer):
            raise TypeError(f"not a layer: {type(layer).__name__}")
        name = self._check_name(name)
        with self._lock:
            if name not in self._layers and len(self._layers) >= self.max_layers:
                raise Conflict(f"a session holds at most {self.max_layers} layers")
            self._layers[name] = layer

    def add(self, name: str, layer: Layer) -> None:
        """Add ``layer`` as ``name``; ``Conflict`` if the name is taken."""
        with self._lock:
            if name in self._layers:
                raise Conflict(f"layer {name!r} exists already")
        self.set(name, layer)

    def remove(self, name: str) -> Layer | None:
        """Remove and return layer ``name`` (None if there was none)."""
        with self._lock:
            return self._layers.pop(name, None)

    def change(self, name: str, **fields: object) -> Layer:
        """Replace layer ``name`` by a copy with ``fields`` changed (layers are frozen dataclasses:
        ``change("smile", amount=0.5)``). ``NotFound`` without such a layer; ``InputError`` for a
        field the layer has not or a value it refuses."""
        with self._lock:
            layer = self._layers.get(name)
            if layer is None:
                raise NotFound(f"no layer {name!r}")
            try:
                new = dataclasses.replace(layer, **fields)  # type: ignore[type-var]
            except (TypeError, ValueError) as e:
                raise InputError(f"layer {name!r}: {e}") from None
            self._layers[name] = new
            return new

    def get(self, name: str) -> Layer | None:
        with self._lock:
            return self._layers.get(name)

    def layers(self) -> dict[str, Layer]:
        """A snapshot: name -> layer, in the order they were added."""
        with self._lock:
            return dict(self._layers)

    def clear(self) -> None:
        with self._lock:
            self._layers.clear()

    def __len__(self) -> int:
        return len(self._layers)

    def mix(self, primary: FaceState | None, t: float | None = None) -> FaceState:
        """The mixed state of this frame (``mix`` of the active layers); drops ended layers."""
        if t is None:
            t = 0.0 if primary is None else primary.t
        with self._lock:
            ended = [n for n, lay in self._layers.items() if lay.end is not None and lay.end < t]
            for n in ended:
                del self._layers[n]
            layers = list(self._layers.values())
        return mix(primary, layers, t, geometry=self.geometry, closures=self.closures)
