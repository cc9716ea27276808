"""Binary frames of live sessions: vertex frames, PCM chunks, marker frames and FAP frames.

Every frame is one binary WebSocket message: a fixed 32-byte little-endian header, a small
kind-specific sub-header, then the payload. ``README.md`` beside this file documents every byte.
All payload offsets are multiples of 8, so a JavaScript client can map them straight into a
``Float32Array`` / ``Int16Array`` without copying.

Decoding never copies the payload: arrays are ``np.frombuffer`` views on the message (read-only
when the message is ``bytes``). Any malformed input raises ``FrameError``, nothing else.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .encoding import VertexEncoding
from .errors import FrameError
from .quantize import dequantize_int16, quantize_int16

__all__ = [
    "HEADER_SIZE",
    "MAGIC",
    "MAX_MARKERS",
    "MAX_SAMPLES",
    "MAX_VERTICES",
    "N_FAP_VALUES",
    "VERSION",
    "FapFrame",
    "Flag",
    "Frame",
    "Header",
    "Kind",
    "MarkerFrame",
    "PcmChunk",
    "VertexFrame",
    "decode",
    "encode_faps",
    "encode_markers",
    "encode_pcm",
    "encode_vertices",
    "encode_vertices_f32",
    "encode_vertices_i16",
    "frame_size",
    "parse_header",
    "vertex_frame_header",
    "vertex_frame_size",
]

MAGIC = b"FCST"
VERSION = 1

#: magic, version, kind, flags, seq, count, t (media seconds), wall (sender's Unix time, seconds).
_HEADER = struct.Struct("<4sBBHIIdd")
HEADER_SIZE = _HEADER.size  # 32
_I16_SUB = struct.Struct("<3f3f")  # offset xyz, scale xyz: 24 bytes
_PCM_SUB = struct.Struct("<IHHQ")  # sample rate, channels, reserved, sample offset: 16 bytes
_FAP_SUB = struct.Struct(
    "<3B4Bx"
)  # viseme (s1, s2, blend), expression (s1, i1, s2, i2), pad: 8 bytes

#: Limits a decoder enforces before allocating anything (a frame claiming more is refused).
MAX_VERTICES = 4_000_000  # 48 MB of float32 positions: far above any face mesh
MAX_SAMPLES = 1 << 20  # ~22 s of 48 kHz audio in one chunk; live chunks are 10-100 ms
MAX_MARKERS = 4096  # optical mocap layouts have tens to a few hundred markers
MAX_RATE = 384_000  # Hz
N_FAP_VALUES = 68  # FAP 1..68; values[k - 1] is FAP k


class Kind(IntEnum):
    """Frame kinds (header byte 5)."""

    VERTICES_F32 = 1  #: server -> viewer: (V, 3) float32 positions
    VERTICES_I16 = 2  #: server -> viewer: (V, 3) int16 positions with per-axis offset and scale
    PCM_I16 = 3  #: producer -> server: (n,) int16 mono samples
    PCM_F32 = 4  #: producer -> server: (n,) float32 mono samples in [-1, 1]
    MARKERS = 5  #: producer -> server: (M, 3) float32 marker positions, NaN = occluded
    FAPS = 6  #: producer -> server: 68 float32 FAP values (NaN = not sent) + viseme/expression
    VERTICES_COMPACT = 7  #: server -> viewer: error-bounded delta frames (``compact.py``)


class Flag(IntEnum):
    """Header flag bits (header bytes 6-7)."""

    VISEME = 1  #: FAPS: the viseme sub-header fields are set
    EXPRESSION = 2  #: FAPS: the expression sub-header fields are set


_KNOWN_FLAGS = {Kind.FAPS: Flag.VISEME | Flag.EXPRESSION, Kind.VERTICES_COMPACT: 1}  # compact.KEY


@dataclass(frozen=True, slots=True)
class Header:
    """The fixed 32-byte header shared by every frame.

    Attributes:
        kind: what follows.
        seq: sequence number (uint32, wraps); the server numbers output frames consecutively, so
            a gap of n means n frames were skipped for this receiver.
        count: vertices, samples, markers or FAP values in the payload.
        t: media time in seconds from the session's start (first sample / the frame's instant).
        wall: the producer's wall clock (Unix seconds) when it sent the input that made this
            frame, copied by the server into the vertex frames it produces; 0.0 = unknown.
        flags: kind-specific bits (``Flag``).
        version: protocol version (``VERSION``).
    """

    kind: Kind
    seq: int
    count: int
    t: float
    wall: float = 0.0
    flags: int = 0
    version: int = VERSION


def parse_header(data: bytes | bytearray | memoryview) -> Header:
    """The header of a frame; checks magic, version, kind and flags but not the payload size."""
    if len(data) < HEADER_SIZE:
        raise FrameError(
            f"frame of {len(data)} bytes is shorter than the {HEADER_SIZE}-byte header"
        )
    magic, version, kind, flags, seq, count, t, wall = _HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise FrameError(
            f"bad magic {bytes(magic)!r}, expected {MAGIC!r}: not a facecast frame",
            where="bytes 0-3",
        )
    if version != VERSION:
        raise FrameError(
            f"protocol version {version} is not supported (this side speaks {VERSION})",
            where="byte 4",
        )
    try:
        k = Kind(kind)
    except ValueError:
        raise FrameError(
            f"unknown frame kind {kind}; known: " + ", ".join(f"{m.value}={m.name}" for m in Kind),
            where="byte 5",
        ) from None
    if flags & ~_KNOWN_FLAGS.get(k, 0):
        raise FrameError(f"unknown flag bits 0x{flags:04x} for kind {k.name}", where="bytes 6-7")
    if not (math.isfinite(t) and math.isfinite(wall)):
        raise FrameError("media time and wall time must be finite", where="bytes 16-31")
    return Header(k, seq, count, t, wall, flags, version)


@dataclass(frozen=True, slots=True)
class VertexFrame:
    """Deformed vertex positions at media time ``header.t``.

    ``vertices`` is ``(V, 3) float32`` for ``VERTICES_F32``; for ``VERTICES_I16`` it is ``(V, 3)
    int16`` and positions are ``offset + vertices * scale`` (``positions()`` does that).
    """

    header: Header
    vertices: np.ndarray
    offset: np.ndarray | None = None  # (3,) float32, i16 only
    scale: np.ndarray | None = None  # (3,) float32, i16 only

    def positions(self) -> np.ndarray:
        """``(V, 3) float32`` positions (a view for float32 frames, dequantised for int16; compact
        frames arrive decoded)."""
        if self.header.kind is not Kind.VERTICES_I16:
            return self.vertices
        assert self.offset is not None and self.scale is not None  # parse_frame sets both for i16
        return dequantize_int16(self.vertices, self.offset, self.scale)


@dataclass(frozen=True, slots=True)
class PcmChunk:
    """Mono audio: ``samples (n,)`` int16 or float32 at ``rate`` Hz, first sample at ``sample_offset``.

    ``header.t`` is ``sample_offset / rate`` as sent by the producer.
    """

    header: Header
    rate: int
    sample_offset: int
    samples: np.ndarray

    def as_float32(self) -> np.ndarray:
        """``(n,) float32`` in [-1, 1] (int16 is divided by 32768)."""
        if self.samples.dtype == np.int16:
            scaled: np.ndarray = self.samples.astype(np.float32) * np.float32(1.0 / 32768.0)
            return scaled
        return self.samples


@dataclass(frozen=True, slots=True)
class MarkerFrame:
    """``markers (M, 3) float32`` in the producer's units (NaN = occluded); names come from the hello."""

    header: Header
    markers: np.ndarray


