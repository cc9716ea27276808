"""JSON control messages of live sessions, as pydantic models shared by the WebSocket and REST APIs.

Every WebSocket text message is one JSON object with a ``type`` field; ``parse_message`` picks the
model by it. The REST session routes use ``SessionCreate`` / ``SessionCreated`` / ``SessionInfo`` /
``SessionList``. ``README.md`` beside this file lists every field.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    ValidationError,
    field_validator,
)

from .encoding import VERTEX_ENCODINGS, SampleFormat, VertexEncoding
from .errors import MessageError

__all__ = [
    "INPUT_ALIASES",
    "INPUT_KINDS",
    "PROTOCOL_VERSION",
    "ROLES",
    "Encoding",
    "ErrorMessage",
    "FapMessage",
    "InputKind",
    "InputKindIn",
    "Message",
    "ProducerHello",
    "ProducerRole",
    "Ready",
    "Role",
    "SessionCreate",
    "SessionCreated",
    "SessionInfo",
    "SessionList",
    "Stats",
    "Status",
    "ViewerHello",
    "dump_message",
    "parse_message",
]

PROTOCOL_VERSION = 1
#: Largest JSON control message a receiver parses (a marker name table fits easily).
MAX_MESSAGE_BYTES = 256 * 1024

#: What a session's producer sends: FAP frames, PCM audio or optical markers (canonical names).
InputKind = Literal["fap", "audio", "markers"]
INPUT_KINDS: tuple[InputKind, ...] = get_args(InputKind)
#: Other names a client may send for an input kind (``mocap``: what batch jobs called markers).
INPUT_ALIASES: dict[str, InputKind] = {"mocap": "markers"}


def input_kind_name(value: object) -> object:
    """``value`` with an alias replaced by its canonical ``InputKind`` (anything else unchanged)."""
    return INPUT_ALIASES.get(value, value) if isinstance(value, str) else value


#: An ``InputKind`` a client sends: an alias is accepted and read as its canonical name.
InputKindIn = Annotated[InputKind, BeforeValidator(input_kind_name)]
Encoding = VertexEncoding  #: the one vocabulary, ``encoding.py``


#: A producer's role in a session: the layer it drives. ``primary`` (the speech, FAP stream or
#: mocap of the session's input kind) clocks the frames; the others add to each frame and send FAPs.
Role = Literal["primary", "expression", "gaze", "head", "idle"]
ROLES: tuple[Role, ...] = get_args(Role)
#: What a producer hello's ``role`` may say: a ``Role``, or ``producer`` (older clients), read as
#: ``primary``.
ProducerRole = Literal["producer", "primary", "expression", "gaze", "head", "idle"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ------------------------------------------------------------------------------------------ WebSocket


class ProducerHello(_Model):
    """Producer -> server, the first message on ``/produce``: what the producer will send."""

    type: Literal["hello"] = "hello"
    role: ProducerRole = Field(
        "producer",
        description="the layer this producer drives: primary (also 'producer', the default), "
        "expression, gaze, head or idle; its token must carry that role",
    )
    protocol: int = PROTOCOL_VERSION
    input: InputKindIn = "fap"
    rate: int | None = Field(None, gt=0, le=384_000, description="audio: sample rate in Hz")
    sample_format: SampleFormat | None = Field(None, description="audio: 'i16' or 'f32' PCM chunks")
    transcript: str | None = Field(
        None,
        min_length=1,
        max_length=10_000,
        description="audio: what will be said (English), when known ahead: the mouth follows "
        "its phones as far as the look-ahead allows",
    )
    markers: list[str] | None = Field(
        None, max_length=4096, description="markers: name of each marker, in frame order"
    )
    layout: dict[str, Any] | None = Field(
        None,
        description="markers: the marker layout as a JSON object "
        "(markers, stable, units, ...), sent inline",
    )
    units: str | None = Field(
        None, max_length=16, description="markers: units of the positions (mm, cm, m)"
    )

    @property
    def layer(self) -> Role:
        """The role as a layer name (``producer`` is ``primary``)."""
        return "primary" if self.role == "producer" else self.role


class Ready(_Model):
    """Server -> producer, the answer to its hello: the session accepts frames now."""

    type: Literal["ready"] = "ready"
    protocol: int = PROTOCOL_VERSION
    session: str
    input: InputKind
    fps: float
    max_fps: float = Field(
        description="input frames per second above which frames are dropped with an error"
    )
    vertex_count: int
    role: Role | None = Field(
        None, description="the layer this producer drives, when not the primary (omitted)"
    )


class ViewerHello(_Model):
    """Server -> viewer, the first message on ``/watch``: how to read the binary frames that follow."""

    type: Literal["hello"] = "hello"
    role: Literal["viewer"] = "viewer"
    protocol: int = PROTOCOL_VERSION
    session: str
    face: str
    topology_url: str = Field(
        description="REST path of the face's triangles (relative to the server)"
    )
    vertex_count: int
    encoding: Encoding
    fps: float
    input: InputKind
    producer_connected: bool
    tolerance: float | None = Field(
        None, description="compact: largest error of a decoded vertex, in the face's units"
    )


class ErrorMessage(_Model):
    """Either direction: something was wrong. ``code`` is a ``CloseCode`` value; if ``fatal``, the
    sender closes the connection with that code right after."""

    type: Literal["error"] = "error"
    code: int
    message: str
    where: str = ""
    fatal: bool = False
    seq: int | None = Field(None, description="sequence number of the offending frame, if any")


class FapMessage(_Model):
    """Producer -> server: one FAP frame as JSON (the binary ``FAPS`` frame carries the same).

    ``faps`` maps FAP number (3..68) to its value in FAPU units; FAPs not listed keep their previous
    value. ``wall`` is the producer's Unix time when sending (copied into the vertex frames, for
    latency); ``t`` is media seconds from the session's start.
    """

    type: Literal["fap"] = "fap"
    seq: int = Field(0, ge=0, le=0xFFFFFFFF)
    t: float = Field(allow_inf_nan=False)
    wall: float = Field(0.0, allow_inf_nan=False)
    faps: dict[int, float] = Field(default_factory=dict)
    viseme: tuple[int, int, int] | None = None
    expression: tuple[int, int, int, int] | None = None

    @field_validator("faps")
    @classmethod
    def _fap_numbers(cls, v: dict[int, float]) -> dict[int, float]:
        for k, x in v.items():
            if not 3 <= k <= 68:
                raise ValueError(
                    f"FAP number {k} is not a low-level FAP (3..68); send FAP 1 as 'viseme' "
                    "and FAP 2 as 'expression'"
                )
            if not math.isfinite(x):
                raise ValueError(f"FAP {k} value must be finite")
        return v

    @field_validator("viseme")
    @classmethod
    def _viseme(cls, v: tuple[int, int, int] | None) -> tuple[int, int, int] | None:
        if v is not None and not (0 <= v[0] <= 14 and 0 <= v[1] <= 14 and 0 <= v[2] <= 63):
            raise ValueError("viseme is (select1 0-14, select2 0-14, blend 0-63)")
        return v

    @field_validator("expression")
    @classmethod
    def _expression(cls, v: tuple[int, int, int, int] | None) -> tuple[int, int, int, int] | None:
        if v is not None and not (
            0 <= v[0] <= 6 and 0 <= v[2] <= 6 and 0 <= v[1] <= 63 and 0 <= v[3] <= 63
        ):
            raise ValueError(
                "expression is (select1 0-6, intensity1 0-63, select2 0-6, intensity2 0-63)"
            )
        return v


class Stats(_Model):
    """Counters of one session (REST ``SessionInfo.stats``; also sent to viewers as a ``stats`` message)."""

    type: Literal["stats"] = "stats"
    frames_in: int = 0  #: input frames (FAP frames, PCM chunks, marker frames) accepted
    frames_rejected: int = 0  #: input frames refused (malformed, over the rate limit)
    states: int = 0  #: face states produced by the driver (= vertex frames numbered)
    frames_deformed: int = 0  #: states deformed (the rest were dropped because deformation lagged)
    frames_dropped: int = 0  #: states dropped before deformation
    frames_sent: int = 0  #: vertex frames sent, summed over viewers
    frames_skipped: int = 0  #: frames a slow viewer never got (replaced by a newer one), summed
    deform_ms_mean: float = 0.0  #: mean deform + encode time per frame, milliseconds
    viewers: int = 0
    producer_connected: bool = False


class Status(_Model):
    """Server -> viewers: the producer connected or disconnected (viewers may stop on the latter)."""

    type: Literal["status"] = "status"
    producer_connected: bool
    viewers: int
    last_seq: int | None = Field(
        None, description="sequence number of the last vertex frame, if any"
    )


def _tag(obj: object) -> str | None:
    """Discriminator: ``type``, and for ``hello`` also ``role`` (a viewer's hello, or a producer's
    whatever role it names: its model says which roles there are; a hello must name one)."""
    get = obj.get if isinstance(obj, dict) else lambda k, d=None: getattr(obj, k, d)
    kind = get("type")
    if kind != "hello" or get("role") is None:
        return kind if kind != "hello" else "hello:None"
    return "hello:viewer" if get("role") == "viewer" else "hello:producer"


Message = Annotated[
    Annotated[ProducerHello, Tag("hello:producer")]
    | Annotated[ViewerHello, Tag("hello:viewer")]
    | Annotated[Ready, Tag("ready")]
    | Annotated[ErrorMessage, Tag("error")]
    | Annotated[FapMessage, Tag("fap")]
    | Annotated[Stats, Tag("stats")]
    | Annotated[Status, Tag("status")],
    Discriminator(_tag),
]


# ------------------------------------------------------------------------------------------------ REST


class SessionCreate(_Model):
    """``POST /v1/sessions`` body."""

    face: str | None = Field(
        None,
        max_length=512,
        description="face name or server-side mesh path; default: the server's face",
    )
    input: InputKindIn = "fap"
    fps: float = Field(
        60.0,
        gt=0,
        le=240,
        allow_inf_nan=False,
        description="output frame rate (audio/markers drivers "
        "resample to it; FAP frames are taken as sent)",
    )
    engine: str = Field("fp", max_length=32, description="deformation engine: fp | rbf | shell")
    max_viewers: int | None = Field(None, gt=0, description="viewer limit (≤ the server's)")
    tolerance: float = Field(
        0.1, gt=0, le=100, description="compact encoding: largest error of a decoded vertex, mm"
    )


class SessionCreated(_Model):
    """``POST /v1/sessions`` answer: keep the tokens, they are shown only once."""

    id: str
    producer_token: str
    viewer_token: str
    face: str
    input: InputKind
    fps: float
    vertex_count: int
    produce_url: str = Field(
        description="WebSocket path for the producer (send 'Authorization: Bearer PRODUCER_TOKEN')"
    )
    watch_url: str = Field(
        description="WebSocket path for viewers (send 'Authorization: Bearer VIEWER_TOKEN'; "
        f"add ?encoding={'|'.join(VERTEX_ENCODINGS)})"
    )


class SessionInfo(_Model):
    """One session in ``GET /v1/sessions`` / ``GET /v1/sessions/{id}``."""

    id: str
    face: str
    input: InputKind
    fps: float
    engine: str
    created: float = Field(description="Unix time")
    vertex_count: int
    max_viewers: int
    stats: Stats


class SessionList(_Model):
    sessions: list[SessionInfo]


# --------------------------------------------------------------------------------------------- codec

_ADAPTER: TypeAdapter[Message] = TypeAdapter(Message)
_TAGS = ("hello:producer", "hello:viewer", "ready", "error", "fap", "stats", "status")


def parse_message(text: str | bytes) -> BaseModel:
    """One JSON control message -> its model.

    Raises:
        MessageError: too long, not JSON, not an object, unknown ``type``, or invalid fields (the
            message names the field).
    """
    if len(text) > MAX_MESSAGE_BYTES:
        raise MessageError(
            f"control message of {len(text)} bytes is over the {MAX_MESSAGE_BYTES}-byte limit"
        )
    try:
        obj = json.loads(text)
    except (ValueError, UnicodeDecodeError) as e:
        raise MessageError(f"not JSON: {e}") from None
    except RecursionError:
        raise MessageError("the message nests too deeply") from None
    if not isinstance(obj, dict):
        raise MessageError("a control message must be a JSON object with a 'type' field")
    tag = _tag(obj)
    if tag not in _TAGS:
        raise MessageError(
            f"unknown message type {obj.get('type')!r}"
            + (" without a role" if tag == "hello:None" else "")
            + "; expected one of: "
            + ", ".join(_TAGS),
            where="type",
        )
    try:
        return _ADAPTER.validate_python(obj)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise MessageError(f"{err['msg']} ({e.error_count()} error(s))", where=where) from None
    except (ValueError, TypeError, RecursionError) as e:
        raise MessageError(f"invalid message: {e}") from None


def dump_message(message: BaseModel) -> str:
    """A model -> its compact JSON text (fields left at None are omitted)."""
    return message.model_dump_json(exclude_none=True)
