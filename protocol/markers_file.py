"""Marker take files as text: TRC (OpenSim / Motion Analysis) and CSV. Pure parsing, no I/O.

A take is ``MarkerTake(names, xyz (T, M, 3) float64, fps, units)``; NaN marks an occluded marker.
CSV layout: a header ``time, <name>_x, <name>_y, <name>_z, ...`` then one row per frame (seconds;
empty cells or ``nan`` = occluded). Units of a CSV come from an optional first comment line
``# units=mm`` (else ``None``: the reader of the take decides). ``read_c3d`` parses the 3-D points
of a C3D file from its bytes (Intel, DEC or MIPS; int16 or float storage) and ``write_c3d`` writes
one: the one C3D path of server and clients, safe for hostile bytes (every count is checked against
the bytes present; malformed input raises ``MarkerFileError``, never anything else).
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import FileFormatError
from .errors import show_token as _show
from .units import UNIT_MM, unit_name


class MarkerFileError(FileFormatError):
    """A malformed take file; ``where`` names the file/line/column at fault."""


@dataclass
class MarkerTake:
    """Marker trajectories.

    Attributes:
        names: marker names, ``M`` of them, unique.
        xyz: ``(T, M, 3) float64`` positions in ``units``; NaN = occluded.
        fps: frames per second.
        units: a name in ``units.UNIT_MM`` (``"mm"``, ``"cm"``, ...) or None when the file does
            not say.
        t0: media time of frame 0 in seconds.
    """

    names: list[str]
    xyz: np.ndarray
    fps: float
    units: str | None = None
    t0: float = 0.0

    @property
    def n_frames(self) -> int:
        return int(self.xyz.shape[0])

    def in_mm(self) -> np.ndarray:
        """``(T, M, 3) float64`` positions in millimetres (units must be known)."""
        if self.units not in UNIT_MM:
            raise MarkerFileError(f"units of the take are unknown ({self.units!r}); declare them")
        return self.xyz * UNIT_MM[self.units]


def normalise_units(text: str | None, where: str = "") -> str | None:
    """``"Millimeters"``/``"mm"`` -> ``"mm"`` etc.; None stays None; unknown -> MarkerFileError."""
    if text is None:
        return None
    name = unit_name(text) if isinstance(text, str) else None
    if name is None:
        raise MarkerFileError(
            f"unknown length unit {_show(str(text))}; use one of {', '.join(UNIT_MM)}", where=where
        )
    return name


def check_take(take: MarkerTake, where: str = "") -> MarkerTake:
    """Validate shapes, names, rate and units; return the take (xyz as float64)."""
    xyz = np.asarray(take.xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.shape[1] != len(take.names):
        raise MarkerFileError(
            f"positions must be (frames, {len(take.names)}, 3), got {xyz.shape}", where=where
        )
    if len(set(take.names)) != len(take.names):
        dup = sorted({n for n in take.names if take.names.count(n) > 1})
        raise MarkerFileError(f"duplicate marker names: {', '.join(dup)}", where=where)
    if not take.names:
        raise MarkerFileError("the take names no markers", where=where)
    if not (math.isfinite(take.fps) and take.fps > 0):
        raise MarkerFileError(f"frame rate must be positive, got {take.fps}", where=where)
    if take.units is not None and take.units not in UNIT_MM:
        raise MarkerFileError(
            f"units {_show(str(take.units))} are not one of {', '.join(UNIT_MM)}", where=where
        )
    if np.isinf(xyz).any():
        xyz = np.where(np.isinf(xyz), np.nan, xyz)
    take.xyz = xyz
    return take


def _float(cell: str, what: str, where: str, *, finite: bool = False) -> float:
    """A number cell (empty: NaN); MarkerFileError naming ``what`` and ``where`` otherwise."""
    if not cell.strip():
        if finite:
            raise MarkerFileError(f"{what} is empty", where=where)
        return math.nan
    try:
        v = float(cell)
    except ValueError:
        raise MarkerFileError(
            f"{what} {_show(cell.strip())} is not a number", where=where
        ) from None
    if finite and not math.isfinite(v):
        raise MarkerFileError(f"{what} {_show(cell.strip())} must be finite", where=where)
    return v


# --------------------------------------------------------------------------------------------- TRC


def read_trc(text: str, *, where: str = "") -> MarkerTake:
    """Parse a TRC file (tab-separated; header lines 1-5 as written by Motion Analysis / OpenSim)."""
    lines = text.splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise MarkerFileError("not a TRC file (line 1 must start with 'PathFileType')", where=where)
    keys = [k.strip() for k in lines[1].split("\t")]
    vals = [v.strip() for v in lines[2].split("\t")]
    meta = dict(zip(keys, vals))
    try:
        fps = float(meta.get("DataRate") or meta.get("CameraRate") or "nan")
        n_markers = int(meta["NumMarkers"])
    except (KeyError, ValueError):
        raise MarkerFileError(
            "line 3 must give DataRate and NumMarkers", where=f"{where}:3"
        ) from None
    units = normalise_units(meta.get("Units"), where=f"{where}:3") if meta.get("Units") else None
    header = lines[3].split("\t")
    names = [h.strip() for h in header[2:] if h.strip()]
    if len(names) != n_markers:
        raise MarkerFileError(
            f"line 4 names {len(names)} markers but NumMarkers is {n_markers}", where=f"{where}:4"
        )
    rows: list[np.ndarray] = []
    times: list[float] = []
    for ln, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        cells = line.split("\t")
        if len(cells) < 2:
            raise MarkerFileError("expected Frame#, Time, then coordinates", where=f"{where}:{ln}")
        times.append(_float(cells[1], "time", f"{where}:{ln}", finite=True))
        coords = cells[2 : 2 + 3 * n_markers]
        coords += [""] * (3 * n_markers - len(coords))
        rows.append(np.array([_float(c, "coordinate", f"{where}:{ln}") for c in coords]))
    if not rows:
        raise MarkerFileError("the file has no frames", where=where)
    xyz = np.stack(rows).reshape(len(rows), n_markers, 3)
    return check_take(MarkerTake(names, xyz, fps, units, times[0] if times else 0.0), where)


def write_trc(take: MarkerTake, *, filename: str = "take.trc") -> str:
    """TRC text for ``take`` (occluded coordinates are empty cells)."""
    take = check_take(take)
    t, m = take.xyz.shape[:2]
    out = io.StringIO()
    out.write(f"PathFileType\t4\t(X/Y/Z)\t{filename}\n")
    out.write(
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    )
    out.write(f"{take.fps:g}\t{take.fps:g}\t{t}\t{m}\t{take.units or 'mm'}\t{take.fps:g}\t1\t{t}\n")
    out.write("Frame#\tTime\t" + "\t\t\t".join(take.names) + "\t\t\n")
    out.write("\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(m)) + "\n")
    for f in range(t):
        cells = ["" if not np.isfinite(v) else repr(float(v)) for v in take.xyz[f].ravel()]
        out.write(f"{f + 1}\t{take.t0 + f / take.fps:.6f}\t" + "\t".join(cells) + "\n")
    return out.getvalue()


# --------------------------------------------------------------------------------------------- CSV


def read_csv(text: str, *, where: str = "", fps: float | None = None) -> MarkerTake:
    """Parse a CSV take (see module docstring). The rate comes from the time column unless given."""
    lines = text.splitlines()
    units = None
    start = 0
    while start < len(lines) and (lines[start].startswith("#") or not lines[start].strip()):
        for part in lines[start].lstrip("#").replace(",", " ").split():
            k, _, v = part.partition("=")
            if k.strip().lower() == "units" and v:
                units = normalise_units(v, where=f"{where}:{start + 1}")
        start += 1
    if start >= len(lines):
        raise MarkerFileError("no header line", where=where)
    header = [h.strip() for h in lines[start].split(",")]
    if not header or header[0].lower() not in ("time", "t", "time_s", "seconds"):
        raise MarkerFileError(
            "the first column must be 'time' (seconds)", where=f"{where}:{start + 1}"
        )
    cols = header[1:]
    if len(cols) % 3:
        raise MarkerFileError(
            f"{len(cols)} coordinate columns is not a multiple of 3", where=f"{where}:{start + 1}"
        )
    names = []
    for i in range(0, len(cols), 3):
        trio = cols[i : i + 3]
        base = trio[0][:-2]
        if (
            not base
            or [c[-2:].lower() for c in trio] != ["_x", "_y", "_z"]
            or any(c[:-2] != base for c in trio)
        ):
            shown = ", ".join(_show(c) for c in trio)
            raise MarkerFileError(
                f"columns {shown} must be <name>_x, <name>_y, <name>_z",
                where=f"{where}:{start + 1}",
            )
        names.append(base)
    times, rows = [], []
    for ln, line in enumerate(lines[start + 1 :], start=start + 2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != len(header):
            raise MarkerFileError(
                f"{len(cells)} cells, the header has {len(header)}", where=f"{where}:{ln}"
            )
        times.append(_float(cells[0], "time", f"{where}:{ln}", finite=True))
        rows.append([_float(c, "coordinate", f"{where}:{ln}") for c in cells[1:]])
    if not rows:
        raise MarkerFileError("the file has no frames", where=where)
    tt = np.asarray(times)
    if fps is None:
        if len(tt) < 2:
            raise MarkerFileError(
                "one frame only: cannot tell the frame rate; pass fps", where=where
            )
        dt = np.diff(tt)
        if (dt <= 0).any():
            raise MarkerFileError("time column must increase", where=where)
        with np.errstate(over="ignore", divide="ignore"):
            fps = float(1.0 / np.median(dt))
        if not (math.isfinite(fps) and 0 < fps <= 1e6):
            raise MarkerFileError(f"the time column gives a frame rate of {fps:g} Hz", where=where)
        if abs(fps - round(fps)) < 1e-3 * fps:  # times are printed with finite precision
            fps = float(round(fps))
    xyz = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(names), 3)
    return check_take(MarkerTake(names, xyz, fps, units, float(tt[0])), where)


def write_csv(take: MarkerTake) -> str:
    """CSV text for ``take``; occluded coordinates are empty cells."""
    take = check_take(take)
    out = io.StringIO()
    if take.units:
        out.write(f"# units={take.units}\n")
    out.write("time," + ",".join(f"{n}_x,{n}_y,{n}_z" for n in take.names) + "\n")
    for f in range(take.n_frames):
        cells = ["" if not np.isfinite(v) else repr(float(v)) for v in take.xyz[f].ravel()]
        out.write(f"{take.t0 + f / take.fps:.9f}," + ",".join(cells) + "\n")
    return out.getvalue()


# --------------------------------------------------------------------------------------------- C3D
#
# A C3D file is 512-byte blocks: a header block, a parameter section (groups and typed parameters,
# a linked list of byte offsets), then frames of ``4 * points + analog samples`` words (int16 when
# POINT:SCALE > 0, float32 when < 0). Numbers follow the processor type: Intel (little-endian IEEE),
# DEC (little-endian integers, VAX F-floating reals) or MIPS (big-endian IEEE). The reader trusts no
# count: every length is checked against the bytes present before anything is allocated or looped.

#: C3D processor types: byte 4 of the parameter section is ``83 + n``.
C3D_PROCESSORS = {84: "intel", 85: "dec", 86: "mips"}
#: Parameter types: bytes per element (-1: characters).
_C3D_TYPES = (-1, 1, 2, 4)
#: More parameters than any capture system writes (real files hold a few hundred).
_C3D_MAX_ENTRIES = 10_000


@dataclass(frozen=True)
class _C3dParam:
    type: int
    dims: tuple[int, ...]
    raw: memoryview  # a view into the file: entries may overlap, so values are never copied


def _dec_to_float(u: np.ndarray) -> np.ndarray:
    """DEC (VAX F-floating) reals read as little-endian uint32 -> float64.

    The DEC layout is IEEE's with the two 16-bit words swapped, a mantissa in [0.5, 1) and the
    exponent biased by 128: ``(-1)^s * (0.5 + f / 2^24) * 2^(e - 128)``; ``e = 0`` is zero.
    """
    u = np.asarray(u, dtype=np.uint64)
    w = ((u & 0xFFFF) << 16) | (u >> 16)
    e = ((w >> 23) & 0xFF).astype(np.int64)
    v = np.ldexp(0.5 + (w & 0x7FFFFF).astype(np.float64) / 2.0**24, e - 128)
    neg = (w >> 31).astype(bool)
    v = np.where(neg, -v, v)
    return np.where(e == 0, np.where(neg, np.nan, 0.0), v)  # sign with e = 0: "reserved operand"


def _float_to_dec(x: np.ndarray) -> np.ndarray:
    """float64 -> DEC reals as little-endian uint32 (float32 precision; inverse of _dec_to_float)."""
    x = np.asarray(x, dtype=np.float32).astype(np.float64)
    if not np.isfinite(x).all():
        raise ValueError("DEC reals cannot hold NaN or infinity")
    m, e = np.frexp(np.abs(x))
    e = e.astype(np.int64) + 128
    tiny = (x == 0) | (e <= 0)
    if (e[~tiny] > 255).any():
        raise ValueError("value too large for a DEC real")
    f = np.round((m - 0.5) * 2.0**24).astype(np.uint64)
    w = (np.signbit(x).astype(np.uint64) << 31) | (np.clip(e, 0, 255).astype(np.uint64) << 23) | f
    w = np.where(tiny, 0, w).astype(np.uint64)
    return (((w & 0xFFFF) << 16) | (w >> 16)).astype("<u4")


@dataclass(frozen=True)
class _C3dCodec:
    """Numbers in one processor type's byte order and real format."""

    processor: str

    @property
    def order(self) -> str:
        return ">" if self.processor == "mips" else "<"

    @property
    def real_dtype(self) -> str:
        """dtype of a stored real (DEC reals are read as raw words and converted)."""
        return "<u4" if self.processor == "dec" else self.order + "f4"

    def reals(self, a: np.ndarray) -> np.ndarray:
        """Stored reals (``real_dtype``) -> float64 (signalling NaNs become quiet NaNs silently)."""
        if self.processor == "dec":
            return _dec_to_float(a)
        with np.errstate(invalid="ignore"):
            return a.astype(np.float64)

    def real(self, data: bytes, offset: int) -> float:
        return float(self.reals(np.frombuffer(data, self.real_dtype, 1, offset))[0])

    def word(self, data: bytes, offset: int) -> int:
        """An unsigned 16-bit word."""
        return int(np.frombuffer(data, self.order + "u2", 1, offset)[0])

    def encode_reals(self, x: ArrayLike) -> bytes:
        if self.processor == "dec":
            return _float_to_dec(np.ravel(x)).tobytes()
        return np.asarray(x, dtype=self.order + "f4").tobytes()

    def encode_words(self, x: ArrayLike) -> bytes:
        return np.asarray(x, dtype=self.order + "i2").tobytes()