@dataclass(frozen=True, slots=True)
class FapFrame:
    """One MPEG-4 FAP frame: ``values (68,) float32``, ``values[k-1]`` = FAP k in its FAPU; NaN =
    not sent (the receiver keeps the previous value). FAPs 1 and 2 travel as ``viseme`` /
    ``expression`` instead (their slots in ``values`` are ignored)."""

    header: Header
    values: np.ndarray
    viseme: tuple[int, int, int] | None = None
    expression: tuple[int, int, int, int] | None = None


Frame = VertexFrame | PcmChunk | MarkerFrame | FapFrame


# ---------------------------------------------------------------------------------------------- encode


def _header(kind: Kind, seq: int, count: int, t: float, wall: float, flags: int = 0) -> bytes:
    if not 0 <= count <= 0xFFFFFFFF:
        raise ValueError(f"count {count} does not fit in uint32")
    return _HEADER.pack(
        MAGIC, VERSION, int(kind), flags, int(seq) & 0xFFFFFFFF, count, float(t), float(wall)
    )


def _vertices_array(vertices: np.ndarray) -> np.ndarray:
    v = np.ascontiguousarray(vertices, dtype="<f4")
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    return v


def encode_vertices_f32(vertices: np.ndarray, *, seq: int, t: float, wall: float = 0.0) -> bytes:
    """``(V, 3)`` positions -> a ``VERTICES_F32`` frame (32 + 12·V bytes, one copy of the data)."""
    v = _vertices_array(vertices)
    return b"".join((_header(Kind.VERTICES_F32, seq, v.shape[0], t, wall), v.data))


