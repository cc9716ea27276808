"""Reading and writing marker takes: C3D (ezc3d), TRC and CSV (pure parsers in ``protocol.markers_file``).

Units: declared by the file (C3D ``POINT:UNITS``, TRC ``Units``, CSV ``# units=``), overridden by the
caller, or detected from the size of the marker cloud (a face spans roughly 100-300 mm).
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from ...protocol.markers_file import (
    UNITS_MM,
    MarkerFileError,
    MarkerTake,
    check_take,
    normalise_units,
    read_csv,
    read_trc,
    write_csv,
    write_trc,
)
from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["SUFFIXES", "MarkerTake", "detect_units", "read_take", "write_take"]

SUFFIXES = (".c3d", ".trc", ".csv")

#: Plausible extent of a face's marker cloud in millimetres (for unit detection and checks).
FACE_SPAN_MM = (40.0, 600.0)


def read_take(
    path: str | Path, *, units: str | None = None, default_units: str | None = None
) -> MarkerTake:
    """Read a take; ``units`` overrides what the file declares, ``default_units`` (e.g. a layout's)
    applies when the file declares none, else they are detected from the marker cloud's size.
    Returns positions in the take's units.

    Raises InputError naming the file (and line) for malformed files, unknown suffixes, unknown or
    implausible units.
    """
    path = Path(path)
    where = str(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise InputError("no such take file", where=where)
    try:
        if suffix == ".c3d":
            take = _read_c3d(path)
        elif suffix == ".trc":
            take = read_trc(path.read_text(encoding="utf-8", errors="replace"), where=where)
        elif suffix == ".csv":
            take = read_csv(path.read_text(encoding="utf-8", errors="replace"), where=where)
        else:
            raise InputError(
                f"unsupported take type {suffix!r}; use one of {', '.join(SUFFIXES)}", where=where
            )
        if units is not None:
            take.units = normalise_units(units, where="units")
        elif take.units is None and default_units is not None:
            take.units = normalise_units(default_units, where="units")
    except MarkerFileError as e:
        raise InputError(
            str(e.args[0]).split(": ", 1)[-1] if e.where else str(e), where=e.where or where
        ) from None
    if units is None:  # units the caller gives are trusted; the file's are checked
        take.units = _check_units(take, where)
    return take


def detect_units(xyz: np.ndarray) -> str | None:
    """Guess the units of ``(T, M, 3)`` face markers from their extent (None if nothing is visible)."""
    span = _span(xyz)
    if span is None:
        return None
    for unit in ("mm", "cm", "m", "in"):
        lo, hi = FACE_SPAN_MM
        if lo <= span * UNITS_MM[unit] <= hi:
            return unit
    return None


def _span(xyz: np.ndarray) -> float | None:
    ok = np.isfinite(xyz).all(axis=2)
    frames = np.flatnonzero(ok.sum(axis=1) >= 2)
    if not len(frames):
        return None
    f = frames[0]
    pts = xyz[f][ok[f]]
    return float(np.ptp(pts, axis=0).max())


def _check_units(take: MarkerTake, where: str) -> str:
    span = _span(take.xyz)
    if take.units is None:
        guess = detect_units(take.xyz)
        if guess is None:
            raise InputError(
                "the take does not declare its units and they cannot be guessed "
                f"(marker cloud spans {span} units); pass units (mm, cm, m, in)",
                where=where,
            )
        log.info("%s: units not declared; the marker cloud's size says %s", where, guess)
        return guess
    if span is not None and span > 0:
        mm = span * UNITS_MM[take.units]
        lo, hi = FACE_SPAN_MM
        if not (lo / 4 <= mm <= hi * 4):
            guess = detect_units(take.xyz)
            hint = f"; the size suggests {guess}" if guess else ""
            raise InputError(
                f"declared units {take.units!r} make the marker cloud {mm:.3g} mm across, "
                f"not a face{hint}; pass the right units",
                where=where,
            )
    return take.units


def _read_c3d(path: Path) -> MarkerTake:
    import ezc3d

    try:
        c = ezc3d.c3d(str(path))
    except Exception as e:  # noqa: BLE001 - ezc3d raises plain RuntimeError/IOError with its own text
        raise InputError(f"cannot read C3D ({e})", where=str(path)) from None
    params = c["parameters"]
    point = params.get("POINT", {})
    labels = list(point.get("LABELS", {}).get("value", []))
    for extra in ("LABELS2", "LABELS3", "LABELS4"):
        labels += list(point.get(extra, {}).get("value", []))
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, M, T)
    m = pts.shape[1]
    labels = [str(s).strip() for s in labels[:m]]
    if len(labels) < m:
        labels += [f"M{i:03d}" for i in range(len(labels), m)]
    rate = float(
        np.ravel(point.get("RATE", {}).get("value", [c["header"]["points"]["frame_rate"]]))[0]
    )
    units_v = point.get("UNITS", {}).get("value", [])
    units = normalise_units(str(units_v[0]), where=f"{path}: POINT:UNITS") if len(units_v) else None
    xyz = np.moveaxis(pts[:3], (0, 1, 2), (2, 1, 0))  # (T, M, 3)
    res = c["data"].get("meta_points", {}).get("residuals")
    if res is not None and np.size(res):
        bad = np.asarray(res)[0].T < 0  # (T, M)
        xyz = xyz.copy()
        xyz[bad] = np.nan
    xyz = np.where(np.isfinite(xyz).all(axis=2, keepdims=True), xyz, np.nan)
    first = int(c["header"]["points"].get("first_frame", 0))
    return check_take(
        MarkerTake(labels, xyz, rate, units, first / rate if rate > 0 else 0.0), str(path)
    )


def _write_c3d(take: MarkerTake, path: Path) -> None:
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(take.fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.names)
    c.add_parameter("POINT", "UNITS", take.units or "mm")
    t, m = take.xyz.shape[:2]
    pts = np.ones((4, m, t))
    pts[:3] = np.moveaxis(take.xyz, (0, 1, 2), (2, 1, 0))
    occluded = ~np.isfinite(take.xyz).all(axis=2)  # (T, M)
    pts[:3, occluded.T] = np.nan
    c["data"]["points"] = pts
    c.write(str(path))


def write_take(take: MarkerTake, path: str | Path) -> Path:
    """Write ``take`` as C3D, TRC or CSV (by suffix), atomically."""
    path = Path(path)
    take = check_take(take, str(path))
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(
            f"cannot write {suffix!r}; use one of {', '.join(SUFFIXES)}", where=str(path)
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=suffix, prefix=".tmp-", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600; takes are ordinary files
    try:
        if suffix == ".c3d":
            _write_c3d(take, Path(tmp))
        else:
            text = write_trc(take, filename=path.name) if suffix == ".trc" else write_csv(take)
            Path(tmp).write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
