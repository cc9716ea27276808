"""Per-connection budgets of the live WebSockets, checked on each raw message before it is decoded.

A message costs the server almost nothing until it is parsed, so the checks come first, in order:

1. **size** by input kind (``Limits.max_text`` / ``max_binary``): a larger message ends the
   connection with close code 1009 (an audio chunk carries at most ``MAX_AUDIO_CHUNK_SECONDS``);
2. **flood**: messages and bytes beyond ``FLOOD_FACTOR`` times the allowed rate, once a burst of
   ``FLOOD_BURST_SECONDS`` of it is used up, end the connection with close code 1008 (policy
   violation): a producer sending tens of thousands of messages a second is cut off within a few
   hundredths of a second instead of costing the event loop (and every other session) its time;
3. **rate**: messages beyond the frame rate (``ServerConfig.max_producer_fps``, one second's burst)
   and, for audio, samples beyond ``AUDIO_SPEED`` times real time are dropped, counted and
   answered with a warning (error 4429, at most one a second).

Pure bookkeeping: the caller passes the clock (``time.monotonic`` seconds).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import IntEnum

from ...protocol import frames
from ...protocol.messages import MAX_MESSAGE_BYTES

#: Longest audio chunk a producer may send, in seconds of audio at its hello's rate.
MAX_AUDIO_CHUNK_SECONDS = 1.0
#: Largest JSON message after the hello (a ``fap`` message with all 66 low-level FAPs is < 2 KiB).
MAX_TEXT_BYTES = 8 * 1024
#: Audio seconds a producer may send per wall-clock second, on average (a 4x-speed file fits).
AUDIO_SPEED = 8.0
#: Beyond this multiple of the allowed rate (after the burst) a connection is a flood and is closed.
FLOOD_FACTOR = 4.0
#: Seconds of the allowed rate a connection may exceed the flood rate by before it is closed.
FLOOD_BURST_SECONDS = 2.0
#: Bytes a FAP or marker frame may exceed its exact size by and still be read (and answered with a
#: "trailing bytes" error that names the frame) rather than end the connection.
SLACK_BYTES = 1024
#: Messages a second a viewer may send (viewers have nothing to say; pings are not messages).
VIEWER_MESSAGES_PER_SECOND = 20.0
#: Largest message a viewer may send.
VIEWER_MAX_BYTES = 4 * 1024


def _pcm_bytes(samples: int, sample_bytes: int) -> int:
    return frames.HEADER_SIZE + 16 + sample_bytes * samples  # header + PCM sub-header + samples


#: The server's WebSocket message size limit (uvicorn ``ws_max_size``): the largest message any
#: input accepts (a hello, or one second of float32 audio at the highest rate).
MAX_WS_MESSAGE = max(
    MAX_MESSAGE_BYTES,
    _pcm_bytes(int(frames.MAX_RATE * MAX_AUDIO_CHUNK_SECONDS), 4),
    frames.HEADER_SIZE + 12 * frames.MAX_MARKERS,
)


class Verdict(IntEnum):
    OK = 0  #: decode it
    DROP = 1  #: over the rate: drop it, count it, warn
    TOO_BIG = 2  #: over the size limit: close with 1009
    FLOOD = 3  #: far over the rate: close with 1008


class TokenBucket:
    """``rate`` units a second on average, bursts up to ``burst`` units (starts full)."""

    __slots__ = ("burst", "last", "rate", "tokens")

    def __init__(self, rate: float, burst: float, now: float | None = None) -> None:
        self.rate, self.burst, self.tokens = rate, burst, burst
        self.last = time.monotonic() if now is None else now

    def take(self, n: float, now: float) -> bool:
        """Take ``n`` units if they are there (True), else take nothing (False)."""
        self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= n:
            self.tokens -= n
            return True
        return False


@dataclass(frozen=True)
class Limits:
    """What one connection may send: per-message sizes (bytes), messages a second, bytes a second
    (None: no byte rate of its own), and how to name the rate in a warning."""

    max_text: int
    max_binary: int
    rate: float
    byte_rate: float | None = None
    unit: str = "frames"

    def too_big(self, nbytes: int, text: bool) -> str | None:
        """Why a message of ``nbytes`` is too big, or None."""
        limit = self.max_text if text else self.max_binary
        if nbytes <= limit:
            return None
        what = "JSON message" if text else "binary message"
        hint = (
            f" (at most {MAX_AUDIO_CHUNK_SECONDS:g} s of audio per chunk: send shorter chunks)"
            if self.unit == "audio chunks" and not text
            else ""
        )
        return f"{what} of {nbytes} bytes is over this connection's limit of {limit} bytes{hint}"


def producer_limits(
    kind: str,
    max_fps: float,
    *,
    rate: int | None = None,
    sample_format: str | None = None,
    markers: int = 0,
) -> Limits:
    """The limits of a producer of ``kind`` (``fap`` | ``audio`` | ``markers``) after its hello."""
    if kind == "audio":
        sample_bytes = 4 if sample_format == "f32" else 2
        per_second = float(rate or frames.MAX_RATE) * sample_bytes
        chunk = _pcm_bytes(int((rate or frames.MAX_RATE) * MAX_AUDIO_CHUNK_SECONDS), sample_bytes)
        return Limits(MAX_TEXT_BYTES, chunk, max_fps, AUDIO_SPEED * per_second, "audio chunks")
    if kind == "markers":
        n = max(1, min(markers, frames.MAX_MARKERS))
        return Limits(MAX_TEXT_BYTES, frames.HEADER_SIZE + 12 * n + SLACK_BYTES, max_fps)
    fap = frames.frame_size(frames.Header(frames.Kind.FAPS, 0, frames.N_FAP_VALUES, 0.0))
    return Limits(MAX_TEXT_BYTES, fap + SLACK_BYTES, max_fps)


def viewer_limits() -> Limits:
    """Viewers only listen: a few small messages a second are read and ignored."""
    return Limits(VIEWER_MAX_BYTES, VIEWER_MAX_BYTES, VIEWER_MESSAGES_PER_SECOND, unit="messages")


class Budget:
    """The running budget of one connection under ``limits``; ``check`` each raw message."""

    def __init__(self, limits: Limits, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self.limits = limits
        r, b = limits.rate, limits.byte_rate
        self.messages = TokenBucket(r, max(1.0, r), now)
        self.flood = TokenBucket(FLOOD_FACTOR * r, FLOOD_BURST_SECONDS * r, now)
        self.bytes = TokenBucket(b, b, now) if b else None
        self.flood_bytes = (
            TokenBucket(FLOOD_FACTOR * b, FLOOD_BURST_SECONDS * b, now) if b else None
        )
        self.dropped = 0
        self.last_warning = -1e9

    def check(self, nbytes: int, text: bool, now: float) -> tuple[Verdict, str]:
        """The verdict on one message of ``nbytes`` (``text``: a JSON text message), and why."""
        lim = self.limits
        big = lim.too_big(nbytes, text)
        if big:
            return Verdict.TOO_BIG, big
        if not self.flood.take(1.0, now) or (
            self.flood_bytes is not None and not self.flood_bytes.take(nbytes, now)
        ):
            return Verdict.FLOOD, (
                f"{lim.unit} arrive far faster than this server's limit of {lim.rate:g} per second"
                + (f" and {AUDIO_SPEED:g}x real time" if self.bytes is not None else "")
                + "; the connection is closed (pace the input at its real rate)"
            )
        if not self.messages.take(1.0, now):
            self.dropped += 1
            return Verdict.DROP, (
                f"{lim.unit} arrive faster than this server's limit of {lim.rate:g} per second; "
                f"{lim.unit} over it are dropped"
            )
        if self.bytes is not None and not self.bytes.take(nbytes, now):
            self.dropped += 1
            return Verdict.DROP, (
                f"audio arrives faster than {AUDIO_SPEED:g}x real time, this server's limit; "
                "chunks over it are dropped"
            )
        return Verdict.OK, ""

    def warn_now(self, now: float, every: float = 1.0) -> bool:
        """True at most once per ``every`` seconds (rate-limit the warnings themselves)."""
        if now - self.last_warning >= every:
            self.last_warning = now
            return True
        return False