def encode_vertices_i16(vertices: np.ndarray, *, seq: int, t: float, wall: float = 0.0) -> bytes:
    """``(V, 3)`` positions -> a ``VERTICES_I16`` frame (56 + 6·V bytes), quantised per frame with
    ``quantize_int16`` (error per axis at most half a step, ``scale / 2``)."""
    v = _vertices_array(vertices)
    q, offset, scale = quantize_int16(v)
    return b"".join(
        (
            _header(Kind.VERTICES_I16, seq, v.shape[0], t, wall),
            _I16_SUB.pack(*offset.tolist(), *scale.tolist()),
            q.data,
        )
    )


def vertex_frame_size(encoding: VertexEncoding, n_vertices: int) -> int:
    """Bytes of a vertex frame of ``n_vertices`` in ``encoding`` (``"f32"`` | ``"i16"``)."""
    if encoding == "f32":
        return HEADER_SIZE + 12 * n_vertices
    if encoding == "i16":
        return HEADER_SIZE + _I16_SUB.size + 6 * n_vertices
    raise ValueError(f"unknown vertex encoding {encoding!r}; use 'f32' or 'i16'")


def vertex_frame_header(
    encoding: VertexEncoding,
    n_vertices: int,
    *,
    seq: int,
    t: float,
    wall: float = 0.0,
    offset: np.ndarray | None = None,
    scale: np.ndarray | None = None,
) -> bytes:
    """The bytes of a vertex frame that precede its vertex data (the header, plus ``offset`` and
    ``scale`` for i16). Followed by the ``(V, 3)`` data (``<f4``, or ``<i2`` from
    ``quantize.quantize_int16``) they make exactly the frame ``encode_vertices`` makes."""
    if encoding == "f32":
        return _header(Kind.VERTICES_F32, seq, n_vertices, t, wall)
    if offset is None or scale is None:
        raise ValueError("an i16 vertex frame header needs offset and scale")
    return b"".join(
        (
            _header(Kind.VERTICES_I16, seq, n_vertices, t, wall),
            _I16_SUB.pack(*offset.tolist(), *scale.tolist()),
        )
    )


def encode_vertices(
    vertices: np.ndarray, encoding: VertexEncoding, *, seq: int, t: float, wall: float = 0.0
) -> bytes:
    """``encoding`` is ``"f32"`` or ``"i16"``."""
    if encoding == "f32":
        return encode_vertices_f32(vertices, seq=seq, t=t, wall=wall)
    if encoding == "i16":
        return encode_vertices_i16(vertices, seq=seq, t=t, wall=wall)
    raise ValueError(f"unknown vertex encoding {encoding!r}; use 'f32' or 'i16'")


def encode_pcm(
    samples: np.ndarray,
    *,
    rate: int,
    sample_offset: int,
    seq: int,
    wall: float = 0.0,
    t: float | None = None,
) -> bytes:
    """Mono ``(n,)`` int16 or float32 samples -> a ``PCM_I16`` / ``PCM_F32`` chunk (48 + 2n or 4n bytes).

    ``t`` defaults to ``sample_offset / rate``.
    """
    s = np.asarray(samples)
    if s.ndim != 1:
        raise ValueError(f"samples must be mono (n,), got {s.shape}")
    if s.dtype == np.int16:
        kind, s = Kind.PCM_I16, np.ascontiguousarray(s, dtype="<i2")
    elif s.dtype == np.float32:
        kind, s = Kind.PCM_F32, np.ascontiguousarray(s, dtype="<f4")
    else:
        raise TypeError(f"samples must be int16 or float32, got {s.dtype}")
    if not 0 < rate <= MAX_RATE or sample_offset < 0:
        raise ValueError(f"bad rate {rate} or sample offset {sample_offset}")
    t = sample_offset / rate if t is None else t
    return b"".join(
        (
            _header(kind, seq, s.shape[0], t, wall),
            _PCM_SUB.pack(rate, 1, 0, sample_offset),
            s.data,
        )
    )


