"""Marker take files as text: TRC (OpenSim / Motion Analysis) and CSV. Pure parsing, no I/O.

A take is ``MarkerTake(names, xyz (T, M, 3) float64, fps, units)``; NaN marks an occluded marker.
CSV layout: a header ``time, <name>_x, <name>_y, <name>_z, ...`` then one row per frame (seconds;
empty cells or ``nan`` = occluded). Units of a CSV come from an optional first comment line
``# units=mm`` (else ``None``: the reader of the take decides). ``read_c3d`` parses the 3-D points
of a C3D file from its bytes (Intel byte order, integer or float data), so that clients can read
takes without ezc3d; the server reads C3D with ezc3d (``facecast.server.mocap.io``).
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass

import numpy as np

#: Length units a take may declare, in millimetres.
UNITS_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


class MarkerFileError(ValueError):
    """A malformed take file; ``where`` names the file/line/column at fault."""

    def __init__(self, message: str, *, where: str = "") -> None:
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


@dataclass
class MarkerTake:
    """Marker trajectories.

    Attributes:
        names: marker names, ``M`` of them, unique.
        xyz: ``(T, M, 3) float64`` positions in ``units``; NaN = occluded.
        fps: frames per second.
        units: ``"mm" | "cm" | "m" | "in"`` or None when the file does not say.
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
        if self.units not in UNITS_MM:
            raise MarkerFileError(f"units of the take are unknown ({self.units!r}); declare them")
        return self.xyz * UNITS_MM[self.units]


def normalise_units(text: str | None, where: str = "") -> str | None:
    """``"Millimeters"``/``"mm"`` -> ``"mm"`` etc.; None stays None; unknown -> MarkerFileError."""
    if text is None:
        return None
    t = text.strip().lower().rstrip(".")
    aliases = {
        "mm": "mm",
        "millimeter": "mm",
        "millimeters": "mm",
        "millimetre": "mm",
        "millimetres": "mm",
        "cm": "cm",
        "centimeter": "cm",
        "centimeters": "cm",
        "centimetre": "cm",
        "centimetres": "cm",
        "m": "m",
        "meter": "m",
        "meters": "m",
        "metre": "m",
        "metres": "m",
        "in": "in",
        "inch": "in",
        "inches": "in",
    }
    if t not in aliases:
        raise MarkerFileError(
            f"unknown length unit {text!r}; use one of mm, cm, m, in", where=where
        )
    return aliases[t]


