"""Layers from their REST bodies: ``from_spec`` builds the layer a ``protocol.layers`` model
(``LayerSpec``: idle, expression, gaze, head) describes. The model is the one validation, the
API's documented schema; plain data (a script's) is validated by it first (``parse_layer``), so
only ``InputError`` naming the field is raised.

Times are seconds from the call, shifted by ``t0`` (e.g. the session's media time now):

- ``{"kind": "expression", "expression": "joy" | 1, "faps": {"31": 100}, "amount": 0.8,
  "envelope": {"start": 0, "attack_peak": 0.3, "relax": 2, "end": 2.5}, "regions": ["mouth"]}``
- ``{"kind": "idle", "seed": 3, "amount": 1, "blink_rate": 17}``
- ``{"kind": "gaze", "target": "camera" | [x, y, z] | {"direction": [x, y, z]}, "amount": 1,
  "envelope": {...}}`` (points in the face's mesh units)
- ``{"kind": "head", "gesture": "nod" | "shake" | "tilt", "amount": 1, "repetitions": 2,
  "envelope": {...}}`` or ``{"kind": "head", "pose": {"pitch": 0, "yaw": 10, "roll": 0}, ...}``
"""

from __future__ import annotations

import numpy as np

from ...protocol import layers as wire
from ..errors import InputError
from ..mpeg4.highlevel import EXPRESSION_NAMES
from .gaze import GazeLayer
from .head import HeadGesture, HeadPose
from .idle import IdleLayer
from .model import Envelope, GazeTarget, Layer
from .overlay import ExpressionLayer

Spec = wire.IdleLayer | wire.ExpressionLayer | wire.GazeLayer | wire.HeadLayer


def from_spec(spec: object, t0: float = 0.0) -> Layer:
    """The layer ``spec`` describes (a ``protocol.layers`` model, or plain data validated as
    one), its times shifted by ``t0`` s. Raises ``InputError`` saying which field is wrong."""
    if not isinstance(spec, Spec):
        spec = wire.parse_layer(spec)  # MessageError: an InputError naming the field
    try:
        if isinstance(spec, wire.ExpressionLayer):
            return _expression(spec, t0)
        if isinstance(spec, wire.IdleLayer):
            given = spec.model_dump(exclude={"kind"}, exclude_none=True)
            return IdleLayer(**given)
        if isinstance(spec, wire.GazeLayer):
            return GazeLayer(
                target=_target(spec.target),
                amount=spec.amount,
                envelope=_envelope(spec.envelope, t0),
            )
        return _head(spec, t0)
    except InputError:
        raise
    except (ValueError, TypeError, KeyError) as e:  # what the layers' own checks add
        raise InputError(f"{spec.kind} layer: {e}") from None


def _envelope(e: wire.Envelope | None, t0: float) -> Envelope:
    if e is None:
        return Envelope(start=t0) if t0 else Envelope()
    return Envelope(
        start=(e.start or 0.0) + t0,
        attack_peak=None if e.attack_peak is None else e.attack_peak + t0,
        relax=None if e.relax is None else e.relax + t0,
        end=None if e.end is None else e.end + t0,
    )


def _expression(spec: wire.ExpressionLayer, t0: float) -> ExpressionLayer:
    e = spec.expression
    expression = EXPRESSION_NAMES.index(e) if isinstance(e, str) else int(e or 0)
    faps = None
    if spec.faps:
        faps = np.zeros(69)
        for k, v in spec.faps.items():
            faps[k] = v
    return ExpressionLayer(
        expression=expression,
        faps=faps,
        amount=spec.amount,
        envelope=_envelope(spec.envelope, t0),
        regions=None if spec.regions is None else tuple(spec.regions),
    )


def _target(value: str | tuple[float, float, float] | wire.GazeDirection) -> GazeTarget:
    if isinstance(value, wire.GazeDirection):
        return GazeTarget(direction=np.asarray(value.direction, dtype=np.float64))
    if isinstance(value, str):  # "camera"
        return GazeTarget.camera()
    return GazeTarget(point=np.asarray(value, dtype=np.float64))


def _head(spec: wire.HeadLayer, t0: float) -> Layer:
    envelope = _envelope(spec.envelope, t0)
    if spec.pose is not None:
        p = spec.pose
        return HeadPose(p.pitch, p.yaw, p.roll, amount=spec.amount, envelope=envelope)
    assert spec.gesture is not None  # (the model has one or the other)
    return HeadGesture(
        kind=spec.gesture,
        amount=spec.amount,
        envelope=envelope,
        repetitions=spec.repetitions or 1,
    )
