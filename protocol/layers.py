"""Layers of a live session on the wire: scoped producer tokens and the REST layer bodies.

A session mixes several inputs into one face state per frame (``server/layers/``): the primary
driver's states clock the frames; secondary producers (roles ``expression``, ``gaze``, ``head``,
``idle``, ``messages.Role``) and layers set over REST are mixed into each. Pure pydantic, no I/O.

- ``POST /v1/sessions/{id}/tokens`` (``TokenCreate`` -> ``TokenCreated``): a producer token that
  may drive only the listed roles.
- ``PUT /v1/sessions/{id}/layers/{name}`` (a ``LayerSpec``), ``PATCH`` (some of its fields),
  ``GET``/``DELETE`` (``LayerInfo``, ``LayerList``).
"""

from __future__ import annotations

import math
from itertools import pairwise
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from .errors import MessageError
from .messages import ROLES, Role

__all__ = [
    "LAYER_NAME_PATTERN",
    "MAX_LAYERS",
    "ROLE_FAPS",
    "Envelope",
    "ExpressionLayer",
    "GazeDirection",
    "GazeLayer",
    "HeadLayer",
    "HeadPoseAngles",
    "IdleLayer",
    "LayerInfo",
    "LayerList",
    "LayerSpec",
    "TokenCreate",
    "TokenCreated",
    "parse_layer",
    "patch_layer",
    "role_refusal",
]

#: A layer's name in a URL: letters, digits, ``_`` and ``-``, 1-32 characters.
LAYER_NAME_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
#: REST layers a session holds at most.
MAX_LAYERS = 16
#: Seconds into the future a layer may be scheduled (start / end), at most.
MAX_SECONDS = 24 * 3600.0

#: The low-level FAPs (3..68) a secondary producer of each role may send; the primary sends any.
#: Eyeballs 23-26 and pupils 29-30 are gaze's, head rotation 48-50 is head's; idle moves eyelids
#: 19-22, eyeballs and head (blinks, saccades, sway); expression moves the rest of the face.
ROLE_FAPS: dict[str, frozenset[int]] = {
    "primary": frozenset(range(3, 69)),
    "expression": frozenset(range(3, 69)) - {23, 24, 25, 26, 29, 30, 48, 49, 50},
    "gaze": frozenset({23, 24, 25, 26, 29, 30}),
    "head": frozenset({48, 49, 50}),
    "idle": frozenset({19, 20, 21, 22, 23, 24, 25, 26, 29, 30, 48, 49, 50}),
}


def role_refusal(role: str, faps: Any) -> str | None:
    """Why a ``role`` producer may not send FAPs numbered ``faps`` (an iterable of ints), or None."""
    allowed = ROLE_FAPS[role]
    bad = sorted(k for k in faps if k not in allowed)
    if not bad:
        return None
    shown = ", ".join(str(k) for k in bad[:8]) + (" ..." if len(bad) > 8 else "")
    return (
        f"a '{role}' producer may not drive FAP {shown}; its FAPs are "
        f"{_ranges(allowed)} (the primary producer drives any)"
    )


def _ranges(numbers: frozenset[int]) -> str:
    """``{3, 4, 5, 9}`` -> ``"3-5, 9"``."""
    out: list[str] = []
    for k in sorted(numbers):
        if out and out[-1].endswith(f"-{k - 1}"):
            out[-1] = out[-1].rsplit("-", 1)[0] + f"-{k}"
        elif out and out[-1] == str(k - 1):
            out[-1] = f"{k - 1}-{k}"
        else:
            out.append(str(k))
    return ", ".join(out)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ---------------------------------------------------------------------------------------- tokens


class TokenCreate(_Model):
    """``POST /v1/sessions/{id}/tokens`` body: the roles the new producer token may drive."""

    roles: list[Role] = Field(min_length=1, max_length=len(ROLES))

    @field_validator("roles")
    @classmethod
    def _unique(cls, v: list[Role]) -> list[Role]:
        if len(set(v)) != len(v):
            raise ValueError("each role at most once")
        return v


