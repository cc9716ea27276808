"""``.fap`` files -> ``Animation`` (one ``FaceState`` per frame at the file's frame rate).

Masked-out FAPs **keep their previous value** (MPEG-4 mask type 1: "FAPs not selected keep their
previous value"); before their first appearance they are 0. In the real Xface files the only mask
changes switch the eyelid FAPs 19/20 on for a blink and off again, and the value is 0 on both
sides of the switch, so "hold" and "zero" give identical animations there; ``masked="zero"``
selects the other reading for files written by tools that drop zero values from the mask.

High-level FAPs: FAP 1 (viseme) and FAP 2 (expression) are held like the others and stored in
``FaceState.viseme`` / ``expression``; in the Greta layout (one value per flag) they carry no
selects and are ignored with a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ...protocol.fap_file import FapFile, FapFormatError, read_fap
from ..errors import InputError
from ..state import Animation, FaceState, zero_faps

log = logging.getLogger(__name__)


def read(path: Path) -> FapFile:
    """Read and parse a ``.fap`` file; ``InputError`` naming the file and line on bad input."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(
            f"not a text .fap file (byte {e.start} is not ASCII/UTF-8)", where=str(path)
        ) from None
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror}", where=str(path)) from None
    try:
        return read_fap(text, where=str(path))
    except FapFormatError as e:
        where = f"{path}:{e.line}" if e.line else str(path)
        raise InputError(e.reason, where=where) from None


def to_animation(f: FapFile, *, masked: str = "hold", source: str = "") -> Animation:
    """``FapFile`` -> ``Animation``; ``masked`` = ``hold`` (default) or ``zero`` (see module doc)."""
    if masked not in ("hold", "zero"):
        raise InputError(f"masked must be 'hold' or 'zero', not {masked!r}", where="masked")
    fps = float(f.fps)
    faps = zero_faps()
    viseme = expression = None
    states: list[FaceState] = []
    warned = False
    for i, fr in enumerate(f.frames):
        if masked == "zero":
            faps = zero_faps()
            viseme = expression = None
        for k, v in fr.faps().items():
            faps[k] = float(v)
        if fr.single_high_level and (fr.viseme is not None or fr.expression is not None):
            if not warned:
                log.warning(
                    "%s: FAP 1/2 carry one value per flag (Greta layout); ignored", source or "fap"
                )
                warned = True
        else:
            if fr.viseme is not None:
                viseme = tuple(int(x) for x in fr.viseme[:3])
            if fr.expression is not None:
                expression = tuple(int(x) for x in fr.expression[:4])
        states.append(FaceState(t=i / fps, faps=faps.copy(), viseme=viseme, expression=expression))
    return Animation(fps=fps, states=states, source=source)


def load(path: Path, face=None, *, masked: str = "hold", **options) -> Animation:
    """Decode the ``.fap`` file at ``path`` (``face`` is not needed: FAPs are face-independent)."""
    if options:
        log.debug("fap driver ignores options %s", sorted(options))
    return to_animation(read(path), masked=masked, source=str(path))
