"""Reading and writing marker takes: C3D, TRC and CSV (pure parsers in ``protocol.markers_file``).

Units: declared by the file (C3D ``POINT:UNITS``, TRC ``Units``, CSV ``# units=``), overridden by the
caller, or detected from the size of the marker cloud (a face spans roughly 100-300 mm).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...protocol import markers_file
from ...protocol.markers_file import (
    TAKE_SUFFIXES,
    MarkerFileError,
    MarkerTake,
    check_take,
    normalise_units,
    write_c3d,
    write_csv,
    write_trc,
)
from ...protocol.units import UNIT_MM
from ..errors import InputError
from ..output.atomic import write_bytes_atomic

log = logging.getLogger(__name__)

__all__ = ["SUFFIXES", "MarkerTake", "detect_units", "read_take", "write_take"]

SUFFIXES = TAKE_SUFFIXES

#: Plausible extent of a face's marker cloud in millimetres (for unit detection and checks).
FACE_SPAN_MM = (40.0, 600.0)
#: Units a take without declared units is guessed in, first match first (``dm`` is left out: a
#: cloud that fits in dm fits in m or cm too, and no capture system writes dm).
GUESSED_UNITS = ("mm", "cm", "m", "in")


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
        take = markers_file.read_take(path.read_bytes(), suffix, where=where)
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
    for unit in GUESSED_UNITS:
        lo, hi = FACE_SPAN_MM
        if lo <= span * UNIT_MM[unit] <= hi:
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
                f"(marker cloud spans {span} units); pass units ({', '.join(UNIT_MM)})",
                where=where,
            )
        log.info("%s: units not declared; the marker cloud's size says %s", where, guess)
        return guess
    if span is not None and span > 0:
        mm = span * UNIT_MM[take.units]
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
    if suffix == ".c3d":
        data = write_c3d(take)
    else:
        text = write_trc(take, filename=path.name) if suffix == ".trc" else write_csv(take)
        data = text.encode("utf-8")
    write_bytes_atomic(path, data)
    return path