def check_take(take: MarkerTake, where: str = "") -> MarkerTake:
    """Validate shapes, names and rate; return the take (xyz as float64)."""
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
    if np.isinf(xyz).any():
        xyz = np.where(np.isinf(xyz), np.nan, xyz)
    take.xyz = xyz
    return take


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
        try:
            times.append(float(cells[1]))
        except ValueError:
            raise MarkerFileError(f"bad time {cells[1]!r}", where=f"{where}:{ln}") from None
        coords = cells[2 : 2 + 3 * n_markers]
        coords += [""] * (3 * n_markers - len(coords))
        try:
            rows.append(
                np.array([float(c) if c.strip() else np.nan for c in coords], dtype=np.float64)
            )
        except ValueError as e:
            raise MarkerFileError(f"bad coordinate ({e})", where=f"{where}:{ln}") from None
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
        if [c[-2:].lower() for c in trio] != ["_x", "_y", "_z"] or any(
            c[:-2] != base for c in trio
        ):
            raise MarkerFileError(
                f"columns {trio} must be <name>_x, <name>_y, <name>_z", where=f"{where}:{start + 1}"
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
        try:
            times.append(float(cells[0]))
            rows.append([float(c) if c.strip() else np.nan for c in cells[1:]])
        except ValueError as e:
            raise MarkerFileError(f"bad number ({e})", where=f"{where}:{ln}") from None
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
        fps = float(1.0 / np.median(dt))
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


def _c3d_parameters(
    data: bytes, start: int, where: str
) -> dict[str, dict[str, tuple[int, tuple, bytes]]]:
    """Groups -> parameters -> ``(type, dims, raw bytes)`` of a C3D parameter section."""
    groups: dict[int, str] = {}
    params: dict[int, dict[str, tuple[int, tuple, bytes]]] = {}
    pos = start + 4
    end = len(data)
    while pos + 4 <= end:
        name_len = abs(struct.unpack_from("<b", data, pos)[0])
        gid = struct.unpack_from("<b", data, pos + 1)[0]
        if name_len == 0:
            break
        name = data[pos + 2 : pos + 2 + name_len].decode("ascii", "replace").strip().upper()
        off_pos = pos + 2 + name_len
        if off_pos + 2 > end:
            raise MarkerFileError("truncated parameter section", where=where)
        nxt = struct.unpack_from("<h", data, off_pos)[0]
        body = off_pos + 2
        if gid < 0:
            groups[-gid] = name
        else:
            ptype = struct.unpack_from("<b", data, body)[0]
            ndim = struct.unpack_from("<B", data, body + 1)[0]
            dims = tuple(data[body + 2 : body + 2 + ndim])
            size = abs(ptype) * (int(np.prod(dims)) if ndim else 1)
            raw = data[body + 2 + ndim : body + 2 + ndim + size]
            params.setdefault(gid, {})[name] = (ptype, dims, raw)
        if nxt == 0:
            break
        pos = off_pos + nxt
    return {groups.get(g, str(g)): p for g, p in params.items()}


def _c3d_value(param: tuple[int, tuple, bytes]):
    ptype, dims, raw = param
    if ptype == -1:  # characters: first dimension is the string length
        if len(dims) <= 1:
            return raw.decode("latin-1").strip()
        w = dims[0]
        return [raw[i * w : (i + 1) * w].decode("latin-1").strip() for i in range(len(raw) // w)]
    fmt = {1: "b", 2: "h", 4: "f"}[abs(ptype)]
    return np.frombuffer(raw, dtype="<" + fmt).tolist()


def read_c3d(data: bytes, *, where: str = "") -> MarkerTake:
    """Parse the 3-D points of a C3D file (Intel processor type; integer or floating-point data).

    Points whose residual word is negative, or whose coordinates are NaN, are occluded. Labels come
    from ``POINT:LABELS`` (then ``LABELS2``...), units from ``POINT:UNITS`` (None if absent), the rate
    from the header (``POINT:RATE`` if present).
    """
    if len(data) < 512 or data[1] != 0x50:
        raise MarkerFileError("not a C3D file (byte 2 of the header must be 0x50)", where=where)
    n_points, n_analog, first, last = struct.unpack_from("<hhHH", data, 2)
    scale = struct.unpack_from("<f", data, 12)[0]
    data_start = struct.unpack_from("<h", data, 16)[0]
    rate = struct.unpack_from("<f", data, 20)[0]
    pstart = (data[0] - 1) * 512
    if pstart + 4 > len(data):
        raise MarkerFileError("the parameter section is missing", where=where)
    if data[pstart + 3] != 84:
        raise MarkerFileError(
            f"processor type {data[pstart + 3]} is not supported (only Intel, 84); re-save the "
            "take from your capture software or read it with ezc3d",
            where=where,
        )
    params = _c3d_parameters(data, pstart, where)
    point = params.get("POINT", {})
    labels: list[str] = []
    for key in ("LABELS", "LABELS2", "LABELS3", "LABELS4"):
        if key in point:
            v = _c3d_value(point[key])
            labels += v if isinstance(v, list) else [v]
    if "DATA_START" in point:
        data_start = int(_c3d_value(point["DATA_START"])[0]) or data_start
    if "RATE" in point:
        rate = float(_c3d_value(point["RATE"])[0])
    units = None
    if "UNITS" in point:
        u = _c3d_value(point["UNITS"])
        units = (
            normalise_units(u[0] if isinstance(u, list) else u, where=f"{where}: POINT:UNITS")
            if u
            else None
        )
    n_frames = last - first + 1
    if "FRAMES" in point:  # may exceed the header's 16-bit frame numbers
        n_frames = max(n_frames, int(_c3d_value(point["FRAMES"])[0]) & 0xFFFF)
    is_float = scale < 0
    word = 4 if is_float else 2
    per_frame = (4 * n_points + n_analog) * word
    offset = (data_start - 1) * 512
    available = max(0, (len(data) - offset) // per_frame) if per_frame else 0
    if n_frames > available:
        raise MarkerFileError(
            f"the header promises {n_frames} frames, the file holds {available}", where=where
        )
    dtype = "<f4" if is_float else "<i2"
    block = np.frombuffer(data, dtype=dtype, count=n_frames * per_frame // word, offset=offset)
    block = (
        block.reshape(n_frames, -1)[:, : 4 * n_points]
        .reshape(n_frames, n_points, 4)
        .astype(np.float64)
    )
    xyz = block[..., :3] * (1.0 if is_float else scale)
    residual = block[..., 3]
    xyz[(residual < 0) | ~np.isfinite(xyz).all(axis=2)] = np.nan
    names = [labels[i] if i < len(labels) and labels[i] else f"M{i:03d}" for i in range(n_points)]
    return check_take(
        MarkerTake(names, xyz, float(rate), units, (first - 1) / rate if rate > 0 else 0.0), where
    )
