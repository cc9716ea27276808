"""The one driver registry: each input kind's file suffixes, batch driver and live driver.

An input kind has one name, ``protocol.messages.InputKind`` (``fap`` | ``audio`` | ``markers``);
``mocap`` is accepted for ``markers`` where a client sends a kind (``INPUT_ALIASES``). ``bml`` (a
scripted performance, ``server/bml``) is a file kind only: no live session takes it. A batch
driver module has ``load(path: Path, face: Face, **options) -> Animation``; ``load_animation``
picks it from the file's suffix. A live driver class turns a producer's decoded frames into face
states (``server/live/inputs.py`` loads it, lazily, when a producer of that kind says hello).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ...protocol.markers_file import TAKE_SUFFIXES
from ...protocol.messages import INPUT_ALIASES, InputKind
from ..errors import InputError
from ..state import Animation

__all__ = [
    "DRIVERS",
    "INPUT_ALIASES",
    "SUFFIXES",
    "Driver",
    "FileKind",
    "input_kind",
    "load_animation",
]

#: What a file may hold: an input kind, or a BML performance (batch and play only).
FileKind = InputKind | Literal["bml"]


@dataclass(frozen=True)
class Driver:
    """One input kind: ``suffixes`` of its files, the ``batch`` driver module and the ``live``
    driver's ``(module, class)`` (None: FAP frames become face states without a driver)."""

    kind: FileKind
    suffixes: tuple[str, ...]
    batch: str
    live: tuple[str, str] | None = None


#: Input kind -> its drivers.
DRIVERS: dict[FileKind, Driver] = {
    d.kind: d
    for d in (
        Driver("fap", (".fap",), "facecast.server.drivers.fap"),
        Driver(
            "audio",
            (".wav", ".flac", ".ogg"),
            "facecast.server.audio.driver",
            ("facecast.server.audio.live", "AudioLiveDriver"),
        ),
        Driver(
            "markers",
            TAKE_SUFFIXES,
            "facecast.server.mocap.driver",
            ("facecast.server.mocap.live", "MarkerLiveDriver"),
        ),
        Driver("bml", (".bml",), "facecast.server.bml.driver"),
    )
}

#: File suffix (lower case, with the dot) -> input kind.
SUFFIXES: dict[str, FileKind] = {s: d.kind for d in DRIVERS.values() for s in d.suffixes}


def input_kind(path: str | Path) -> FileKind:
    """``fap`` | ``audio`` | ``markers`` | ``bml`` from the suffix; InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(
            f"unsupported input type {suffix or '(none)'!r}; expected one of "
            f"{', '.join(sorted(SUFFIXES))}",
            where=str(path),
        )
    return SUFFIXES[suffix]


def load_animation(path: str | Path, face: Any, **options: Any) -> Animation:
    """Decode ``path`` into an ``Animation`` for ``face`` with the driver its suffix names."""
    path = Path(path)
    module = importlib.import_module(DRIVERS[input_kind(path)].batch)
    animation: Animation = module.load(path, face, **options)
    return animation
