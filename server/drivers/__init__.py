"""The one driver registry: each input kind's file suffixes, batch driver and live driver.

An input kind has one name, ``protocol.messages.InputKind`` (``fap`` | ``audio`` | ``markers``);
``mocap`` is accepted for ``markers`` where a client sends a kind (``INPUT_ALIASES``). A batch
driver module has ``load(path: Path, face: Face, **options) -> Animation``; ``load_animation``
picks it from the file's suffix. A live driver class turns a producer's decoded frames into face
states (``server/live/inputs.py`` loads it, lazily, when a producer of that kind says hello).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...protocol.markers_file import TAKE_SUFFIXES
from ...protocol.messages import INPUT_ALIASES, InputKind
from ..errors import InputError
from ..state import Animation

__all__ = ["DRIVERS", "INPUT_ALIASES", "SUFFIXES", "Driver", "input_kind", "load_animation"]


@dataclass(frozen=True)
class Driver:
    """One input kind: ``suffixes`` of its files, the ``batch`` driver module and the ``live``
    driver's ``(module, class)`` (None: FAP frames become face states without a driver)."""

    kind: InputKind
    suffixes: tuple[str, ...]
    batch: str
    live: tuple[str, str] | None = None


#: Input kind -> its drivers.
DRIVERS: dict[InputKind, Driver] = {
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
    )
}

#: File suffix (lower case, with the dot) -> input kind.
SUFFIXES: dict[str, InputKind] = {s: d.kind for d in DRIVERS.values() for s in d.suffixes}


def input_kind(path: str | Path) -> InputKind:
    """``fap`` | ``audio`` | ``markers`` from the suffix; InputError for anything else."""
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