def encode_markers(markers: np.ndarray, *, seq: int, t: float, wall: float = 0.0) -> bytes:
    """``(M, 3)`` marker positions (NaN = occluded) -> a ``MARKERS`` frame (32 + 12·M bytes)."""
    m = np.ascontiguousarray(markers, dtype="<f4")
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"markers must be (M, 3), got {m.shape}")
    return b"".join((_header(Kind.MARKERS, seq, m.shape[0], t, wall), m.data))


def encode_faps(
    values: np.ndarray,
    *,
    seq: int,
    t: float,
    wall: float = 0.0,
    viseme: tuple[int, int, int] | None = None,
    expression: tuple[int, int, int, int] | None = None,
) -> bytes:
    """``(68,)`` FAP values (``values[k-1]`` = FAP k, NaN = not sent) -> a ``FAPS`` frame (312 bytes).

    Also accepts a ``(69,)`` vector indexed by FAP number (``FaceState.faps``); its index 0 is dropped.
    """
    v = np.asarray(values, dtype="<f4")
    if v.shape == (N_FAP_VALUES + 1,):
        v = v[1:]
    if v.shape != (N_FAP_VALUES,):
        raise ValueError(
            f"FAP values must be ({N_FAP_VALUES},) or ({N_FAP_VALUES + 1},), got {v.shape}"
        )
    flags = (Flag.VISEME if viseme is not None else 0) | (
        Flag.EXPRESSION if expression is not None else 0
    )
    vis = tuple(viseme) if viseme is not None else (0, 0, 0)
    exp = tuple(expression) if expression is not None else (0, 0, 0, 0)
    _check_viseme(vis)
    _check_expression(exp)
    return b"".join(
        (
            _header(Kind.FAPS, seq, N_FAP_VALUES, t, wall, flags),
            _FAP_SUB.pack(*vis, *exp),
            np.ascontiguousarray(v).tobytes(),
        )
    )


def _check_viseme(v: tuple[int, ...], exc: type[Exception] = ValueError) -> None:
    if not (0 <= v[0] <= 14 and 0 <= v[1] <= 14 and 0 <= v[2] <= 63):
        raise exc(f"viseme {v} out of range: ids 0-14, blend 0-63")


def _check_expression(e: tuple[int, ...], exc: type[Exception] = ValueError) -> None:
    if not (0 <= e[0] <= 6 and 0 <= e[2] <= 6 and 0 <= e[1] <= 63 and 0 <= e[3] <= 63):
        raise exc(f"expression {e} out of range: ids 0-6, intensities 0-63")


# ---------------------------------------------------------------------------------------------- decode


def frame_size(header: Header, data: bytes | bytearray | memoryview | None = None) -> int:
    """The exact byte size a frame with ``header`` must have (PCM needs nothing beyond the header)."""
    k, n = header.kind, header.count
    if k is Kind.VERTICES_F32:
        return HEADER_SIZE + 12 * n
    if k is Kind.VERTICES_I16:
        return HEADER_SIZE + _I16_SUB.size + 6 * n
    if k is Kind.PCM_I16:
        return HEADER_SIZE + _PCM_SUB.size + 2 * n
    if k is Kind.PCM_F32:
        return HEADER_SIZE + _PCM_SUB.size + 4 * n
    if k is Kind.MARKERS:
        return HEADER_SIZE + 12 * n
    return HEADER_SIZE + _FAP_SUB.size + 4 * n  # FAPS


