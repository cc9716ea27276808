"""Layers from plain data (a REST body, a script): ``from_spec`` checks everything and raises only
``InputError`` naming the field, so a client's JSON can be handed to it as it is.

A spec is a mapping with ``kind`` and that kind's fields; times are seconds of media time, shifted
by ``t0`` (e.g. the session's media time now):

- ``{"kind": "expression", "expression": "joy" | 1, "faps": {"31": 100}, "amount": 0.8,
  "envelope": {"start": 0, "attack_peak": 0.3, "relax": 2, "end": 2.5}, "regions": ["mouth"]}``
- ``{"kind": "idle", "seed": 3, "amount": 1, "blink_rate": 17}``
- ``{"kind": "gaze", "target": "camera" | [x, y, z] | {"direction": [x, y, z]}, "amount": 1,
  "envelope": {...}}`` (points in the face's mesh units)
- ``{"kind": "head", "gesture": "nod" | "shake" | "tilt", "amount": 1, "repetitions": 2,
  "envelope": {...}}`` or ``{"kind": "head", "pose": {"pitch": 0, "yaw": 10, "roll": 0}, ...}``
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import InputError
from ..mpeg4.highlevel import EXPRESSION_NAMES
from .gaze import GazeLayer
from .head import HeadGesture, HeadPose
from .idle import IdleLayer
from .model import Envelope, GazeTarget, Layer
from .overlay import ExpressionLayer

#: Fields each kind accepts (besides ``kind``).
FIELDS: dict[str, frozenset[str]] = {
    "expression": frozenset({"expression", "faps", "amount", "envelope", "regions"}),
    "idle": frozenset({"seed", "amount", "blink_rate", "blinks", "saccades", "sway", "breathing"}),
    "gaze": frozenset({"target", "amount", "envelope"}),
    "head": frozenset({"gesture", "pose", "amount", "repetitions", "envelope"}),
}
_ENVELOPE = ("start", "attack_peak", "relax", "end")


def from_spec(spec: object, t0: float = 0.0) -> Layer:
    """The layer ``spec`` describes (see the module docstring), its times shifted by ``t0`` s.

    Raises ``InputError`` saying which field is wrong and what it should be.
    """
    if not isinstance(spec, Mapping):
        raise InputError("a layer is a JSON object with a 'kind'")
    kind = spec.get("kind")
    if not isinstance(kind, str) or kind not in FIELDS:
        raise InputError(f"layer kind must be one of {', '.join(FIELDS)}", where="kind")
    unknown = sorted(str(k) for k in spec if k != "kind" and k not in FIELDS[kind])
    if unknown:
        raise InputError(
            f"unknown field {unknown[0]!r} for a {kind} layer; known: {', '.join(sorted(FIELDS[kind]))}",
            where=unknown[0][:64],
        )
    try:
        if kind == "expression":
            return _expression(spec, t0)
        if kind == "idle":
            return IdleLayer(**{k: v for k, v in spec.items() if k != "kind"})
        if kind == "gaze":
            return GazeLayer(
                target=_target(spec.get("target", "camera")),
                amount=spec.get("amount", 1.0),
                envelope=_envelope(spec.get("envelope"), t0),
            )
        return _head(spec, t0)
    except InputError:
        raise
    except (ValueError, TypeError, KeyError) as e:
        raise InputError(f"{kind} layer: {e}") from None


def _envelope(value: object, t0: float) -> Envelope:
    if value is None:
        return Envelope(start=t0) if t0 else Envelope()
    if not isinstance(value, Mapping):
        raise InputError("envelope is an object with start, attack_peak, relax, end (s)")
    bad = [k for k in value if k not in _ENVELOPE]
    if bad:
        raise InputError(f"unknown envelope field {str(bad[0])[:64]!r}", where="envelope")
    times: dict[str, Any] = {}
    for k in _ENVELOPE:
        v = value.get(k)
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise InputError(f"envelope {k} must be a number of seconds", where="envelope")
            times[k] = float(v) + t0
    times.setdefault("start", t0)
    return Envelope(**times)


def _expression(spec: Mapping[str, Any], t0: float) -> ExpressionLayer:
    e = spec.get("expression", 0)
    if isinstance(e, str):
        if e not in EXPRESSION_NAMES:
            raise InputError(
                f"expression must be one of {', '.join(EXPRESSION_NAMES)} or 0-6",
                where="expression",
            )
        e = EXPRESSION_NAMES.index(e)
    faps = None
    given = spec.get("faps")
    if given is not None:
        if not isinstance(given, Mapping) or len(given) > 68:
            raise InputError("faps is an object of FAP number -> value (FAPU)", where="faps")
        faps = np.zeros(69)
        for k, v in given.items():
            try:
                n = int(k)
            except (TypeError, ValueError):
                n = -1
            if not 3 <= n <= 68 or isinstance(v, bool) or not isinstance(v, int | float):
                raise InputError("faps maps FAP numbers 3-68 to numbers", where="faps")
            faps[n] = float(v)
    if e == 0 and faps is None:
        raise InputError("an expression layer needs an expression or faps", where="expression")
    regions = spec.get("regions")
    return ExpressionLayer(
        expression=e,
        faps=faps,
        amount=spec.get("amount", 1.0),
        envelope=_envelope(spec.get("envelope"), t0),
        regions=tuple(regions) if isinstance(regions, list) else regions,
    )


def _target(value: object) -> GazeTarget:
    if value == "camera":
        return GazeTarget.camera()
    if isinstance(value, Mapping) and set(value) == {"direction"}:
        return GazeTarget(direction=np.asarray(_xyz(value["direction"])))
    return GazeTarget(point=np.asarray(_xyz(value)))


def _xyz(value: object) -> list[float]:
    if (
        not isinstance(value, list | tuple)
        or len(value) != 3
        or any(isinstance(v, bool) or not isinstance(v, int | float) for v in value)
    ):
        raise InputError("a gaze target is 'camera', [x, y, z] or {'direction': [x, y, z]}")
    return [float(v) for v in value]


def _head(spec: Mapping[str, Any], t0: float) -> Layer:
    envelope = _envelope(spec.get("envelope"), t0)
    if ("gesture" in spec) == ("pose" in spec):
        raise InputError("a head layer has a gesture or a pose", where="gesture")
    if "pose" in spec:
        pose = spec["pose"]
        if not isinstance(pose, Mapping) or not set(pose) <= {"pitch", "yaw", "roll"}:
            raise InputError("pose is an object with pitch, yaw, roll (degrees)", where="pose")
        if "repetitions" in spec:
            raise InputError("repetitions belong to a gesture", where="repetitions")
        return HeadPose(**pose, amount=spec.get("amount", 1.0), envelope=envelope)
    return HeadGesture(
        kind=spec["gesture"],
        amount=spec.get("amount", 1.0),
        envelope=envelope,
        repetitions=spec.get("repetitions", 1),
    )