def _i8(b: int) -> int:
    """A byte as a signed 8-bit number."""
    return b - 256 if b > 127 else b


def _c3d_parameters(
    data: bytes, start: int, end: int, codec: _C3dCodec, where: str
) -> dict[str, dict[str, _C3dParam]]:
    """Groups -> parameters of the parameter section in ``data[start:end]`` (names upper case)."""
    groups: dict[int, str] = {}
    params: dict[int, dict[str, _C3dParam]] = {}
    view = memoryview(data)
    pos = start + 4
    for _ in range(_C3D_MAX_ENTRIES):
        if pos + 2 > end:
            break  # ran into the end of the section without an end marker: what was read stands
        name_len, gid = abs(_i8(data[pos])), _i8(data[pos + 1])
        if name_len == 0 or gid == 0:
            break  # end marker
        at = f"{where}: parameter section byte {pos}"
        off = pos + 2 + name_len
        if off + 2 > end:
            raise MarkerFileError(
                "the parameter section is cut short (a name runs past it)", where=at
            )
        name = data[pos + 2 : off].decode("latin-1").strip().upper()
        nxt = int(np.frombuffer(data, codec.order + "i2", 1, off)[0])
        body = off + 2
        if gid < 0:
            groups[-gid] = name
        else:
            if body + 2 > end:
                raise MarkerFileError(f"parameter {name} is cut short", where=at)
            ptype, ndim = _i8(data[body]), data[body + 1]
            if ptype not in _C3D_TYPES:
                raise MarkerFileError(
                    f"parameter {name} has type {ptype}; C3D types are -1 (text), 1, 2 and 4 "
                    "(bytes per number)",
                    where=at,
                )
            dims = tuple(data[body + 2 : body + 2 + ndim])
            size = abs(ptype) * math.prod(dims)
            first = body + 2 + ndim
            if first + size > end:
                raise MarkerFileError(
                    f"parameter {name} declares {size} bytes of values; the section holds "
                    f"{max(0, end - first)} more",
                    where=at,
                )
            params.setdefault(gid, {})[name] = _C3dParam(ptype, dims, view[first : first + size])
        if nxt == 0:
            break  # the last entry
        if nxt < 0:
            raise MarkerFileError(
                f"entry {name} points {nxt} bytes back; pointers to the next entry must be positive",
                where=at,
            )
        pos = off + nxt
    else:
        raise MarkerFileError(f"more than {_C3D_MAX_ENTRIES} parameters", where=where)
    return {groups.get(g, str(g)): p for g, p in params.items()}


