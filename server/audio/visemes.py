"""From LPC features to MPEG-4 visemes and low-level lip/jaw FAPs.

Pure stages, shared by the batch driver and the live driver (which runs them on a sliding
window, so both give the same frames when they use the same calibration and look-ahead):

1. ``calibrate`` / ``calibrate_reference`` and ``median_filter_proba``: the energy levels and the
   smoothed frame-network output from which ``pipeline.classes_to_visemes`` gives each 10 ms
   frame a viseme id and an intensity.
2. ``coarticulate``: Cohen–Massaro dominance functions blend the segments (runs of equal visemes):
   segment s with viseme v has dominance ``alpha_v · exp(-theta_v · d_s(t))`` at time t, d_s = the
   distance from t to the segment (0 inside it); the FAPs at t are the dominance-weighted mean of
   the segments' targets ``table[v] · w`` (w = intensity at the segment's frame nearest t),
   and the reported viseme is the one with the largest dominance. Only frames up to ``lookahead``
   seconds after t are seen (free in batch).
3. ``viseme_table``: the viseme → low-level FAP table (FAPU units): ``facecast.server.mpeg4.VISEMES``
   (or the face's own), so mouth shapes have one source of truth.

Viseme ids are MPEG-4 FAP 1 ids (mpeg4-reference §4.1): 0 sil, 1 PP, 2 FF, 3 TH, 4 DD, 5 kk,
6 CH, 7 SS, 8 nn, 9 RR, 10 aa, 11 E, 12 ih, 13 oh, 14 ou.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage

from ..state import N_FAPS

SIL, PP, FF, TH, DD, KK, CH, SS, NN, RR, AA, E, IH, OH, OU = range(15)
#: Network class index (a e i o u) → viseme id.
VOWEL_VISEMES = np.array([AA, E, IH, OH, OU])


def viseme_table(face=None) -> np.ndarray:
    """``(15, 69)`` viseme → low-level FAP targets (FAPU, full strength): the face's own table
    (``face.visemes``) if it has one, else ``facecast.server.mpeg4.VISEMES`` — the single source
    of truth for mouth shapes, shared with the FAP rig."""
    table = getattr(face, "visemes", None)
    if table is None:
        from ..mpeg4.highlevel import VISEMES

        table = VISEMES
    table = np.asarray(table, dtype=np.float64)
    if table.shape != (15, N_FAPS + 1):
        raise ValueError(f"viseme table must be (15, {N_FAPS + 1}), not {table.shape}")
    return table


#: Cohen–Massaro dominance per viseme: (alpha, theta 1/s). Closures and labiodentals dominate
#: strongly but briefly (the lips must meet: a 30 ms /p/ wins at its centre against vowels on
#: both sides, and gives way 20 ms into them), rounded vowels spread a little further, tongue
#: consonants and silence are weak.
DOMINANCE = np.array(
    [
        (0.5, 20.0),  # sil
        (1.5, 50.0),  # PP: the lips must close, briefly
        (1.0, 40.0),  # FF
        (0.5, 30.0),  # TH
        (0.5, 30.0),  # DD
        (0.5, 30.0),  # kk
        (0.8, 40.0),  # CH
        (0.8, 40.0),  # SS
        (0.5, 30.0),  # nn
        (0.6, 25.0),  # RR
        (0.6, 20.0),  # aa
        (0.6, 20.0),  # E
        (0.6, 20.0),  # ih
        (0.7, 20.0),  # oh: lip rounding spreads to neighbours
        (0.7, 20.0),  # ou
    ]
)


@dataclass
class Calibration:
    """Energy levels in dB (10·log10 of mean frame power, full scale = 0 dB).

    ``silence_db``: frames below are quiet (mouth closed or at rest); ``max_db``: the loudest
    normal-speech level (intensity 1).
    """

    silence_db: float
    max_db: float

    def intensity(self, energy_db: np.ndarray) -> np.ndarray:
        """``(T,)`` in [0, 1], linear in dB between the silence threshold and the maximum (EXT)."""
        span = np.maximum(np.asarray(self.max_db) - self.silence_db, 1e-6)
        return np.minimum(np.maximum((np.asarray(energy_db) - self.silence_db) / span, 0.0), 1.0)


#: Quietest level ever used as a silence threshold, dB (digital silence is -120 dB; 16-bit
#: dither about -100 dB, which the noise margin keeps below the threshold anyway). Low enough
#: that a quiet recording (speech peaking 50 dB below full scale) is calibrated like a loud one.
MIN_SILENCE_DB = -100.0
#: The silence threshold sits at most this far below the maximum, dB.
SILENCE_RANGE_DB = 40.0
#: ... and at least this far above the noise floor, dB.
NOISE_MARGIN_DB = 8.0


def calibrate(energy_db: np.ndarray) -> Calibration:
    """File calibration from the frame energies themselves (the source recorded room noise and a
    loud /a/ instead): noise floor = 5th percentile, maximum = 99th percentile of frame energy;
    silence threshold = max(noise + 8 dB, maximum - 40 dB, MIN_SILENCE_DB)."""
    e = np.asarray(energy_db, dtype=np.float64)
    if e.size == 0:
        return Calibration(MIN_SILENCE_DB, MIN_SILENCE_DB + SILENCE_RANGE_DB)
    noise = float(np.percentile(e, 5))
    top = float(np.percentile(e, 99))
    sil = max(noise + NOISE_MARGIN_DB, top - SILENCE_RANGE_DB, MIN_SILENCE_DB)
    return Calibration(silence_db=sil, max_db=max(top, sil + 10.0))


#: A calibration recording must span at least this much between room noise and the loud /a/, dB.
MIN_CALIBRATION_SPAN_DB = 15.0


def calibrate_reference(energy_db: np.ndarray, *, where: str = "calibration") -> Calibration:
    """The source's calibration: from a recording of the room's noise and a loud sustained /a/
    (in one file, in any order). Noise floor = 10th percentile of frame energy, the /a/ = 90th
    percentile; silence threshold as ``calibrate`` (noise + 8 dB, at most 40 dB below the /a/),
    maximum = the /a/. Raises InputError when the recording holds no loud part well above its
    noise (what to record is in the message)."""
    from ..errors import InputError

    e = np.asarray(energy_db, dtype=np.float64)
    if e.size < 20:
        raise InputError(
            "the calibration recording is shorter than 0.2 s; record about 1 s of "
            "room noise and then a loud sustained /a/",
            where=where,
        )
    noise, loud = float(np.percentile(e, 10)), float(np.percentile(e, 90))
    if loud - noise < MIN_CALIBRATION_SPAN_DB:
        raise InputError(
            f"the calibration recording's loud part is only {loud - noise:.1f} dB "
            f"above its quiet part (at least {MIN_CALIBRATION_SPAN_DB:.0f} dB needed): "
            "record about 1 s of room noise and then a loud sustained /a/",
            where=where,
        )
    sil = max(noise + NOISE_MARGIN_DB, loud - SILENCE_RANGE_DB, MIN_SILENCE_DB)
    return Calibration(silence_db=sil, max_db=max(loud, sil + 10.0))


@dataclass
class Params:
    """Smoothing (EXT = facecast's choice where the source gives no value).

    Attributes:
        median: length of the median filter over the frame network's outputs, frames.
        coart_past: how far back dominance functions reach, seconds.
    """

    median: int = 3
    coart_past: float = 0.25
    dominance: np.ndarray = field(default_factory=lambda: DOMINANCE.copy())


def median_filter_proba(proba: np.ndarray, size: int) -> np.ndarray:
    """Per-class running median of ``proba (T, C)`` over ``size`` frames (centred; edges repeat).

    The source median-filters its vowel labels; filtering each class score and taking the argmax
    afterwards does the same job without imposing an order on the classes.
    """
    if size <= 1 or len(proba) == 0:
        return proba
    if size == 3:  # the default: the median of three, exactly, without scipy's per-call cost
        prev = np.concatenate([proba[:1], proba[:-1]])
        nxt = np.concatenate([proba[1:], proba[-1:]])
        med: np.ndarray = np.maximum(
            np.minimum(prev, proba), np.minimum(np.maximum(prev, proba), nxt)
        )
        return med
    return scipy.ndimage.median_filter(proba, size=(size, 1), mode="nearest")


#: Output times ``coarticulate`` works on at once (its arrays are rows × window frames).
COART_ROWS = 4096


@dataclass
class Track:
    """Coarticulated output at times ``t (N,)``: ``faps (N, 69)``, top two visemes ``select1``,
    ``select2`` (N,), ``blend`` (N,) weight of select1 in [0, 1], ``weight`` (N,) intensity of
    select1 in [0, 1] (its most dominant segment's; 0 for silence)."""

    t: np.ndarray
    faps: np.ndarray
    select1: np.ndarray
    select2: np.ndarray
    blend: np.ndarray
    weight: np.ndarray


def coarticulate(
    frame_t: np.ndarray,
    vis: np.ndarray,
    w: np.ndarray,
    t_out: np.ndarray,
    params: Params,
    *,
    hop: float,
    lookahead: float | None = None,
    table: np.ndarray | None = None,
) -> Track:
    """Blend per-frame targets with dominance functions and sample at ``t_out (N,)`` seconds.

    ``frame_t (T,)`` must be evenly spaced by ``hop`` seconds. Frames with
    ``frame_t > t + lookahead`` do not contribute to time t (None = no limit). ``table``: viseme
    → FAP targets (default ``viseme_table()``). Output times are taken ``COART_ROWS`` at a time,
    so the working memory does not grow with the length of the track.
    """
    t_out = np.asarray(t_out, dtype=np.float64)
    if len(t_out) <= COART_ROWS:
        return _coarticulate(
            frame_t, vis, w, t_out, params, hop=hop, lookahead=lookahead, table=table
        )
    parts = [
        _coarticulate(
            frame_t,
            vis,
            w,
            t_out[i : i + COART_ROWS],
            params,
            hop=hop,
            lookahead=lookahead,
            table=table,
        )
        for i in range(0, len(t_out), COART_ROWS)
    ]
    return Track(
        *(
            np.concatenate([getattr(p, k) for p in parts])
            for k in ("t", "faps", "select1", "select2", "blend", "weight")
        )
    )


@functools.lru_cache(maxsize=16)
def _offsets(n_past: int, n_future: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(offs (W,), offs == 0, offs <= 0)`` of the frame window -n_past..n_future (read-only;
    made once: the live path asks for the same window every chunk)."""
    offs = np.arange(-n_past, n_future + 1)
    out = (offs, offs[None, :] == 0, offs[None, :] <= 0)
    for a in out:
        a.flags.writeable = False
    return out


@functools.lru_cache(maxsize=16)
def _rows(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(arange(n), arange(n)[:, None] * 15)``, read-only (the live path's few rows)."""
    rows = np.arange(n)
    out = (rows, rows[:, None] * 15)
    for a in out:
        a.flags.writeable = False
    return out


def _coarticulate(
    frame_t: np.ndarray,
    vis: np.ndarray,
    w: np.ndarray,
    t_out: np.ndarray,
    params: Params,
    *,
    hop: float,
    lookahead: float | None = None,
    table: np.ndarray | None = None,
) -> Track:
    frame_t = np.asarray(frame_t, dtype=np.float64)
    N = len(t_out)
    if len(frame_t) == 0 or N == 0:
        z = np.zeros(N, dtype=np.int64)
        return Track(t_out, np.zeros((N, N_FAPS + 1)), z, z.copy(), np.ones(N), np.zeros(N))
    future = params.coart_past if lookahead is None else min(lookahead, params.coart_past)
    offs, is_base, before = _offsets(
        int(round(params.coart_past / hop)), int(round(future / hop + 1e-9))
    )
    # nearest frame at or before each output time, then a window of frames around it
    # (np.minimum/np.maximum: np.clip's per-call cost on integers weighs on the live path)
    base = np.minimum(
        np.maximum(np.floor((t_out - frame_t[0]) / hop + 1e-9).astype(np.int64), 0),
        len(frame_t) - 1,
    )
    j = base[:, None] + offs[None, :]
    ok = (j >= 0) & (j < len(frame_t))
    jc = np.minimum(np.maximum(j, 0), len(frame_t) - 1)
    dt = frame_t[jc] - t_out[:, None]
    if lookahead is not None:
        ok &= dt <= lookahead + 1e-9
    v = np.where(ok, vis[jc], -1)
    # Cohen–Massaro: one dominance function per segment (run of equal visemes), measured from
    # the segment's frame nearest to t (0 inside it); that frame also gives the intensity.
    changes = v[:, 1:] != v[:, :-1]
    new_next = np.empty(ok.shape, dtype=bool)  # the next frame starts another segment (or none)
    new_next[:, :-1], new_next[:, -1] = changes, True
    new_prev = np.empty(ok.shape, dtype=bool)  # the previous frame ends another segment
    new_prev[:, 1:], new_prev[:, 0] = changes, True
    rep = np.where(before, is_base | new_next, new_prev) & ok
    v = np.where(ok, v, 0)
    at = params.dominance[v]  # (N, W, 2): alpha, theta
    dom = np.where(rep, at[..., 0] * np.exp(-at[..., 1] * np.abs(dt)), 0.0)
    total = dom.sum(axis=1)
    total = np.where(total > 0, total, 1.0)
    table = viseme_table() if table is None else table
    # per output time and viseme: dominance mass, and dominance × intensity (→ FAP targets)
    rows, rows15 = _rows(N)
    flat = (rows15 + v).ravel()
    mass = np.bincount(flat, weights=dom.ravel(), minlength=N * 15).reshape(N, 15)
    coef = np.bincount(flat, weights=(dom * w[jc]).ravel(), minlength=N * 15).reshape(N, 15)
    faps = (coef @ table) / total[:, None]
    # the two largest masses, ties to the lower viseme id (a stable descending sort's first two;
    # mass >= 0, so -1 takes s1 out of the second pick)
    s1 = np.argmax(mass, axis=1)
    m1 = mass[rows, s1]
    rest = mass.copy()
    rest[rows, s1] = -1.0
    s2 = np.argmax(rest, axis=1)
    m2 = mass[rows, s2]
    m12 = m1 + m2
    blend = np.where(m12 > 0, m1 / np.maximum(m12, 1e-12), 1.0)
    # weight: intensity of the most dominant segment of the chosen viseme
    best = np.argmax(np.where(v == s1[:, None], dom, -1.0), axis=1)
    weight = np.where(dom[rows, best] > 0, w[jc[rows, best]], 0.0)
    return Track(t_out, faps, s1.astype(np.int64), s2.astype(np.int64), blend, weight)