_LIMITS = {
    Kind.VERTICES_F32: MAX_VERTICES,
    Kind.VERTICES_I16: MAX_VERTICES,
    Kind.PCM_I16: MAX_SAMPLES,
    Kind.PCM_F32: MAX_SAMPLES,
    Kind.MARKERS: MAX_MARKERS,
    Kind.FAPS: N_FAP_VALUES,
}


def decode(data: bytes | bytearray | memoryview, *, kinds: frozenset[Kind] | None = None) -> Frame:
    """Parse one binary frame. Payload arrays are zero-copy views on ``data``.

    Args:
        data: one whole binary WebSocket message.
        kinds: if given, only these kinds are accepted (a server accepts only producer kinds).

    Raises:
        FrameError: truncated, trailing bytes, bad magic/version/kind/flags, counts over the
            limits, or inconsistent sub-header values.
    """
    h = parse_header(data)
    if kinds is not None and h.kind not in kinds:
        raise FrameError(
            f"frame kind {h.kind.name} is not accepted here; expected "
            + " or ".join(k.name for k in sorted(kinds)),
            where="byte 5",
        )
    if h.kind is Kind.VERTICES_COMPACT:
        raise FrameError(
            "VERTICES_COMPACT frames depend on earlier frames: decode them with "
            "compact.CompactDecoder",
            where="byte 5",
        )
    limit = _LIMITS[h.kind]
    if h.kind is Kind.FAPS:
        if h.count != N_FAP_VALUES:
            raise FrameError(
                f"a FAP frame carries exactly {N_FAP_VALUES} values, header says {h.count}",
                where="bytes 12-15",
            )
    elif h.count > limit:
        raise FrameError(
            f"count {h.count} is over the limit of {limit} for {h.kind.name}", where="bytes 12-15"
        )
    size = frame_size(h)
    if len(data) != size:
        what = "truncated" if len(data) < size else "has trailing bytes"
        raise FrameError(
            f"{h.kind.name} frame of {h.count} items must be {size} bytes, got {len(data)} ({what})"
        )
    k, n, o = h.kind, h.count, HEADER_SIZE
    if k is Kind.VERTICES_F32:
        return VertexFrame(h, np.frombuffer(data, "<f4", 3 * n, o).reshape(n, 3))
    if k is Kind.VERTICES_I16:
        sub = _I16_SUB.unpack_from(data, o)
        offset, scale = np.array(sub[:3], np.float32), np.array(sub[3:], np.float32)
        if not (np.all(np.isfinite(offset)) and np.all(np.isfinite(scale)) and np.all(scale > 0)):
            raise FrameError(
                "int16 frame offset/scale must be finite with scale > 0", where="bytes 32-55"
            )
        return VertexFrame(
            h, np.frombuffer(data, "<i2", 3 * n, o + _I16_SUB.size).reshape(n, 3), offset, scale
        )
    if k in (Kind.PCM_I16, Kind.PCM_F32):
        rate, channels, _reserved, sample_offset = _PCM_SUB.unpack_from(data, o)
        if not 0 < rate <= MAX_RATE:
            raise FrameError(
                f"sample rate {rate} Hz is out of range 1..{MAX_RATE}", where="bytes 32-35"
            )
        if channels != 1:
            raise FrameError(
                f"only mono PCM is supported, got {channels} channels", where="bytes 36-37"
            )
        dtype = "<i2" if k is Kind.PCM_I16 else "<f4"
        return PcmChunk(h, rate, sample_offset, np.frombuffer(data, dtype, n, o + _PCM_SUB.size))
    if k is Kind.MARKERS:
        return MarkerFrame(h, np.frombuffer(data, "<f4", 3 * n, o).reshape(n, 3))
    sub = _FAP_SUB.unpack_from(data, o)
    vis = sub[:3] if h.flags & Flag.VISEME else None
    exp = sub[3:7] if h.flags & Flag.EXPRESSION else None
    if vis is not None:
        _check_viseme(vis, FrameError)
    if exp is not None:
        _check_expression(exp, FrameError)
    values = np.frombuffer(data, "<f4", n, o + _FAP_SUB.size)
    if np.count_nonzero(np.isinf(values)):  # (``.any()`` costs twice as much on 68 values)
        raise FrameError("FAP values must be finite (NaN means 'not sent')", where="bytes 40-311")
    return FapFrame(h, values, vis, exp)
