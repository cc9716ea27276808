"""``.bml`` files -> ``Animation``: ``facecast render performance.bml -o out.glb`` goes through here.

A speech's ``audio`` names its recording relative to the BML file's folder (a local render), or,
for a client's upload, one of the files uploaded with it (``media``: name -> the server's copy);
``protocol.bml.audio_name_problem`` has already refused absolute paths and ``..`` (links in the
BML file's own folder are followed: that folder is the user's; an upload's folder has none).
Speeches are lip-synced (with their text as the transcript), the block is scheduled and its
behaviours mixed as layers over the speech.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ...protocol.bml import MAX_BML_BYTES, BmlBlock, BmlError, Speech, parse_bml
from ..audio.driver import track_states
from ..audio.io import max_audio_seconds
from ..audio.visemes import viseme_table
from ..errors import InputError
from ..state import Animation
from .perform import render_performance
from .schedule import Performance, schedule
from .speech import SpokenSpeech, lipsync_speech

log = logging.getLogger(__name__)

__all__ = ["audio_path", "load", "perform", "read_block"]


def read_block(path: Path) -> BmlBlock:
    """Read and parse the BML file at ``path`` (BmlError / InputError naming it)."""
    try:
        size = path.stat().st_size
        if size > MAX_BML_BYTES:
            raise BmlError(
                f"the BML file is {size} bytes, more than {MAX_BML_BYTES}; split the performance",
                where=str(path),
            )
        data = path.read_bytes()
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror}", where=str(path)) from None
    return parse_bml(data, where=str(path))


def audio_path(speech: Speech, base: Path, media: Mapping[str, Path] | None, where: str) -> Path:
    """The recording of ``speech``: ``media[name]`` when given, else ``base / name`` inside
    ``base``; BmlError naming the speech's line when there is none."""
    name = speech.audio or ""
    if media is not None:
        found = media.get(name)
        if found is None:
            raise BmlError(
                f"audio {name!r} is not among the uploaded files "
                f"({', '.join(sorted(media)) or 'none'}); upload it with the BML",
                line=speech.line,
                element="speech",
                where=where,
            )
        return Path(found)
    p = base / name  # a relative name without '..' (parse_bml): inside base, as written
    if not p.is_file():
        raise BmlError(
            f"audio {name!r} is not a file next to the BML file ({base})",
            line=speech.line,
            element="speech",
            where=where,
        )
    return p


def perform(
    block: BmlBlock,
    base: Path,
    fps: float,
    *,
    face: Any = None,
    media: Mapping[str, Path] | None = None,
    where: str = "",
) -> tuple[Performance, dict[str, SpokenSpeech]]:
    """Lip-sync ``block``'s speeches and schedule it: the performance and each speech's lip-sync.

    The recordings together may last at most ``FACECAST_MAX_AUDIO_SECONDS`` (speeches do not
    overlap, so no longer performance needs more): each is refused from its header, before it is
    decoded, once the budget is spent (hundreds of speeches naming one long file cost no more).
    """
    table = viseme_table(face)
    spoken: dict[str, SpokenSpeech] = {}
    limit = left = max_audio_seconds()
    for b in block.behaviours:
        if isinstance(b, Speech):
            audio = audio_path(b, base, media, where)
            if left <= 0:
                raise BmlError(
                    f"the speeches' recordings last more than this server's limit of {limit:g} s "
                    "in all (FACECAST_MAX_AUDIO_SECONDS); split the performance",
                    line=b.line,
                    element="speech",
                    where=where,
                )
            try:
                spoken[b.id] = lipsync_speech(b, audio, fps, table, max_seconds=left)
            except BmlError:
                raise
            except InputError as e:  # name the speech at fault
                raise BmlError(
                    f"audio {b.audio!r}: {e}".replace(str(audio), b.audio or "")
                    + (
                        f" (what is left of {limit:g} s for all the speeches)"
                        if left < limit
                        else ""
                    ),
                    line=b.line,
                    element="speech",
                    where=where,
                ) from None
            left -= spoken[b.id].timing.duration
    perf = schedule(block, {k: s.timing for k, s in spoken.items()}, where=where)
    if perf.duration > limit:
        raise BmlError(
            f"the performance lasts {perf.duration:.1f} s, longer than this server's limit of "
            f"{limit:g} s (FACECAST_MAX_AUDIO_SECONDS); split it",
            where=where,
        )
    return perf, spoken


def load(
    path: str | Path,
    face: Any = None,
    fps: float = 25.0,
    idle: bool = False,
    media: Mapping[str, Path] | None = None,
    layers: Sequence[Any] = (),
    **options: Any,
) -> Animation:
    """Decode the BML file at ``path`` into the performance's animation for ``face``.

    Args:
        fps: frame rate of the animation.
        idle: add the idle layer (blinks, saccades, sway, breathing).
        media: the files uploaded with the BML (name as the BML writes it -> server path); None:
            the recordings are next to the BML file.
        layers: more ``server.layers`` layers mixed with the performance's own (``render``'s
            ``--idle``, ``--layer``, ``--gaze``), in the same mix.
        options: other drivers' options are ignored (logged).
    Raises:
        InputError (BmlError): unreadable, malformed or unsupported BML, a recording that is missing
            or unreadable, a transcript that does not match its recording.
    """
    if options:
        log.debug("bml driver ignores options %s", sorted(options))
    path = Path(path)
    where = str(path)
    block = read_block(path)
    perf, spoken = perform(block, path.parent, float(fps), face=face, media=media, where=where)
    geometry = None
    if face is not None:
        from ..layers import Geometry

        geometry = Geometry.of_face(face)
    animation = render_performance(
        perf,
        {k: track_states(s.lipsync) for k, s in spoken.items()},
        float(fps),
        geometry=geometry,
        idle=bool(idle),
        layers=layers,
        source=where,
    )
    log.info(
        "%s: %d behaviours, %.2f s -> %d frames at %g fps",
        path.name,
        len(block.behaviours),
        perf.duration,
        len(animation.states),
        fps,
    )
    return animation
