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
    "EXPRESSION_NAMES",
    "LAYER_NAME_PATTERN",
    "MAX_LAYERS",
    "ROLE_FAPS",
    "ExpressionLayer",
    "GazeLayer",
    "HeadLayer",
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
#: MPEG-4 expression names, by id (FAP 2: 1 joy ... 6 surprise).
EXPRESSION_NAMES = ("joy", "sadness", "anger", "fear", "disgust", "surprise")
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
_Amount = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]


class IdleLayer(_Model):
    """Idle behaviour: blinks, saccades and fixations, small head sway, breathing."""

    kind: Literal["idle"] = "idle"
    seed: int = Field(
        0, ge=0, le=2**31 - 1, description="random seed (the same seed, the same idle)"
    )
    amount: _Amount = Field(1.0, description="scale of the motion, 0-1")


class ExpressionLayer(_Model):
    """An expression overlay (a named MPEG-4 expression, or FAPs) with intensity and timing.

    Times are seconds from the call: it ramps in over ``attack`` from ``start``, holds, and ramps
    out over ``relax`` before ``end`` (None: held until changed or removed).
    """

    kind: Literal["expression"] = "expression"
    expression: Literal["joy", "sadness", "anger", "fear", "disgust", "surprise"] | None = None
    faps: dict[int, float] | None = Field(
        None, description="low-level FAPs (3..68, FAPU) of the overlay, instead of or with a name"
    )
    amount: _Amount = 1.0
    start: _Seconds = 0.0
    attack: _Seconds = 0.3
    relax: _Seconds = 0.3
    end: _Seconds | None = None

    @field_validator("faps")
    @classmethod
    def _faps(cls, v: dict[int, float] | None) -> dict[int, float] | None:
        if v is None:
            return v
        if len(v) > 66:
            raise ValueError("at most the 66 low-level FAPs")
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
        if self.expression is None and not self.faps:
            raise ValueError("an expression layer needs 'expression' (joy, ...) or 'faps'")
        if self.end is not None and self.end < self.start:
            raise ValueError("'end' comes before 'start'")
        return self


class GazeLayer(_Model):
    """Where the eyes look: a ``target`` point (millimetres, in the face's coordinates: +x the
    face's left, +y up, +z out of the face), ``camera`` (straight ahead), or yaw/pitch (degrees,
    a direction from the face). The eyes follow it whatever the head does."""

    kind: Literal["gaze"] = "gaze"
    target: tuple[float, float, float] | Literal["camera"] | None = None
    yaw: float | None = Field(
        None, ge=-60, le=60, allow_inf_nan=False, description="degrees, + left"
    )
    pitch: float | None = Field(
        None, ge=-45, le=45, allow_inf_nan=False, description="degrees, + up"
    )

    @field_validator("target")
    @classmethod
    def _target(cls, v: Any) -> Any:
        if isinstance(v, tuple) and not all(math.isfinite(x) and abs(x) <= 1e6 for x in v):
            raise ValueError("target coordinates must be finite, within ±1e6 mm")
        return v

    @model_validator(mode="after")
    def _whole(self) -> GazeLayer:
        if self.target is None and self.yaw is None and self.pitch is None:
            raise ValueError("a gaze layer needs 'target' ([x, y, z] mm or 'camera') or yaw/pitch")
        if self.target is not None and (self.yaw is not None or self.pitch is not None):
            raise ValueError("give 'target' or yaw/pitch, not both")
        return self


class HeadLayer(_Model):
    """Head motion: a ``gesture`` (nod, shake, tilt) of ``amount`` degrees (default: the
    gesture's own, 8° nod, 12° shake, 10° tilt) from ``start``, each cycle ``duration`` seconds,
    ``repeat`` times; or, without a gesture, a held pose (pitch down +, yaw to the face's left +,
    roll; degrees) replacing the primary's head."""

    kind: Literal["head"] = "head"
    gesture: Literal["nod", "shake", "tilt"] | None = None
    amount: float | None = Field(None, gt=0, le=45, allow_inf_nan=False, description="degrees")
    start: _Seconds = 0.0
    duration: float = Field(0.6, gt=0, le=60, allow_inf_nan=False)
    repeat: int = Field(1, ge=1, le=20)
    yaw: float = Field(0.0, ge=-60, le=60, allow_inf_nan=False)
    pitch: float = Field(0.0, ge=-45, le=45, allow_inf_nan=False)
    roll: float = Field(0.0, ge=-45, le=45, allow_inf_nan=False)


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