class TokenCreated(_Model):
    """The answer: the token (shown only now) and its roles."""

    session: str
    token: str = Field(
        description="a producer token for these roles only ('Authorization: Bearer')"
    )
    roles: list[Role]


# ---------------------------------------------------------------------------------------- layers

_Seconds = Annotated[float, Field(ge=0, le=MAX_SECONDS, allow_inf_nan=False)]
_Unit = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
_Xyz = tuple[
    Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)],
    Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)],
    Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)],
]
#: Face regions an expression may be limited to (``server/layers/model.py`` ``REGIONS``).
Region = Literal[
    "jaw",
    "lips",
    "mouth",
    "eyelids",
    "eyes",
    "eyebrows",
    "cheeks",
    "tongue",
    "head",
    "nose",
    "ears",
]


class Envelope(_Model):
    """When a layer acts (BML timing), seconds from the call: it rises from ``start`` to full at
    ``attack_peak``, holds, falls from ``relax`` to nothing at ``end``. Missing: starts now, no
    rise (or fall), no end."""

    start: _Seconds | None = None
    attack_peak: _Seconds | None = None
    relax: _Seconds | None = None
    end: _Seconds | None = None

    @model_validator(mode="after")
    def _ordered(self) -> Envelope:
        given = [v for v in (self.start, self.attack_peak, self.relax, self.end) if v is not None]
        if any(b < a for a, b in pairwise(given)):
            raise ValueError("envelope times must satisfy start <= attack_peak <= relax <= end")
        return self


class IdleLayer(_Model):
    """Idle behaviour: blinks, saccades and fixations, small head sway, breathing."""

    kind: Literal["idle"] = "idle"
    seed: int = Field(0, ge=0, le=2**31 - 1, description="the same seed, the same idle")
    amount: _Unit = Field(1.0, description="scale of the motion, 0-1")
    blink_rate: float | None = Field(None, ge=1, le=60, allow_inf_nan=False, description="/min")
    blinks: bool | None = None
    saccades: bool | None = None
    sway: bool | None = None
    breathing: bool | None = None


class ExpressionLayer(_Model):
    """An expression overlay: a named MPEG-4 expression (or its id 1-6) and/or low-level FAPs,
    scaled by ``amount``, timed by ``envelope``, optionally limited to face ``regions``."""

    kind: Literal["expression"] = "expression"
    expression: (
        Literal["joy", "sadness", "anger", "fear", "disgust", "surprise"]
        | Annotated[int, Field(ge=0, le=6)]
        | None
    ) = None
    faps: dict[int, float] | None = Field(
        None, description="low-level FAP offsets (3..68, FAPU) at full strength"
    )
    amount: float = Field(1.0, ge=0, le=2, allow_inf_nan=False)
    envelope: Envelope | None = None
    regions: list[Region] | None = Field(None, max_length=11)

    @field_validator("faps")
    @classmethod
    def _faps(cls, v: dict[int, float] | None) -> dict[int, float] | None:
        if v is None:
            return v
        for k, x in v.items():
            if not 3 <= k <= 68:
                raise ValueError(f"FAP number {k} is not a low-level FAP (3..68)")
            if not math.isfinite(x) or abs(x) > 1e6:
                raise ValueError(f"FAP {k} value must be finite and within ±1e6 FAPU")
        refused = role_refusal("expression", v)
        if refused:
            raise ValueError(refused.replace("producer", "layer"))
        return v

    @model_validator(mode="after")
    def _whole(self) -> ExpressionLayer:
        if not self.expression and not self.faps:
            raise ValueError("an expression layer needs 'expression' (joy, ...) or 'faps'")
        return self


class GazeDirection(_Model):
    direction: _Xyz

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not any(v):
            raise ValueError("a gaze direction must not be zero")
        return v


