"""Producer inputs -> face states: FAP frames directly, PCM chunks and marker frames through the
audio and mocap live drivers (imported lazily, by name, when a producer of that kind says hello).

Each input object turns one decoded frame into the face states that became final, oldest first.
They are used by one producer at a time and are not thread-safe.
"""

from __future__ import annotations

import importlib
import logging
from typing import Any, cast

import numpy as np

from ...protocol import frames
from ...protocol.errors import CloseCode, FrameError, MessageError
from ...protocol.messages import FapMessage, InputKind, ProducerHello
from ..drivers import DRIVERS
from ..errors import FacecastError, InputError, Unavailable
from ..state import FaceState, zero_faps

log = logging.getLogger(__name__)

Viseme = tuple[int, int, int]
Expression = tuple[int, int, int, int]


class InputUnavailable(Unavailable):
    """The driver for an input kind is not installed (close code 4503)."""

    close_code = CloseCode.UNAVAILABLE


class BadHello(MessageError):
    """The producer's hello does not fit the session (close code 4400)."""


def load_driver_class(kind: InputKind) -> Any:
    """The live driver class for ``kind`` (``audio`` | ``markers``); ``InputUnavailable`` if absent."""
    live = DRIVERS[kind].live  # the one registry, ``server/drivers``
    if live is None:
        raise InputError(f"input {kind!r} has no live driver (its frames map straight to states)")
    module, name = live
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise InputUnavailable(
            f"live '{kind}' input is not available on this server ({module}.{name}: {e}); "
            "use a FAP producer, or install the missing part"
        ) from None


class FapInput:
    """FAP frames (JSON ``fap`` messages or binary ``FAPS`` frames) -> one ``FaceState`` each.

    FAPs a frame does not carry keep their previous value (all start at 0); viseme and expression
    likewise hold until a frame sets them again.
    """

    kinds = frozenset({frames.Kind.FAPS})
    control_vertices = None

    def __init__(self) -> None:
        self.faps = zero_faps()
        self.viseme: Viseme | None = None
        self.expression: Expression | None = None

    def _state(self, t: float) -> FaceState:
        return FaceState(t=t, faps=self.faps.copy(), viseme=self.viseme, expression=self.expression)

    def flush(self) -> list[FaceState]:
        """End of input: FAP frames are final as they arrive, nothing is held back."""
        return []

    def push_message(self, msg: FapMessage) -> list[FaceState]:
        for k, v in msg.faps.items():
            self.faps[k] = v
        if msg.viseme is not None:
            self.viseme = cast(Viseme, tuple(msg.viseme))
        if msg.expression is not None:
            self.expression = cast(Expression, tuple(msg.expression))
        return [self._state(msg.t)]

    def push_frame(self, frame: frames.Frame) -> list[FaceState]:
        assert isinstance(frame, frames.FapFrame)
        v = frame.values[2:]  # FAPs 1 and 2 travel in the sub-header
        np.copyto(self.faps[3:], v, where=~np.isnan(v))  # NaN: not sent, the previous value holds
        if frame.viseme is not None:
            self.viseme = cast(Viseme, tuple(frame.viseme))
        if frame.expression is not None:
            self.expression = cast(Expression, tuple(frame.expression))
        return [self._state(frame.header.t)]


class AudioInput:
    """PCM chunks at the hello's rate -> ``AudioLiveDriver`` -> face states at the driver's rate."""

    def __init__(self, face: Any, hello: ProducerHello, fps: float) -> None:
        if not hello.rate:
            raise BadHello(
                "an audio producer must declare 'rate' (Hz) in its hello", where="hello.rate"
            )
        self.rate = hello.rate
        fmt = hello.sample_format or "i16"
        self.kinds = frozenset({frames.Kind.PCM_I16 if fmt == "i16" else frames.Kind.PCM_F32})
        cls = load_driver_class("audio")
        text = {"text": hello.transcript} if hello.transcript else {}  # known ahead: followed
        try:
            try:
                self.driver = cls(face, hello.rate, fps=fps, **text)
            except TypeError:  # a driver without an output-rate parameter
                self.driver = cls(face, hello.rate)
        except (ValueError, FacecastError) as e:
            raise BadHello(f"the audio driver refused this hello: {e}", where="hello") from None
        self.control_vertices = getattr(self.driver, "control_vertices", None)

    def flush(self) -> list[FaceState]:
        """End of input: the states the driver held back for its look-ahead."""
        flush = getattr(self.driver, "flush", None)
        return list(flush()) if flush else []

    def push_message(self, msg: FapMessage) -> list[FaceState]:
        raise MessageError("this session takes audio: send binary PCM chunks, not FAP messages")

    def push_frame(self, frame: frames.Frame) -> list[FaceState]:
        assert isinstance(frame, frames.PcmChunk)
        if frame.rate != self.rate:
            raise FrameError(
                f"chunk sample rate {frame.rate} Hz differs from the hello's {self.rate} Hz",
                where="bytes 32-35",
            )
        return list(self.driver.push(frame.as_float32(), frame.sample_offset / self.rate))


