"""Audio file → ``Animation``: ``facecast render speech.wav -o out.glb`` goes through here."""

from __future__ import annotations

import logging
from pathlib import Path

from ..state import Animation, FaceState
from .pipeline import LipSync, lipsync_file
from .visemes import Params, viseme_table

log = logging.getLogger(__name__)


def track_states(ls: LipSync, fap1: bool = False) -> list[FaceState]:
    """One ``FaceState`` per output frame of ``ls.track``.

    Default: the coarticulated, intensity-scaled mouth as low-level FAPs (jaw 3, inner lip 4-13,
    lip protrusion 16-17, outer lip 51-60) and ``viseme=None`` — decoders add FAP 1 to the
    low-level FAPs, so sending both would count the mouth twice. ``fap1=True``: FAP 1 only (top
    two visemes and their blend), for viseme-only consumers.
    """
    tr = ls.track
    states = []
    for i in range(len(tr.t)):
        if fap1:
            blend = int(round(63 * float(tr.blend[i])))
            states.append(
                FaceState(t=float(tr.t[i]), viseme=(int(tr.select1[i]), int(tr.select2[i]), blend))
            )
        else:
            states.append(FaceState(t=float(tr.t[i]), faps=tr.faps[i].copy()))
    return states


def load(
    path: str | Path,
    face=None,
    fps: float = 25.0,
    lookahead: float | None = None,
    silence_db: float | None = None,
    max_db: float | None = None,
    fap1: bool = False,
    text: str | None = None,
    **options,
) -> Animation:
    """Decode and lip-sync an audio file.

    Args:
        path: ``.wav``/``.flac``/``.ogg`` (any rate, mono or multichannel, any sample format).
        face: the target face; its own viseme shapes (``face.visemes``) are used if it has
            them, else ``facecast.server.mpeg4.VISEMES``.
        fps: frame rate of the animation.
        lookahead: coarticulation look-ahead in seconds (None = free, the batch default).
        silence_db, max_db: explicit energy calibration (dB full scale); default: from the file.
        fap1: emit FAP 1 (visemes) instead of low-level FAPs (see ``track_states``).
        text: the transcript, aligned to the audio (``align.align_features``); None = none.
        options: other drivers' options are ignored (logged).
    The file is decoded in blocks straight to the analysis rate (``pipeline.lipsync_file``):
    memory follows the audio's duration, not the file's size, rate or channels.

    Raises:
        InputError: unreadable, invalid or too long audio (``io.decode_audio``), or a
            transcript that does not match it.
    """
    if options:
        log.debug("audio driver ignores options %s", sorted(options))
    ls = lipsync_file(
        path,
        fps=float(fps),
        lookahead=lookahead,
        silence_db=silence_db,
        max_db=max_db,
        params=Params(),
        table=viseme_table(face),
        text=text,
    )
    log.info(
        "%s: %.2f s of audio → %d frames at %g fps (silence %.1f dB, max %.1f dB)",
        Path(path).name,
        ls.duration,
        len(ls.track.t),
        fps,
        ls.calibration.silence_db,
        ls.calibration.max_db,
    )
    return Animation(
        fps=float(fps), states=track_states(ls, fap1), control_vertices=None, source=str(path)
    )
