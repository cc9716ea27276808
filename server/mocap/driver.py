"""Batch mocap driver: a take file (C3D, TRC, CSV) + a marker layout -> an ``Animation`` for a face.

Pipeline (Sánchez Lorenzo 2006 ch. 4): spike rejection, DCT gap filling, Kalman/RTS filtering
(``clean``), head pose from the stable markers and its removal (``stabilise``), RBF retargeting of
the stabilised markers onto the face (``retarget``). With the RTS smoother (batch) the head poses
are then refined with every marker (``stabilise.refine_poses``) and the displacements projected onto
the take's motion subspace (``clean.lowrank_denoise``). The ``Animation`` has ``control_vertices`` =
the marker vertices on the face, ``FaceState.controls`` = their displacements (face units),
``FaceState.head`` = the head pose (face axes and units), and ``FaceState.faps`` = FAPs projected
from markers on feature points (FAP 3 from the jaw marker, 48-50 from the head pose).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...protocol.markers_file import MarkerTake
from ..errors import InputError
from ..faces.face import Face
from ..state import Animation, FaceState
from .clean import CleanParams, clean, lowrank_denoise, motion_rank
from .io import read_take
from .layout import Layout, load_layout
from .neutral import find_neutral, rest_frame, tied_positions
from .prior import DEFAULT as PRIOR_DEFAULT
from .prior import ramp
from .rig import MarkerRig, match_names
from .stabilise import (
    check_stable,
    head_track,
    hold_pose,
    kabsch,
    pose_uncertainty,
    refine_poses,
    remove_head,
    smooth_poses,
)

log = logging.getLogger(__name__)

__all__ = ["Processed", "find_layout", "load", "process"]

#: How far (mm, 90th percentile) the filtered, stabilised markers may stray from the running mean of
#: the neutral frames before the neutral stops averaging (``still_neutral``): a hold (HOLD_MM), or
#: without one, the first frames (STILL_MM). At 1 mm a take moving from frame 0 averaged the first
#: half second of expression into its neutral, a constant 0.48 mm on every marker's displacement
#: (0.52 mm mean; 0.23 mm at 0.2); a take with a hold averages its hold (at 0.2 mm the generated
#: take's stabilised displacements' p95 rose from 0.371 to 0.392 mm, at 0.4 it stays).
HOLD_MM, STILL_MM = 0.4, 0.2
#: Batch head poses refined with every marker (``stabilise.refine_poses``), each pass followed by
#: the stabilised markers smoothed again: each pass starts from the last one's poses, neutral and
#: principal motions (an alternating fit, as generalised Procrustes re-estimates its mean shape), so
#: the expression part a pass took for head motion shrinks over the passes. One pass left a rigid
#: error tied to the take's neutral frame, carried into every output frame (0.08 deg on the issue16
#: take, 0.2 deg on sparse30's three headband markers). 2-s generated takes, batch ratio to not
#: deforming and head pose (degrees), 1 / 3 / 6 passes: tuning (issue16 and technician, mirror
#: folds) 0.497 / 0.479 / 0.467x, 0.071 / 0.064 / 0.057 deg; held out, the other five variants'
#: mirror folds 0.788 / 0.759 / 0.733x, 0.106 / 0.094 / 0.083 deg; every variant's strict folds
#: 0.679 / 0.640 / 0.634x, 0.109 / 0.091 / 0.082 deg. The batch pipeline's CPU time: 1.3 s one pass,
#: 1.75 s three, 2.3 s six (a 4-s take, prior off: each pass adds about 0.2 s a 4-s take).
REFINE_PASSES = 6
#: Batch head poses then refit rigidly to every control marker where the face prior explains the
#: frame (``fit_pose``): passes (0: off) and the relative-residual gate (the prior's fit trusted
#: fully below gate[0], not at all above gate[1]; ``rig.BATCH_TOWARD_FIT``'s, not tuned again).
#: 2-s generated takes, fold priors, bench/mocap_diagnose.py --fit-pose 0 / 2 in the same minutes
#: (load 13-20), the five variants never tuned on (sparse30, dense100, neck-pivot, neutral-last,
#: fast-large), folds 0/1: mirror batch ratio 0.702 -> 0.684x, head pose 0.082 -> 0.072 deg
#: (sparse30 fold 0 0.186 -> 0.150, dense100 0.085/0.072 -> 0.072/0.063; sparse30 fold 1 0.065
#: -> 0.076 deg with batch 0.885 -> 0.887x, the one row worse by more than 0.01x: neutral-last
#: fold 1 0.748 -> 0.768x); strict (the gate stays mostly shut) 0.660 -> 0.658x, 0.0874 -> 0.0869
#: deg, no row worse in batch. 4 passes: mirror 0.681x, 0.0685 deg (sparse30 fold 0 0.130),
#: strict 0.657x, 0.0867 deg; each pass ~0.13 s CPU on a 2-s take (1.9 s without, 2.3 s with 4;
#: load 0.6). The rows tuned on earlier (issue16, technician), 4 passes: mirror 0.455 -> 0.430x,
#: 0.058 -> 0.046 deg; strict 0.579 -> 0.585x: technician fold 0 0.688 -> 0.712x, 0.057 -> 0.077
#: deg (a fold the shapes half explain: the gate opens on frames it should not), the others equal
#: or better. The corrections RTS-smoothed over frames (as ``refine_poses``'s): the same numbers
#: to 0.001 on the six rows measured, left out.
FIT_POSE_PASSES = 4
FIT_POSE_GATE = (0.3, 0.6)
# Tried and left out: batch head poses refined again with every marker, the face's motion
# explained by the face prior's shapes (``stabilise.ShapePose`` over the take, then RTS-smoothed as
# ``refine_poses`` smooths its corrections; ridge 0.003), after ``refine_poses``. It helped where
# the prior spans the take and hurt where it does not. 2-s takes, batch ratio to not deforming,
# without fast-large fold 1: mirror folds (the held-out shape's other side in the prior) 0.533 ->
# 0.524x on issue16 + technician (the ridge chosen there), 0.718 -> 0.692x on the other variants,
# head pose 0.106 -> 0.073 deg; strict folds (whole families held out) 0.605 -> 0.632x and 0.701
# -> 0.716x, head pose 0.109 -> 0.111 deg. (Live uses ``ShapePose`` per frame: ``live.SHAPE_POSE``.)


@dataclass
class Processed:
    """Everything the batch pipeline computed (for benchmarks and tools).

    ``raw``/``cleaned``/``local``: ``(T, L, 3)`` mm in layout marker order (capture frame; local =
    head removed, in the neutral frame's head pose); ``r (T,3,3)``, ``t (T,3)`` head poses (mm);
    ``states`` the face states; ``info`` counts from cleaning.
    """

    take: MarkerTake
    layout: Layout
    raw: np.ndarray
    cleaned: np.ndarray
    local: np.ndarray
    r: np.ndarray
    t: np.ndarray
    neutral_frame: int
    rig: MarkerRig
    states: list[FaceState]
    info: dict


def find_layout(path: Path) -> Path:
    """The layout beside a take: ``<stem>.layout.json``, else ``layout.json`` in its folder."""
    for cand in (path.with_name(path.stem + ".layout.json"), path.with_name("layout.json")):
        if cand.is_file():
            return cand
    raise InputError(
        "a mocap take needs a marker layout: pass --layout layout.json (or put "
        f"{path.stem}.layout.json beside the take)",
        where=str(path),
    )


def process(
    take: MarkerTake,
    face: Face,
    layout,
    *,
    neutral_frame: int | None = None,
    clean_params: CleanParams | None = None,
    kernel: str = "imq",
    mu: float = 2.0,
    stabilise_method: str = "auto",
    neutral_window: float = 0.5,
    where: str = "take",
    prior=None,
) -> Processed:
    """Run the batch pipeline on a take already read (see module docstring).

    The actor's neutral averages up to ``neutral_window`` seconds from the neutral frame while the
    face holds still (``neutral_pose``): 0.5 s brought the neutral's error from 0.17 to 0.11 mm on
    generated takes (0.5 mm noise), the stabilised displacements' from 0.35 to 0.28 mm (technician
    layout, seed 1).
    """
    layout = load_layout(layout)
    if take.units is None:
        take.units = layout.units
    if take.units is None:
        raise InputError(
            "units of the take are unknown; declare them in the file or the layout", where=where
        )
    idx = match_names(take.names, layout, where)
    raw = take.in_mm()[:, idx]
    n = len(raw)
    if n < 2:
        raise InputError(f"the take has {n} frame(s); at least 2 are needed", where=where)
    seen = np.isfinite(raw).all(axis=2)
    never = [layout.names[i] for i in np.flatnonzero(~seen.any(axis=0))]
    if never:
        raise InputError(
            f"marker(s) never visible in the take: {', '.join(never[:10])}; remove them from the "
            "layout",
            where=where,
        )
    empty = np.flatnonzero(~seen.any(axis=1))
    if len(empty):
        log.warning(
            "%s: %d frame(s) with no visible marker (first: %d); filled from their neighbours",
            where,
            len(empty),
            int(empty[0]),
        )
    params = clean_params or CleanParams()
    nf = neutral_frame if neutral_frame is not None else layout.neutral_frame
    rest = None  # the frame of the head's rest: the neutral frame's unless auto says otherwise
    if nf in (None, "auto"):
        nf = find_neutral(raw, layout, face, take.fps, where)
        default = layout.neutral_frame if isinstance(layout.neutral_frame, int) else 0
        rest = rest_frame(raw, tied_positions(layout, face), nf, default)
        if rest != nf:
            log.info(
                "%s: the head's rest is frame %d's pose (frame %d's head, the neutral, is turned "
                "from the capture axes)",
                where,
                rest,
                nf,
            )
    if not 0 <= nf < n:
        raise InputError(
            f"neutral_frame {nf} is outside the take's {n} frames",
            where=f"{layout.where}: neutral_frame",
        )
    stable = layout_index(layout, layout.stable)
    observed = np.isfinite(raw).all(axis=2)
    if params.filter in ("rts", "kalman"):
        # Despike and fill, solve and smooth the head pose, then filter the stabilised markers (their
        # motion is the face's alone, far gentler than with the head's on top). ``rts`` smooths both
        # ways (batch); ``kalman`` filters causally, exactly as the live driver does.
        filled, info = clean(raw, take.fps, replace(params, filter="none"))
        observed &= ~info.pop("rejected", np.zeros_like(observed))
        window = round(neutral_window * take.fps)
        anchor = neutral_pose(
            filled, nf, window, tolerance_mm=2.5
        )  # raw noise: ~1 mm between frames
        stable = _rigid_stable(filled, stable, layout, info, where)
        r, t, solved = head_track(filled, stable, anchor, stabilise_method, observed=observed)
        if solved.sum() > 3:
            r, t = smooth_poses(
                r, t, filled[nf, stable].mean(axis=0), take.fps, causal=params.filter == "kalman"
            )
        unsmoothed = remove_head(filled, r, t)
        local, info2 = clean(unsmoothed, take.fps, replace(params, despike=False))
        info.update({k: v for k, v in info2.items() if k in ("q", "r", "filter")})
        if params.filter == "rts" and params.lowrank != "off" and solved.sum() > 12:
            # the poses again with every marker (stabilise.refine_poses), then the markers again
            # (REFINE_PASSES times; the later passes keep the first's noise estimates)
            first = replace(params, despike=False)
            later = replace(first, q=info["q"], r=info["r"])
            for i in range(REFINE_PASSES):
                neutral = still_neutral(local, nf, window)
                r, t, _ = refine_poses(filled, r, t, neutral, stable, local - neutral, take.fps)
                unsmoothed = remove_head(filled, r, t)
                local = clean(unsmoothed, take.fps, first if i == 0 else later)[0]
        cleaned = np.einsum("tij,tmj->tmi", r, local) + t[:, None, :]
        if (
            params.filter == "kalman"
        ):  # the causal filters start cold: take the neutral from the raw hold
            neutral = anchor
    else:
        cleaned, info = clean(raw, take.fps, params)
        observed &= ~info.pop("rejected", np.zeros_like(observed))
        stable = _rigid_stable(cleaned, stable, layout, info, where)
        r, t, solved = head_track(cleaned, stable, cleaned[nf], stabilise_method, observed=observed)
        local = remove_head(cleaned, r, t)
    if not solved.any():
        raise InputError(
            f"the stable markers ({', '.join(layout.stable)}) never show 3 at once; head motion "
            "cannot be removed",
            where=where,
        )
    info["head_solved_frames"] = int(solved.sum())
    # The head's rest is the neutral frame's pose exactly (the face frame): poses were solved against
    # a reference averaged over the first frames (moving, in a take without a neutral hold) and then
    # smoothed, so re-anchor them on the final pose of frame ``nf``. Left as they were, every output
    # frame carried the reference's offset (0.77 degrees on a take moving from frame 0, 1.1 mm of
    # skin error on frame 0, where the truth is the rest face).
    w = round(
        neutral_window * take.fps
    )  # a neutral hold's frames share their pose (stabilise.hold_pose)
    if rest is None or rest == nf:
        rest = nf
        r[nf], t[nf] = hold_pose(
            r,
            t,
            neutral_frames(local, nf, w, HOLD_MM),
            nf,
            np.nanmean(local[nf, stable], 0),
            w // 4,
        )
    r0, t0 = r[rest].copy(), t[rest].copy()
    r, t = reanchor(r, t, rest)
    local = local @ r0.T + t0
    if params.filter in ("rts", "kalman"):
        unsmoothed = unsmoothed @ r0.T + t0
    if params.filter == "kalman":
        neutral = neutral @ r0.T + t0
    if params.filter != "kalman":
        neutral = still_neutral(local, nf, round(neutral_window * take.fps))
    xs = np.where(observed[..., None], raw, np.nan)[:, stable]
    ref = np.nanmean(remove_head(xs, r, t), axis=0)
    face_markers = np.setdiff1d(np.arange(len(layout.names)), stable)
    # one frame's pose from the stable markers alone; smoothing over frames and the face markers'
    # refinement (batch) take the final poses well below it
    info["pose_frame_sd_deg"], info["pose_frame_sd_mm"] = pose_uncertainty(
        ref, xs, r, t, neutral[face_markers] if len(face_markers) else ref
    )
    log.info(
        "%s: one frame's head pose from the stable markers (%s) is uncertain by %.3f deg, %.3f mm "
        "at the face markers (before smoothing)",
        where,
        ", ".join(layout.names[i] for i in stable),
        info["pose_frame_sd_deg"],
        info["pose_frame_sd_mm"],
    )
    if params.filter == "rts" and params.lowrank != "off":
        local, info["lowrank"] = denoise_displacements(
            local, neutral, stable, params.lowrank, unsmoothed=unsmoothed
        )
    rig = MarkerRig(face, layout, neutral, kernel=kernel, mu=mu, prior=prior)
    states = rig.solve_batch(local, r, t, take.fps, 0.0)
    if params.filter == "rts" and rig.prior is not None:
        for _ in range(FIT_POSE_PASSES):
            r, t, local = fit_pose(rig, local, r, t, FIT_POSE_GATE)
            states = rig.solve_batch(local, r, t, take.fps, 0.0)
    return Processed(take, layout, raw, cleaned, local, r, t, nf, rig, states, info)


def fit_pose(
    rig: MarkerRig,
    local: np.ndarray,
    r: np.ndarray,
    t: np.ndarray,
    gate: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R, t, local)``: batch head poses refit rigidly to every control marker on frames the face
    prior explains (after ``rig.solve_batch``, whose prior fit it reads).

    The stabilised markers ``local (T, L, 3)`` mm carried back to the capture frame by the poses
    ``r (T,3,3)``, ``t (T,3)`` are fitted (Kabsch) by the model's markers: the stable markers at the
    neutral, the control markers at the stabilised markers less what the prior leaves unexplained of
    them (``d - B_m w``, face units, carried back into mm by the retarget's similarity), so the
    rigid part of that residual becomes head motion. Each frame's correction is scaled by
    ``ramp(relative residual, gate)`` (none where the shapes do not explain the frame); the
    markers are re-stabilised with the new poses."""
    from scipy.spatial.transform import Rotation

    prior = rig.prior
    assert prior is not None and prior.fits is not None and prior.residuals is not None
    g = ramp(prior.residuals, gate)
    if not (g > 0).any():
        return r, t, local
    d = rig.rbf.displacements(local[:, rig.control]) * rig.gains  # (T, K, 3) face units
    unexplained = ((d - prior.fits) / rig.gains) @ rig.q / rig.s  # mm, capture axes
    model = local.copy()
    model[:, rig.control] -= unexplained
    use = np.r_[rig.stable, rig.control]
    model[:, rig.stable] = rig.neutral[rig.stable]
    frame = np.einsum("tij,tmj->tmi", r, local) + t[:, None, :]
    rr, tt = r.copy(), t.copy()
    for i in np.flatnonzero(g > 0):
        ok = use[np.isfinite(frame[i, use]).all(axis=1) & np.isfinite(model[i, use]).all(axis=1)]
        if len(ok) < 4:
            continue
        rk, tk = kabsch(model[i, ok], frame[i, ok])
        # the correction in the stabilised frame: frame = R S x + (R c + t) about the origin
        s_full = r[i].T @ rk
        rotvec = Rotation.from_matrix(s_full).as_rotvec() * g[i]
        s = Rotation.from_rotvec(rotvec).as_matrix()
        shift = g[i] * (r[i].T @ (tk - t[i]))
        rr[i], tt[i] = r[i] @ s, r[i] @ shift + t[i]
    return rr, tt, remove_head(frame, rr, tt)