class MarkerInput:
    """Marker frames in the hello's name order -> ``MarkerLiveDriver`` -> face states at the
    session's rate: the driver filters every marker frame (captures run at 60-240 Hz), and a state
    goes out at each tick of the session's clock (1/``fps`` apart, anchored at the first state; a
    frame up to a fifth of a period early counts), so a 120 Hz take gives a 60 fps session every
    other frame, a 30 fps one every fourth, and a slower take every frame."""

    kinds = frozenset({frames.Kind.MARKERS})

    def __init__(self, face: Any, hello: ProducerHello, fps: float) -> None:
        if not hello.markers:
            raise BadHello(
                "a marker producer must list its marker names in the hello", where="hello.markers"
            )
        if len(set(hello.markers)) != len(hello.markers):
            raise BadHello("marker names must be unique", where="hello.markers")
        if not hello.layout:
            raise BadHello(
                "a marker producer must send its marker layout (a JSON object with 'markers' and "
                "'stable') in the hello; the server never reads files named by clients",
                where="hello.layout",
            )
        self.names = list(hello.markers)
        self.period = 1.0 / fps if fps and fps > 0 else 0.0  # seconds between states sent
        self.next_t = -np.inf  # the next tick
        cls = load_driver_class("markers")
        try:
            self.driver = cls(face, self.names, dict(hello.layout), units=hello.units, fps=fps)
        except (ValueError, TypeError, KeyError, FacecastError) as e:
            raise BadHello(f"the marker driver refused this hello: {e}", where="hello") from None
        self.control_vertices = getattr(self.driver, "control_vertices", None)

    def flush(self) -> list[FaceState]:
        """End of input: marker frames are final as they arrive."""
        return []

    def push_message(self, msg: FapMessage) -> list[FaceState]:
        raise MessageError(
            "this session takes markers: send binary MARKERS frames, not FAP messages"
        )

    def push_frame(self, frame: frames.Frame) -> list[FaceState]:
        assert isinstance(frame, frames.MarkerFrame)
        if frame.markers.shape[0] != len(self.names):
            raise FrameError(
                f"frame has {frame.markers.shape[0]} markers, the hello named {len(self.names)}",
                where="bytes 12-15",
            )
        if np.isinf(frame.markers).any():
            raise FrameError("marker positions must be finite or NaN (occluded)")
        states = []
        for st in self.driver.push(np.array(frame.markers, dtype=np.float32), frame.header.t):
            late = st.t - self.next_t
            if late >= -0.2 * self.period or late < -2.0 * self.period:  # due (or time went back)
                states.append(st)
                # next tick: one period on, unless the stream jumped (a gap, a restart): re-anchor
                self.next_t = (
                    self.next_t + self.period if 0 <= late < self.period else st.t + self.period
                )
        # drivers that place their controls from the actor's neutral know them only now
        self.control_vertices = getattr(self.driver, "control_vertices", None)
        return states


def make_input(
    kind: str, face: Any, hello: ProducerHello, fps: float
) -> FapInput | AudioInput | MarkerInput:
    """The input object for a session of ``kind`` after ``hello`` (blocking: drivers may precompute)."""
    if hello.input != kind:
        raise BadHello(
            f"this session takes '{kind}' input, the hello says '{hello.input}'",
            where="hello.input",
        )
    if kind == "fap":
        return FapInput()
    if kind == "audio":
        return AudioInput(face, hello, fps)
    return MarkerInput(face, hello, fps)
