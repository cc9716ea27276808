"""Drivers decode an input file into an ``Animation`` (face states at a frame rate).

``load_animation`` picks the driver from the file's suffix. Each driver module has
``load(path: Path, face: Face, **options) -> Animation``.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from ..errors import InputError
from ..state import Animation

DRIVERS: dict[str, str] = {
    ".fap": "facecast.server.drivers.fap",
    ".wav": "facecast.server.audio.driver",
    ".flac": "facecast.server.audio.driver",
    ".ogg": "facecast.server.audio.driver",
    ".c3d": "facecast.server.mocap.driver",
    ".trc": "facecast.server.mocap.driver",
    ".csv": "facecast.server.mocap.driver",
}


def input_kind(path: str | Path) -> str:
    """``fap`` | ``audio`` | ``mocap`` from the suffix; InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in DRIVERS:
        raise InputError(f"unsupported input type {suffix or '(none)'!r}; expected one of "
                         f"{', '.join(sorted(DRIVERS))}", where=str(path))
    return DRIVERS[suffix].split(".")[-2] if suffix != ".fap" else "fap"


def load_animation(path: str | Path, face, **options) -> Animation:
    """Decode ``path`` into an ``Animation`` for ``face`` with the driver its suffix names."""
    path = Path(path)
    input_kind(path)
    module = importlib.import_module(DRIVERS[path.suffix.lower()])
    return module.load(path, face, **options)