def _rigid_stable(
    xyz: np.ndarray, stable: np.ndarray, layout: Layout, info: dict, where: str
) -> np.ndarray:
    """``stabilise.check_stable`` with its findings logged and kept in ``info``."""
    keep, dropped, added = check_stable(xyz, stable, layout.names)
    if dropped:
        log.warning(
            "%s: stable marker(s) %s move against the others (not rigid with the head): left "
            'out of the head pose; fix the layout\'s "stable" list',
            where,
            ", ".join(dropped),
        )
    if added:
        log.warning(
            "%s: fewer than 3 rigid stable markers; the head pose also uses %s (the markers "
            "most rigid with them)",
            where,
            ", ".join(added),
        )
    info["stable_dropped"], info["stable_added"] = dropped, added
    return keep


def reanchor(r: np.ndarray, t: np.ndarray, nf: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(T, 3, 3)``, ``(T, 3)`` (``frame = R x + t``) made relative to frame ``nf``'s: the
    stabilised markers ``R'^T (frame - t')`` are then in frame ``nf``'s pose, and ``R'[nf] = I``."""
    rr = np.einsum("tij,kj->tik", r, r[nf])
    return rr, t - np.einsum("tij,j->ti", rr, t[nf])


def still_neutral(local: np.ndarray, nf: int, window: int) -> np.ndarray:
    """``neutral_pose`` over a hold when the take has one (a quarter of ``window`` or more frames
    within ``HOLD_MM``), else over the first frames within ``STILL_MM`` (the face moves from ``nf``)."""
    hold = neutral_frames(local, nf, window, HOLD_MM)
    if len(hold) < max(2, window // 4):
        hold = neutral_frames(local, nf, window, STILL_MM)
    return np.nanmean(local[hold], axis=0)


def neutral_pose(local: np.ndarray, nf: int, window: int, tolerance_mm: float = 1.0) -> np.ndarray:
    """The actor's neutral ``(L, 3)``: the mean of ``neutral_frames``."""
    return np.nanmean(local[neutral_frames(local, nf, window, tolerance_mm)], axis=0)