class GazeLayer(_Model):
    """Where the eyes look, whatever the head does: ``camera`` (straight ahead), a point
    ``[x, y, z]`` in the face's mesh coordinates (+x its left, +y up, +z out of the face), or
    ``{"direction": [x, y, z]}``."""

    kind: Literal["gaze"] = "gaze"
    target: Literal["camera"] | _Xyz | GazeDirection = "camera"
    amount: _Unit = 1.0
    envelope: Envelope | None = None


class HeadPoseAngles(_Model):
    pitch: float = Field(0.0, ge=-90, le=90, allow_inf_nan=False, description="degrees, down +")
    yaw: float = Field(0.0, ge=-90, le=90, allow_inf_nan=False, description="degrees, left +")
    roll: float = Field(0.0, ge=-90, le=90, allow_inf_nan=False, description="degrees")


class HeadLayer(_Model):
    """Head motion: a ``gesture`` (nod, shake, tilt; ``amount`` 1 = 8° nod, 12° shake, 10° tilt)
    ``repetitions`` times, or a held ``pose`` (degrees) replacing the primary's head by
    ``amount``."""

    kind: Literal["head"] = "head"
    gesture: Literal["nod", "shake", "tilt"] | None = None
    pose: HeadPoseAngles | None = None
    amount: float = Field(1.0, ge=-5, le=5, allow_inf_nan=False)
    repetitions: int | None = Field(None, ge=1, le=100)
    envelope: Envelope | None = None

    @model_validator(mode="after")
    def _one(self) -> HeadLayer:
        if (self.gesture is None) == (self.pose is None):
            raise ValueError("a head layer has a 'gesture' or a 'pose'")
        if self.pose is not None and (self.repetitions is not None or not 0 <= self.amount <= 1):
            raise ValueError("a pose takes an amount 0-1 and no repetitions")
        return self


LayerSpec = Annotated[
    IdleLayer | ExpressionLayer | GazeLayer | HeadLayer, Field(discriminator="kind")
]
_SPEC: TypeAdapter[LayerSpec] = TypeAdapter(LayerSpec)


def parse_layer(obj: object) -> IdleLayer | ExpressionLayer | GazeLayer | HeadLayer:
    """A layer body (a JSON object) -> its model; ``MessageError`` naming the field if invalid."""
    if not isinstance(obj, dict):
        raise MessageError("a layer is a JSON object with a 'kind' (idle, expression, gaze, head)")
    try:
        return _SPEC.validate_python(obj)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"][1:] or err["loc"])
        raise MessageError(
            f"{where or 'layer'}: {err['msg']} ({e.error_count()} error(s))", where=where
        ) from None
    except (ValueError, TypeError, RecursionError) as e:
        raise MessageError(f"invalid layer: {e}") from None


def patch_layer(
    spec: IdleLayer | ExpressionLayer | GazeLayer | HeadLayer, changes: object
) -> IdleLayer | ExpressionLayer | GazeLayer | HeadLayer:
    """``spec`` with the fields of ``changes`` (a JSON object) replaced; its kind cannot change."""
    if not isinstance(changes, dict):
        raise MessageError("a layer patch is a JSON object of the fields to change")
    if changes.get("kind", spec.kind) != spec.kind:
        raise MessageError(
            f"a layer's kind cannot change ({spec.kind} -> {changes['kind']!r}); PUT a new one",
            where="kind",
        )
    return parse_layer(spec.model_dump() | changes)


class LayerInfo(_Model):
    """One layer of a session: set over REST (``source`` ``rest``) or a connected producer's."""

    name: str
    source: Literal["rest", "producer"]
    kind: str
    spec: dict[str, Any] | None = Field(None, description="the layer as set (REST layers)")
    age: float = Field(description="seconds since it was set or connected")


class LayerList(_Model):
    """``GET /v1/sessions/{id}/layers``."""

    session: str
    layers: list[LayerInfo]
