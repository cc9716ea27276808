"""The per-take setup shared by the batch driver and the live driver.

``MarkerRig(face, names, layout, neutral_mm)`` matches the take's markers to the layout, places the
control markers on the face, fits the RBF retarget from the actor's neutral to the face and the
similarity that carries head poses into face axes. ``rig.solve(local_mm, r, t, time)`` turns one
stabilised frame into a ``FaceState``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..faces.face import Face
from ..state import FaceState, zero_faps
from .layout import Layout, load_layout, marker_gains, place_markers
from .prior import ExpressionBasis, ExpressionPrior, load_basis, ramp
from .retarget import RBFMap
from .sampling import farthest_points
from .stabilise import pose_in_frame, to_matrix

log = logging.getLogger(__name__)

__all__ = [
    "FIT_SPACING_FRACTION",
    "MarkerRig",
    "check_vertex_fit",
    "match_names",
    "rig_controls",
    "similarity",
]

#: A layout is refused when its vertex-tied markers, after the best similarity (rotation, scale,
#: shift) onto their face vertices, sit a median distance from the actor's neutral markers above this
#: fraction of the median distance between neighbouring markers on the face. A vertex id says "this
#: marker sits on this vertex of this mesh": for the face the layout was made for, what is left is
#: capture noise (0.1 mm on the generated take, 0.5 mm noise before averaging) and small differences
#: of shape; once it reaches a good part of the marker spacing, markers are no longer arranged on the
#: face as they were captured, and the retarget carries one region's motion onto another (the ICT
#: layout on the built-in head: 53 mm median, a torn chin and neck). A quarter of the spacing is
#: ~3 mm with 60 markers: several times the noise, far below a mismatch. Markers tied to feature
#: points or placed automatically are not judged: they retarget across faces by design.
FIT_SPACING_FRACTION = 0.25
#: The face prior's direct per-vertex channel (``prior.ExpressionPrior.set_channel``) is on.
CHANNEL = True
#: Batch marker displacements move toward the face prior's fit at the markers (``toward_fit``) by
#: this relative-residual gate (None: off), as the live path does (``live.TOWARD_FIT``, whose gate
#: this is, not tuned again): what the RTS smoother and the low-rank step leave of the markers'
#: noise and stabilisation error no longer reaches the skin through the engine where the shapes
#: explain a frame. 2-s generated takes, fold priors, batch ratio to not deforming
#: (bench/mocap_diagnose.py, load ~10): mirror folds 0.657 -> 0.631x (9 of 14 better, by up to
#: 0.07; 5 worse by 0.001-0.013; the non-rigid part, the output with the true head pose, 0.508 ->
#: 0.441x, all 14 better); strict folds, which the shapes do not explain (the gate stays shut),
#: unchanged (within 0.003x). Batch only: the live path moves each frame itself. Other gates on
#: the tuning takes (issue16 and technician, folds 0/1), mirror / strict means: (0.3, 0.6)
#: 0.455 / 0.579x, (0.2, 0.4) 0.460x mirror, (0.5, 0.8) 0.449 / 0.637x (technician strict fold 0
#: 0.69 -> 0.85: a looser gate moves markers to shapes that do not explain them).
BATCH_TOWARD_FIT: tuple[float, float] | None = (0.3, 0.6)


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares ``dst ~= s Q src + c`` (Umeyama): ``(Q (3,3) rotation, s, c (3,))``."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - cs, dst - cd
    u, sig, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    q = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    s = float((sig * np.array([1.0, 1.0, d])).sum() / max((a**2).sum(), 1e-300))
    return q, s, cd - s * q @ cs


def match_names(take_names: list[str], layout: Layout, where: str = "") -> np.ndarray:
    """For each layout marker, its index among the take's markers. Markers of the take that the
    layout does not name are ignored (logged); layout markers missing from the take are an
    InputError naming them."""
    index = {n: i for i, n in enumerate(take_names)}
    missing = [n for n in layout.names if n not in index]
    if missing:
        stable = [n for n in missing if n in layout.stable]
        what = f" (stable: {', '.join(stable)})" if stable else ""
        raise InputError(
            f"the take lacks {len(missing)} marker(s) the layout names: {', '.join(missing[:10])}"
            f"{'...' if len(missing) > 10 else ''}{what}; the take has {', '.join(take_names[:10])}"
            f"{'...' if len(take_names) > 10 else ''}",
            where=where,
        )
    extra = [n for n in take_names if n not in set(layout.names)]
    if extra:
        log.warning(
            "%s: ignoring %d marker(s) the layout does not name: %s",
            where or "take",
            len(extra),
            ", ".join(extra[:10]),
        )
    return np.array([index[n] for n in layout.names], dtype=np.int64)


class MarkerRig:
    """Retargeting set-up for one actor neutral onto one face.

    Args:
        face: the target face.
        layout: the marker layout (path, dict or ``Layout``).
        neutral_mm: ``(L, 3)`` the actor's neutral positions of the layout's markers (layout order),
            millimetres, NaN where unseen (a control marker must be seen).
        kernel, mu: the retarget RBF (``imq`` with mu = 2 as in the thesis, or ``r``).
        anchors: also pin skin far from every marker (back and top of the head, ears, the neck
            below the jaw) with zero displacement, so that the deformation does not spread the
            face's motion over parts no marker sees.

    Attributes:
        control: ``(K,)`` layout indices of the control markers; ``control_vertices`` their face vertices.
        stable: layout indices of the stable markers.
        jaw: position of the jaw marker among the controls (None without one).
    """

    def __init__(
        self,
        face: Face,
        layout,
        neutral_mm: np.ndarray,
        *,
        kernel: str = "imq",
        mu: float = 2.0,
        anchors: bool = True,
        prior: str | Path | ExpressionBasis | None = None,
    ):
        self.face = face
        self.layout = load_layout(layout)
        names = self.layout.names
        self.neutral = np.asarray(neutral_mm, dtype=np.float64)
        pos = {n: i for i, n in enumerate(names)}
        placement = place_markers(
            self.layout, face, {n: self.neutral[i] for i, n in enumerate(names)}
        )
        self.control = np.array([pos[n] for n in placement.names], dtype=np.int64)
        self.control_names = placement.names
        self.placement = placement
        self.anchor_vertices = (
            anchor_vertices(face, placement.vertices) if anchors else np.zeros(0, np.int32)
        )
        self.prior, self.control_vertices = rig_controls(
            face, placement.vertices, self.anchor_vertices, prior
        )
        self.stable = np.array([pos[n] for n in self.layout.stable], dtype=np.int64)
        unseen = [names[i] for i in self.control if not np.isfinite(self.neutral[i]).all()]
        if unseen:
            raise InputError(
                f"marker(s) {', '.join(unseen[:8])} are not visible in the neutral frame (even after "
                'gap filling); choose another neutral_frame or mark them {"control": false}',
                where=self.layout.where,
            )
        src = self.neutral[self.control]
        dst = face.vertices[placement.vertices].astype(np.float64)
        self.rbf = RBFMap(src, dst, kernel=kernel, mu=mu)
        # The frame change actor -> face for head poses (rigid part of the retarget).
        self.q, self.s, self.c = similarity(src, dst)
        # exaggeration per region (the layout's masks): each control's displacement scaled
        self.gains = marker_gains(self.layout, placement.names)[:, None]
        jaw = self.layout.jaw
        self.jaw = placement.names.index(jaw) if jaw in placement.names else None
        try:
            from ..mpeg4.fapu import measure_fapu

            self.fapu: dict[str, float] | None = measure_fapu(face)
        except Exception as e:  # noqa: BLE001 - a face without feature points has no FAPU: no FAP output
            log.info("no FAPU for face %s (%s): FAPs from markers are off", face.name, e)
            self.fapu = None
        from .to_fap import FapProjection

        self.fap_projection = (
            FapProjection(face, self.placement, self.fapu, self.jaw) if self.fapu else None
        )
        self.fit = check_vertex_fit(self.layout, face, placement, src)
        mm_face = face.mm_per_unit
        fit = np.linalg.norm(self.s * src @ self.q.T + self.c - dst, axis=1) * mm_face
        log.info(
            "retarget: %d control markers, actor->face scale %.4g face units/mm (x%.3g after units), "
            "rigid fit residual mean %.2f mm",
            len(src),
            self.s,
            self.s * mm_face,
            fit.mean(),
        )

    def marker_motion(self) -> np.ndarray | None:
        """``(E, L, 3)`` the face prior's shapes at the layout's markers, carried back into the
        capture frame (mm, the retarget's similarity undone; zero at markers that are not
        controls), or None without a prior: how the actor's markers move (``stabilise.ShapePose``)."""
        if self.prior is None:
            return None
        at = self.prior.shapes[:, self.placement.vertices].astype(np.float64) / self.gains[None]
        out = np.zeros((len(self.prior.shapes), self.n_markers, 3))
        out[:, self.control] = at @ self.q / self.s
        return out

    @property
    def n_markers(self) -> int:
        return len(self.layout.names)

    def head_matrix(self, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``(..., 3, 4)`` head transform in face axes and units from a capture-space pose (mm)."""
        rf, tf = pose_in_frame(r, t, self.q, self.s, self.c)
        return to_matrix(rf, tf)

    def solve(self, local_mm: np.ndarray, r: np.ndarray, t: np.ndarray, time: float) -> FaceState:
        """One ``FaceState`` from ``(L, 3)`` stabilised markers (mm, layout order) and the head pose."""
        d = self.rbf.displacements(local_mm[self.control]).astype(np.float32) * self.gains
        head = self.head_matrix(r, t)
        if self.prior is None:
            return self.state(d, head, time)
        virtual, weights = self.prior.solve(d[None], warm=True)
        return self.state(
            d,
            head,
            time,
            None if virtual is None else virtual[0],
            None if weights is None else weights[0],
        )

    def _with_anchors(self, d: np.ndarray, virtual: np.ndarray | None = None) -> np.ndarray:
        parts = [d] if virtual is None else [d, virtual.astype(d.dtype)]
        if len(self.anchor_vertices):
            parts.append(np.zeros((len(self.anchor_vertices), 3), dtype=d.dtype))
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)

    def solve_batch(
        self, local_mm: np.ndarray, r: np.ndarray, t: np.ndarray, fps: float, t0: float = 0.0
    ) -> list[FaceState]:
        """``solve`` for ``(T, L, 3)`` frames at once."""
        d = self.rbf.displacements(local_mm[:, self.control]).astype(np.float32) * self.gains
        return self.states(d, self.head_matrix(r, t), fps, t0)

    def states(
        self, d: np.ndarray, heads: np.ndarray, fps: float, t0: float = 0.0
    ) -> list[FaceState]:
        """``FaceState``s from ``(T, K, 3)`` marker control displacements (face units) and
        ``(T, 3, 4)`` heads, the prior fitted to all frames at once (``solve_batch``'s tail)."""
        virtual, weights = self.prior.solve(d) if self.prior is not None else (None, None)
        if self.prior is not None and BATCH_TOWARD_FIT is not None:
            d = toward_fit(d, self.prior, BATCH_TOWARD_FIT)
        return [
            self.state(
                d[i],
                heads[i],
                t0 + i / fps,
                None if virtual is None else virtual[i],
                None if weights is None else weights[i],
            )
            for i in range(len(d))
        ]

    def state(
        self,
        d: np.ndarray,
        head: np.ndarray,
        time: float,
        virtual: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> FaceState:
        """A ``FaceState`` from ``(K, 3)`` marker control displacements (face units), the prior's
        ``(N, 3)`` virtual controls and ``(E,)`` channel weights (when it has them) and a
        ``(3, 4)`` head."""
        faps = (
            self.fap_projection.faps(d, head[:, :3])
            if self.fap_projection is not None
            else zero_faps()
        )
        return FaceState(
            t=float(time),
            faps=faps,
            controls=self._with_anchors(d, virtual),
            head=head.astype(np.float64),
            shapes=None if weights is None or self.prior is None else self.prior.channel,
            shape_weights=weights,
        )


def toward_fit(d: np.ndarray, prior: ExpressionPrior, gate: tuple[float, float]) -> np.ndarray:
    """``(T, K, 3)`` marker displacements ``d`` moved toward the prior's fit at the markers (its
    last ``fit`` over the same frames): ``d - g (d - B_m w)``, ``g`` 1 below ``gate[0]`` relative
    residual, 0 above ``gate[1]``, linear between (as ``live.TOWARD_FIT`` does per frame)."""
    assert prior.fits is not None and prior.residuals is not None
    g = ramp(prior.residuals, gate)[:, None, None]
    return (d - g * (d - prior.fits)).astype(d.dtype)


def rig_controls(
    face: Face, markers: np.ndarray, anchors: np.ndarray, prior
) -> tuple[ExpressionPrior | None, np.ndarray]:
    """``(the face prior or None, (K,) int32 control vertices)`` of a rig whose markers sit on
    ``markers`` (face vertices) with ``anchors`` pinned: the markers, the prior's virtual controls
    (if any), then the anchors; ``prior`` the prior's source (``MarkerRig``) or a built one."""
    built = _prior(face, prior, markers, anchors)
    virtual = built.vertices if built is not None else np.zeros(0, np.int64)
    return built, np.r_[markers, virtual, anchors].astype(np.int32)


def _prior(face: Face, source, markers: np.ndarray, anchors: np.ndarray) -> ExpressionPrior | None:
    """The rig's ``prior.ExpressionPrior`` (None for ``off``/None or a face without shapes), with
    the fall-back interpolation of the markers alone taken from the fp engine's rows, and its
    direct channel against the fp engine's operator over all the rig's controls (the default
    engine's; another engine spreads the controls a little otherwise)."""
    if isinstance(source, ExpressionPrior):
        return source
    if source is None or str(source) == "off":
        return None
    basis = source if isinstance(source, ExpressionBasis) else load_basis(face, source)
    if basis is None:
        return None
    prior = ExpressionPrior(face, basis, markers, anchors)
    from ..deform.build import get_operator

    if prior.n_virtual:
        op = get_operator(face, np.r_[markers, anchors], engine="fp")
        prior.set_interpolation(operator_rows(op, prior.vertices, len(markers)))
    if CHANNEL:
        controls = np.r_[markers, prior.vertices, anchors].astype(np.int32)
        prior.set_channel(get_operator(face, controls, engine="fp"), controls, face)
    log.info(
        "prior: %d expression shapes (with mirrors), %d virtual controls, channel over %d vertices",
        len(prior.shapes),
        prior.n_virtual,
        0 if prior.channel is None else len(prior.channel.vertices),
    )
    return prior


def operator_rows(op, vertices: np.ndarray, n: int) -> np.ndarray:
    """``(N, n, 3)`` per-axis weights of the first ``n`` controls at ``vertices`` of an operator."""
    if not op.is_sparse:
        return np.repeat(op.dense[vertices, :n, None].astype(np.float64), 3, axis=2)
    return np.stack([op.axis_matrix(a)[vertices][:, :n].toarray() for a in range(3)], axis=2)


def check_vertex_fit(layout: Layout, face: Face, placement, actor_mm: np.ndarray) -> dict:
    """Refuse (InputError) a layout whose vertex-tied markers do not fit ``face`` (see
    ``FIT_SPACING_FRACTION``); returns the fit: ``markers``, ``median_mm``, ``max_mm``, ``limit_mm``.

    ``placement``: the layout's ``Placement`` on the face; ``actor_mm``: ``(K, 3)`` the actor's
    neutral positions of its control markers (mm, placement order)."""
    from scipy.spatial import cKDTree

    mm = face.mm_per_unit
    on_face = face.vertices[placement.vertices].astype(np.float64) * mm  # (K, 3) mm
    tied = np.array([h == "vertex" for h in placement.how], dtype=bool)
    fit = {"markers": int(tied.sum()), "median_mm": 0.0, "max_mm": 0.0, "limit_mm": float("inf")}
    if tied.sum() < 4 or len(on_face) < 2:
        return fit
    src = np.asarray(actor_mm, dtype=np.float64)[tied]
    q, s, c = similarity(src, on_face[tied])
    res = np.linalg.norm(s * src @ q.T + c - on_face[tied], axis=1)
    spacing = float(np.median(cKDTree(on_face).query(on_face, k=2)[0][:, 1]))
    fit.update(
        median_mm=float(np.median(res)),
        max_mm=float(res.max()),
        limit_mm=FIT_SPACING_FRACTION * spacing,
    )
    if fit["median_mm"] > fit["limit_mm"]:
        instead = (
            f"pass --face {layout.face} (the face this layout was made for)"
            if layout.face
            else "pass --face <the mesh this layout was made for>"
        )
        raise InputError(
            f"this layout does not fit the face {face.name!r}: after the best rigid fit its {fit['markers']} "
            f"vertex-tied markers sit {fit['median_mm']:.1f} mm (median; max {fit['max_mm']:.1f} mm) from "
            f"the actor's, where a layout made for this face leaves about the capture noise (refused above "
            f"{fit['limit_mm']:.1f} mm, a quarter of the {spacing:.1f} mm between neighbouring markers): "
            f"its vertex ids are for another mesh. {instead[0].upper()}{instead[1:]}, or a layout made for "
            f'this face (markers tied to feature points, {{"fp": "2.1"}}, or placed automatically, '
            "{}, retarget across faces)",
            where=layout.where,
        )
    return fit


def anchor_vertices(
    face: Face, markers: np.ndarray, factor: float = 2.0, limit: int = 256
) -> np.ndarray:
    """Skin vertices to pin (see ``MarkerRig``): farther than ``factor`` x the median marker spacing
    from every marker, spread by farthest-point sampling until the remaining far skin is within that
    distance of a pin (at most ``limit``).

    The neck is pinned too: on the ICT head its skin more than ~3 cm below the chin moves less than
    0.1 mm in every expression, and left free the shell dragged it 0.3-0.44 mm with the jaw. On
    ``bench/mocap_fidelity.py`` (technician layout, exact displacements, shell) pinning it cut the
    mean skin error from 0.212 to 0.188 mm, and lifting the old limit of 64 pins (the ICT head
    needs 130 to cover its far skin) to 0.175 mm."""
    from scipy.spatial import cKDTree

    from .layout import _skin_vertices

    v = face.vertices.astype(np.float64)
    pts = v[markers]
    if len(pts) < 4:
        return np.zeros(0, dtype=np.int32)
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    skin = _skin_vertices(face)
    dist = cKDTree(pts).query(v[skin])[0]
    far = skin[dist > factor * spacing]
    if not len(far):
        return np.zeros(0, dtype=np.int32)
    return far[farthest_points(v[far], limit, seed_points=pts, until=factor * spacing)].astype(
        np.int32
    )