def neutral_frames(local: np.ndarray, nf: int, window: int, tolerance_mm: float = 1.0) -> list[int]:
    """The frames of the actor's neutral (``neutral_pose``): frame ``nf`` of the markers, with the following
    frames (up to ``window``) until one in which a tenth of the markers lie farther than
    ``tolerance_mm`` from the mean of the frames taken so far (an actor holds the neutral for a
    moment; averaging removes what noise the filter left). The 90th percentile, not the median,
    stops as soon as the jaw or the lips start to move; the running mean, not frame ``nf`` alone,
    keeps one noisy frame from cutting the average short (on a take with a poorly conditioned head
    pose the displacements' error fell from 0.66 to 0.35 mm)."""
    first = np.asarray(local[nf], dtype=np.float64)
    total = np.where(np.isfinite(first), first, 0.0)
    count = np.isfinite(first).astype(np.float64)
    frames = [nf]
    for f in range(nf + 1, min(len(local), nf + max(window, 1))):
        mean = np.where(count > 0, total / np.maximum(count, 1.0), np.nan)
        dist = np.linalg.norm(local[f] - mean, axis=1)
        if np.isfinite(dist).any() and np.nanpercentile(dist, 90) > tolerance_mm:
            break
        frames.append(f)
        seen = np.isfinite(local[f])
        total += np.where(seen, local[f], 0.0)
        count += seen
    return frames