def _c3d_numbers(p: _C3dParam, codec: _C3dCodec) -> np.ndarray:
    """A numeric parameter's values, flattened (int64 or float64)."""
    if p.type == 1:
        return np.frombuffer(p.raw, np.int8).astype(np.int64)
    if p.type == 2:
        return np.frombuffer(p.raw, codec.order + "i2").astype(np.int64)
    return codec.reals(np.frombuffer(p.raw, codec.real_dtype))


def _c3d_strings(p: _C3dParam, limit: int) -> list[str]:
    """A text parameter's first ``limit`` strings (the first dimension is the length of each)."""
    if len(p.dims) <= 1:
        return [bytes(p.raw).decode("latin-1").strip()]
    w = p.dims[0]
    n = min(math.prod(p.dims[1:]), limit)
    if not w:
        return [""] * n
    return [bytes(p.raw[i * w : (i + 1) * w]).decode("latin-1").strip() for i in range(n)]


def read_c3d(data: bytes, *, where: str = "") -> MarkerTake:
    """Parse the 3-D points of a C3D file (Intel, DEC or MIPS; int16 or float32 storage).

    Points whose residual word is negative, or whose coordinates are not finite, are occluded (NaN);
    analog samples are skipped. Labels come from ``POINT:LABELS``, ``LABELS2``, ...; units from
    ``POINT:UNITS`` (None if absent); counts, scale, rate and data start from the ``POINT``
    parameters where present, else the header. A file that is malformed, or holds fewer frames than
    it declares, raises MarkerFileError saying what is wrong; no partial take is returned.
    """
    data = bytes(data)
    if len(data) < 512 or data[1] != 0x50:
        raise MarkerFileError("not a C3D file (byte 2 of the header must be 0x50)", where=where)
    if data[0] < 2:
        raise MarkerFileError(
            f"the header puts the parameter section at block {data[0]}; it must follow the header "
            "(block 2 or later)",
            where=where,
        )
    pstart = (data[0] - 1) * 512
    if pstart + 4 > len(data):
        raise MarkerFileError(
            f"the parameter section (block {data[0]}) is past the end of the file "
            f"({len(data)} bytes); the file was cut short",
            where=where,
        )
    if data[pstart + 3] not in C3D_PROCESSORS:
        raise MarkerFileError(
            f"processor type {data[pstart + 3]} is unknown; C3D knows 84 (Intel), 85 (DEC) "
            "and 86 (MIPS)",
            where=where,
        )
    codec = _C3dCodec(C3D_PROCESSORS[data[pstart + 3]])
    n_points, n_analog, first, last = (codec.word(data, 2 * i) for i in (1, 2, 3, 4))
    data_start = codec.word(data, 16)
    scale, rate = codec.real(data, 12), codec.real(data, 20)
    section_end = (data_start - 1) * 512 if data_start - 1 > data[0] - 1 else len(data)
    params = _c3d_parameters(data, pstart, min(section_end, len(data)), codec, where)
    point = params.get("POINT", {})

    def number(group: str, name: str, default: float) -> float:
        p = params.get(group, {}).get(name)
        if p is None:
            return default
        if p.type == -1:
            raise MarkerFileError(f"{group}:{name} must be a number, it is text", where=where)
        v = _c3d_numbers(p, codec)
        if not len(v):
            raise MarkerFileError(f"{group}:{name} has no value", where=where)
        return float(v[0])

    def count(group: str, name: str, default: int) -> int:
        """A 16-bit count (stored signed; read unsigned, as capture systems mean it)."""
        x = number(group, name, default)
        p = params.get(group, {}).get(name)
        if p is not None and p.type == 2 and x < 0:
            x += 65536
        if not (math.isfinite(x) and 0 <= x < 2**31):
            raise MarkerFileError(f"{group}:{name} is {x}; it must be a count", where=where)
        return int(x)

    n_points = count("POINT", "USED", n_points)
    scale = number("POINT", "SCALE", scale)
    rate = number("POINT", "RATE", rate)
    data_start = count("POINT", "DATA_START", data_start) or data_start
    n_frames = max(last - first + 1, count("POINT", "FRAMES", 0))
    trial = params.get("TRIAL", {})
    if last == 65535 and all(
        k in trial and trial[k].type == 2 and len(trial[k].raw) >= 4
        for k in ("ACTUAL_START_FIELD", "ACTUAL_END_FIELD")
    ):  # long takes: frame numbers as two 16-bit words (low, high)
        s, e = (
            _c3d_numbers(trial[k], codec) & 0xFFFF
            for k in ("ACTUAL_START_FIELD", "ACTUAL_END_FIELD")
        )
        n_frames = max(n_frames, int(e[0] + 65536 * e[1]) - int(s[0] + 65536 * s[1]) + 1)

    labels: list[str] = []
    for key in ["LABELS"] + [f"LABELS{i}" for i in range(2, 100)]:
        if key not in point:
            break
        if point[key].type != -1:
            raise MarkerFileError(f"POINT:{key} must be text", where=where)
        labels += _c3d_strings(point[key], n_points - len(labels))
        if len(labels) >= n_points:
            break
    units = None
    if "UNITS" in point:
        if point["UNITS"].type != -1:
            raise MarkerFileError("POINT:UNITS must be text", where=where)
        u = next(iter(_c3d_strings(point["UNITS"], 1)), "")  # (width, 0) dimensions: no string
        units = normalise_units(u, where=f"{where}: POINT:UNITS") if u else None

    if n_points == 0:
        raise MarkerFileError("the file holds no 3-D points", where=where)
    if n_frames <= 0:
        raise MarkerFileError("the file holds no frames", where=where)
    if not math.isfinite(scale) or scale == 0:
        raise MarkerFileError(f"POINT:SCALE is {scale}; it must be a non-zero number", where=where)
    if not (math.isfinite(rate) and rate > 0):
        raise MarkerFileError(f"POINT:RATE is {rate}; it must be a positive number", where=where)
    if data_start < 2:
        raise MarkerFileError(
            f"the data start block is {data_start}; it must be 2 or later", where=where
        )
    word = 4 if scale < 0 else 2
    per_frame = (4 * n_points + n_analog) * word
    offset = (data_start - 1) * 512
    available = max(0, len(data) - offset) // per_frame
    if n_frames > available:
        raise MarkerFileError(
            f"the file declares {n_frames} frames of {n_points} points but holds {available}; "
            "it was cut short (re-export or re-send the whole file)",
            where=where,
        )
    dtype = codec.real_dtype if scale < 0 else codec.order + "i2"
    words = np.frombuffer(data, dtype, n_frames * per_frame // word, offset)
    block = words.reshape(n_frames, -1)[:, : 4 * n_points].reshape(n_frames, n_points, 4)
    block = codec.reals(block) if scale < 0 else block * np.array([scale, scale, scale, 1.0])
    xyz = block[..., :3]
    xyz[(block[..., 3] < 0) | ~np.isfinite(xyz).all(axis=2)] = np.nan
    names = [labels[i] if i < len(labels) and labels[i] else f"M{i:03d}" for i in range(n_points)]
    return check_take(MarkerTake(names, xyz, rate, units, (first - 1) / rate), where)


def _c3d_entry(name: str, gid: int, body: bytes, last: bool, order: str) -> bytes:
    """One group (``gid < 0``) or parameter entry: name, pointer to the next entry, body."""
    raw = name.encode("ascii")
    nxt = 0 if last else 2 + len(body)
    return bytes([len(raw), gid & 0xFF]) + raw + struct.pack(order + "h", nxt) + body


def write_c3d(take: MarkerTake, *, processor: str = "intel", scale: float = -1.0) -> bytes:
    """C3D bytes for ``take``: points only, float32 storage (``scale < 0``) or int16 (``scale > 0``:
    coordinates are stored as multiples of ``scale``). Occluded points have residual -1.

    ``processor`` is ``"intel"``, ``"dec"`` or ``"mips"``. Raises MarkerFileError if the take does
    not fit the format (more than 65535 markers, a label over 255 characters, int16 overflow).
    """
    take = check_take(take)
    if processor not in C3D_PROCESSORS.values():
        raise ValueError(f"processor must be one of {sorted(C3D_PROCESSORS.values())}")
    if not (math.isfinite(scale) and scale != 0):
        raise ValueError("scale must be a non-zero number")
    codec = _C3dCodec(processor)
    be = codec.order
    t, m = take.xyz.shape[:2]
    if m > 65535 or any(len(n.encode("latin-1", "replace")) > 255 for n in take.names):
        raise MarkerFileError("C3D holds at most 65535 markers with labels of 255 characters")
    first = max(1, round(take.t0 * take.fps) + 1)
    last = first + t - 1

    def param(
        name: str, gid: int, ptype: int, dims: tuple[int, ...], values: bytes
    ) -> tuple[str, int, bytes]:
        return name, gid, bytes([ptype & 0xFF, len(dims), *dims]) + values + b"\x00"

    def words(*x: int) -> bytes:
        return np.asarray(x, be + "u2").tobytes()

    def text(strings: list[str]) -> tuple[tuple[int, ...], bytes]:
        width = max(1, *(len(s) for s in strings))
        return (width, len(strings)), b"".join(
            s.encode("latin-1", "replace").ljust(width) for s in strings
        )

    def build(data_start: int) -> bytes:
        entries = [
            ("POINT", -1, b"\x00"),
            param("USED", 1, 2, (), words(m)),
            param("SCALE", 1, 4, (), codec.encode_reals([scale])),
            param("RATE", 1, 4, (), codec.encode_reals([take.fps])),
            param("DATA_START", 1, 2, (), words(data_start)),
            param("FRAMES", 1, 2, (), words(min(t, 65535))),
            param("UNITS", 1, -1, (len(take.units or "mm"),), (take.units or "mm").encode()),
        ]
        for k in range(0, m, 255):  # a dimension is one byte: 255 labels per parameter
            dims, raw = text(take.names[k : k + 255])
            entries.append(param("LABELS" if k == 0 else f"LABELS{k // 255 + 1}", 1, -1, dims, raw))
        entries += [
            ("ANALOG", -2, b"\x00"),
            param("USED", 2, 2, (), words(0)),
            param("RATE", 2, 4, (), codec.encode_reals([take.fps])),
        ]
        if last > 65535:
            entries += [
                ("TRIAL", -3, b"\x00"),
                param("ACTUAL_START_FIELD", 3, 2, (2,), words(first & 0xFFFF, first >> 16)),
                param("ACTUAL_END_FIELD", 3, 2, (2,), words(last & 0xFFFF, last >> 16)),
            ]
        body = b"".join(
            _c3d_entry(n, g, b, i == len(entries) - 1, be) for i, (n, g, b) in enumerate(entries)
        )
        n_blocks = (4 + len(body) + 511) // 512
        code = {v: k for k, v in C3D_PROCESSORS.items()}[processor]
        return (bytes([1, 0x50, n_blocks, code]) + body).ljust(n_blocks * 512, b"\x00")

    section = build(0)
    data_start = 2 + len(section) // 512
    section = build(data_start)
    header = bytearray(512)
    header[0:2] = bytes([2, 0x50])
    header[2:12] = words(m, 0, first, min(last, 65535), 0)
    header[12:16] = codec.encode_reals([scale])
    header[16:20] = words(data_start, 1)  # analog samples per frame: ANALOG:RATE / POINT:RATE
    header[20:24] = codec.encode_reals([take.fps])
    occluded = ~np.isfinite(take.xyz).all(axis=2)
    xyz = np.where(occluded[..., None], 0.0, take.xyz)
    if scale > 0:
        q = np.round(xyz / scale)
        if np.abs(q).max(initial=0) > 32767:
            raise MarkerFileError(
                f"coordinates overflow int16 at scale {scale}; use a larger scale"
            )
        pts = np.concatenate([q, np.where(occluded, -1, 0)[..., None]], axis=2)
        frames = codec.encode_words(pts.astype(np.int16))
    else:
        pts = np.concatenate([xyz, np.where(occluded, -1.0, 0.0)[..., None]], axis=2)
        frames = codec.encode_reals(pts)
    return bytes(header) + section + frames.ljust(-(-len(frames) // 512) * 512, b"\x00")


#: Suffixes of take files, each read by ``read_take``.
TAKE_SUFFIXES: tuple[str, ...] = (".c3d", ".trc", ".csv")


def read_take(data: bytes, suffix: str, *, where: str = "") -> MarkerTake:
    """A take file's bytes -> its take, by its ``suffix`` (``.c3d``, ``.trc`` or ``.csv``, any case):
    the one reading path of server and clients. TRC and CSV text is UTF-8 (bad bytes are replaced,
    then refused by the parser if they matter).

    Raises:
        MarkerFileError: an unknown suffix, or a malformed file (``where`` names the place).
    """
    s = suffix.lower()
    if s == ".c3d":
        return read_c3d(data, where=where)
    if s in (".trc", ".csv"):
        text = data.decode("utf-8", errors="replace")
        return read_trc(text, where=where) if s == ".trc" else read_csv(text, where=where)
    raise MarkerFileError(
        f"unsupported take type {s!r}; use one of {', '.join(TAKE_SUFFIXES)}", where=where
    )