def denoise_displacements(
    local: np.ndarray,
    neutral: np.ndarray,
    stable: np.ndarray,
    rank: str | int = "auto",
    unsmoothed: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """``(local, rank)``: the stabilised markers ``(T, L, 3)`` mm with their displacements from
    ``neutral`` projected onto their leading principal directions (``clean.lowrank_denoise``;
    ``rank`` a count, or ``auto``: ``clean.motion_rank`` of the ``unsmoothed`` stabilised markers,
    whose noise is white as that threshold assumes). The stable markers are left alone: they do not
    move with the face.

    On generated takes (0.5 mm noise, technician layout) the driver's displacement error, seeds
    1/2/3: 0.295/0.299/0.248 mm with neither this nor ``stabilise.refine_poses``, 0.182/0.197/0.188
    with both (``auto`` kept 16-19 of 165 directions).
    """
    face = np.setdiff1d(np.arange(local.shape[1]), stable)
    if rank == "auto":
        rank = motion_rank((local if unsmoothed is None else unsmoothed)[:, face] - neutral[face])
    out = local.copy()
    out[:, face] = neutral[face] + lowrank_denoise(local[:, face] - neutral[face], int(rank))
    return out, int(rank)


def _lowrank(value: str | int) -> str | int:
    """``auto``, ``off`` or a positive count (from a flag's text); InputError otherwise."""
    text = str(value).strip().lower()
    if text in ("auto", "off"):
        return text
    if text.isdigit() and int(text) > 0:
        return int(text)
    raise InputError(
        f"lowrank must be auto, off or a positive count, not {value!r}", where="lowrank"
    )


def layout_index(layout: Layout, names: list[str]) -> np.ndarray:
    pos = {n: i for i, n in enumerate(layout.names)}
    return np.array([pos[n] for n in names], dtype=np.int64)


def load(
    path: Path,
    face: Face,
    layout=None,
    *,
    units: str | None = None,
    neutral_frame: int | None = None,
    filter: str = "rts",
    lowrank: str | int = "auto",
    stable: list[str] | None = None,
    kernel: str = "imq",
    mu: float = 2.0,
    prior: str | Path | None = PRIOR_DEFAULT,
    **options,
) -> Animation:
    """Decode a mocap take into an ``Animation`` for ``face``.

    Args:
        path: ``.c3d``, ``.trc`` or ``.csv``.
        layout: layout path/dict/``Layout``; None looks beside the take (``find_layout``).
        units: units of the take, overriding what the file declares.
        neutral_frame: the actor's neutral frame, or "auto" (default: the layout's, else auto).
        filter: ``rts`` (zero-lag smoother), ``kalman`` (causal, as live) or ``none``.
        lowrank: ``auto``, ``off`` or a count of principal motions kept (``CleanParams.lowrank``).
        stable: stable marker names overriding the layout's (each checked for rigidity).
        kernel, mu: retarget RBF.
        prior: the face prior (``mocap.prior``): ``auto`` (default: the face's ``expressions/``
            folder when it has one), ``off``, a folder of expression meshes or an ``.npz`` basis.
    """
    path = Path(path)
    for k, v in options.items():
        if v is not None and k not in ("progress", "engine", "backend", "device"):
            log.warning("mocap driver: ignoring option %s=%r", k, v)
    lay = load_layout(layout if layout is not None else find_layout(path))
    if stable is not None:
        unknown = [n for n in stable if n not in lay.markers]
        if unknown or len(stable) < 3:
            raise InputError(
                f"--stable needs at least 3 of the layout's markers; unknown: "
                f"{', '.join(unknown) or 'none'}",
                where="stable",
            )
        lay = replace(lay, stable=list(stable))
    lowrank = _lowrank(lowrank)
    take = read_take(path, units=units, default_units=lay.units)
    proc = process(
        take,
        face,
        lay,
        neutral_frame=neutral_frame,
        clean_params=CleanParams(filter=filter, lowrank=lowrank),
        kernel=kernel,
        mu=mu,
        where=str(path),
        prior=prior,
    )
    log.info(
        "%s: %d frames at %g fps, %d markers (%d controls), %d occluded samples, %d spikes",
        path.name,
        len(proc.states),
        take.fps,
        len(lay.names),
        len(proc.rig.control),
        proc.info["occluded"],
        proc.info.get("spikes", 0),
    )
    return Animation(
        fps=take.fps,
        states=proc.states,
        control_vertices=proc.rig.control_vertices,
        source=path.name,
    )
