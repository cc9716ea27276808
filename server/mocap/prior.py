"""A face prior for mocap: the target face's own expression space fitted to the markers.

Markers see a few dozen skin points; the skin between and beyond them (eyelids, lip rolls, the
cheeks' bulge) is what an engine can only interpolate. When the face comes with expression shapes
(blendshapes: full meshes in its vertex order, e.g. the ICT FaceKit's ``expressions/``), each frame's
marker displacements ``d (K, 3)`` are fitted by shape weights ``w`` in [0, 1] (bounded ridge least
squares, ``fit_weights``), and the shapes give the whole skin: ``B w``. The prior carries that to the
output through a *direct per-vertex channel* (``ExpressionPrior.set_channel``): each frame's
``FaceState`` carries the fitted weights, scaled by the fit's trust, of per-vertex shapes
(``state.Shapes``): each shape minus what the engine spreads of it from the markers, so the output
is ``E d + trust (B w - E B_m w)``: the fitted shapes' own skin, with the engine interpolating only
what they leave unexplained at the markers (``E``: the engine's operator, ``B_m`` the shapes at the
markers). Before it, the fit reached the output only through ~500 *virtual controls* (skin
vertices taking the fitted shapes' displacements, interpolated by the engine; ``n_virtual``, now
off by default), which lost much of it: with exact markers the prior alone reached 0.24x of not
deforming, carried through them 0.31-0.38x.

A take may show expressions the shapes do not span. Each frame's relative fit residual
``|d - B_m w| / |d|`` says how well they do: below ``trust[0]`` the channel and the virtual
controls take the fitted shapes' displacements, above ``trust[1]`` they take what the markers alone interpolate to (the
engine's own result), and in between a linear blend of the two; the channel's weights are scaled
by the same trust.

A symmetric face's shapes are also taken mirrored (x -> -x, ``mirror_map``): a left-side shape gives
the right side's.
"""

from __future__ import annotations

import hashlib
import logging
import lzma
import math
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np
from scipy.spatial import cKDTree

from ..deform.operator import Operator
from ..errors import InputError
from ..faces.face import Face
from ..output.atomic import atomic_path
from ..paths import cache_dir
from ..state import Shapes
from .sampling import farthest_points

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT",
    "ExpressionBasis",
    "ExpressionPrior",
    "fit_weights",
    "load_basis",
    "mirror_map",
    "ramp",
]

#: Shapes whose largest skin motion is below this (mm) are left out (pupil dilation, eye turns).
MIN_MOTION_MM = 0.3
#: Relative marker fit residual: fully trusted below TRUST[0], not at all above TRUST[1]. Smoothed
#: marker noise on a small expression the shapes explain leaves 0.3-0.5 of its motion unexplained,
#: and at (0.3, 0.5) the channel dropped (trust < 1 on 60 % of a generated take's frames, 0 on
#: 16 %). Chosen on mirror folds 0/1 of issue16 and technician (mean 0.533 -> 0.516x; (0.8, 1.2)
#: and no gate at all 0.516x); on strict folds (never tuned on) batch median 0.68 -> 0.67 and mean
#: without fast-large fold 1 0.67 -> 0.66 (no take worse by more than 0.003x); live mean without
#: neutral-last 1.00 -> 0.98 (none of them worse by more than 0.004x).
TRUST = (0.5, 0.8)
#: Ridge weight (relative to the mean squared column norm of the marker block). 0.03 shrank an
#: exact fit: markers moved by three known shapes left 0.047 mm on the skin, 0.025 at 0.01. Chosen
#: on mirror folds 0/1 of issue16 and technician (0.516 -> 0.497x; 0.003: 0.492x); not tuned on:
#: mirror folds of the other five variants 0.695 -> 0.672x (batch, without fast-large fold 1), live
#: no take worse; strict folds (shapes the prior cannot span) 0.688 -> 0.691x, live 0.984 -> 0.985x.
RIDGE = 0.01
#: Virtual controls spread over the skin the shapes move (more than MIN_MOTION_MM); none by
#: default: the direct channel (``set_channel``) carries the fit to every vertex. On mirror folds
#: (issue16 and technician variants, 2-s takes, folds 0/1; the folds the choice was made on) 500
#: virtual controls with the channel gave 0.45/0.87 and 0.16/0.67x, none 0.46/0.87 and 0.15/0.66x
#: (the virtual controls alone: 0.51/0.90 and 0.24/0.73x); none keeps the live frame cheaper.
N_VIRTUAL = 0
#: The direct channel keeps the vertices where some shape's channel delta exceeds this (mm).
CHANNEL_MM = 0.005
#: Fit iterations per live frame, warm started from the last (batch: 200 from zero).
WARM_ITERS = 30
# Tried and left out: a regional prior (Tena et al. 2011): each shape split by R soft region
# weights over the skin (k-means centres on one half of the moving skin, mirrored; Gaussian falloff,
# summing to 1 per vertex), fitted with a Laplacian penalty tying a shape's weights in overlapping
# regions. Its span reaches much more of an unseen expression (ICT strict folds 0/1, the held-out
# shapes' skin projected by least squares: global 0.59/0.78 of their motion left, 6 regions
# 0.32/0.48, 10 0.27/0.38, 16 0.22/0.33; mirror folds 0.002 either way), but 64 or 30 noisy
# markers do not pin the extra weights. Batch (bench/mocap_diagnose.py, 2-s takes, fold priors, 6
# regions, tie 1), global -> regional: strict issue16 0.49/0.69 -> 0.487/0.695, sparse30
# 0.70/0.81 -> 0.701/0.807, dense100 fold 0 0.44 -> 0.444 (with exact markers the prior adds nothing
# there: 0.313 against 0.316 without it); mirror issue16 0.42/0.75 -> 0.416/0.780, sparse30
# 0.83/0.93 -> 0.902/1.005 (more freedom fits the markers' noise). The prior alone from exact
# markers + 0.2 mm noise, 10-16 regions, ties 0.01-10: no setting better on both protocols.
#: The prior batch and live use when none is chosen: the face's own shapes when it has them. On
#: held-out folds (bench/mocap_fidelity.py, rendered output) it is better where a take's shapes are
#: known only by their mirror images (technician 0.40x -> 0.24x) and within 0.01x of the engine
#: alone where they are unknown in any form.
DEFAULT = "auto"


@dataclass(frozen=True)
class ExpressionBasis:
    """Expression shapes of one face: ``deltas (E, V, 3) float32`` from its neutral, face units."""

    names: list[str]
    deltas: np.ndarray

    def __post_init__(self) -> None:
        if (
            self.deltas.ndim != 3
            or self.deltas.shape[2] != 3
            or len(self.names) != len(self.deltas)
        ):
            raise InputError(
                f"an expression basis is (E, V, 3) with E names; got {self.deltas.shape} and "
                f"{len(self.names)} names",
                where="prior",
            )

    def save(self, path: Path) -> Path:
        """Write as ``.npz`` (``names``, ``deltas``) atomically; returns ``path``."""
        with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, names=np.array(self.names), deltas=self.deltas.astype(np.float32))
        return Path(path)


def _read_obj_vertices(text: str) -> np.ndarray:
    rows = [ln.split()[1:4] for ln in text.splitlines() if ln.startswith("v ")]
    return np.asarray(rows, dtype=np.float32).reshape(-1, 3)


def _shape_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.endswith((".obj", ".obj.xz")))


def load_basis(face: Face, source: str | Path = "auto") -> ExpressionBasis | None:
    """The face's expression shapes from ``source``:

    - ``auto``: the ``expressions/`` folder beside the face's mesh file, if there is one (else None);
    - a folder of ``.obj`` / ``.obj.xz`` meshes in the face's vertex order;
    - an ``.npz`` with ``names (E,)`` and ``deltas (E, V, 3)`` (face units, from its neutral).

    Folders are read once and cached under ``cache_dir("mocap")``. InputError when a named source is
    missing or does not match the face's vertex count."""
    if str(source) == "auto":
        mesh = Path(str(face.name))
        folder = mesh.parent / "expressions"
        if not mesh.is_file() or not folder.is_dir() or not _shape_files(folder):
            return None
        source = folder
    path = Path(source)
    if path.is_dir():
        files = _shape_files(path)
        if not files:
            raise InputError("no .obj or .obj.xz expression meshes in the folder", where=str(path))
        key = hashlib.sha256(
            "|".join(f"{f.name}:{f.stat().st_size}:{f.stat().st_mtime_ns}" for f in files).encode()
        ).hexdigest()[:16]
        cache = cache_dir("mocap") / f"basis-{face.mesh_hash}-{key}.npz"
        if cache.is_file():
            return _read_npz(cache, face)
        names, deltas = [], []
        for f in files:
            opener = lzma.open if f.name.endswith(".xz") else open
            with opener(f, "rt") as fh:
                v = _read_obj_vertices(fh.read())
            if v.shape != face.vertices.shape:
                raise InputError(
                    f"expression mesh has {len(v)} vertices, the face {face.n_vertices}",
                    where=str(f),
                )
            names.append(f.name.split(".obj")[0])
            deltas.append(v - face.vertices)
        basis = ExpressionBasis(names, np.stack(deltas).astype(np.float32))
        basis.save(cache)
        return basis
    if path.suffix.lower() == ".npz" and path.is_file():
        return _read_npz(path, face)
    raise InputError(
        "the prior must be auto, off, a folder of expression meshes or an .npz basis",
        where=str(source),
    )


def _read_npz(path: Path, face: Face) -> ExpressionBasis:
    try:
        with np.load(path, allow_pickle=False) as z:
            names, deltas = [str(n) for n in z["names"]], np.asarray(z["deltas"], np.float32)
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"unreadable expression basis ({e})", where=str(path)) from None
    if deltas.ndim != 3 or deltas.shape[1:] != face.vertices.shape:
        raise InputError(
            f"expression basis is {deltas.shape}, the face has {face.n_vertices} vertices",
            where=str(path),
        )
    return ExpressionBasis(names, deltas)


def mirror_map(face: Face, tolerance_mm: float = 0.5) -> np.ndarray | None:
    """``(V,)`` each vertex's mirror image (x -> -x) when the face is symmetric about x = 0 (the
    90th percentile of the mirrored skin's distance to the nearest vertex within ``tolerance_mm``),
    else None."""
    v = face.vertices.astype(np.float64)
    dist, idx = cKDTree(v).query(v * np.array([-1.0, 1.0, 1.0]))
    skin = face.parts.get("skin")
    sel = dist if skin is None or not len(skin) else dist[skin]
    if np.percentile(sel, 90) * face.mm_per_unit > tolerance_mm:
        return None
    return idx.astype(np.int64)


def mirrored(deltas: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """``(E, V, 3)`` the shapes reflected through x = 0 (``mirror_map``)."""
    out = deltas[:, mirror].copy()
    out[..., 0] *= -1.0
    return out


def apply_operator(op: Operator, values: np.ndarray) -> np.ndarray:
    """``(E, V, 3)``: ``op`` applied to each of ``values (E, K, 3)`` (all at once per axis)."""
    e = len(values)
    if op.dense is not None:
        return np.einsum("vk,ekc->evc", op.dense.astype(np.float64), values)
    out = np.empty((e, op.n_vertices, 3))
    for c in range(3):
        out[:, :, c] = (op.axis_matrix(c) @ values[:, :, c].T).T
    return out


@overload
def ramp(x: float, band: tuple[float, float]) -> float: ...
@overload
def ramp(x: np.ndarray, band: tuple[float, float]) -> np.ndarray: ...
def ramp(x: float | np.ndarray, band: tuple[float, float]) -> float | np.ndarray:
    """How far a fit with relative residual ``x`` (a number or an array) is trusted: 1 below
    ``band[0]``, 0 above ``band[1]``, linear between (``ExpressionPrior.trust``, the live and
    batch ``TOWARD_FIT`` gates, ``stabilise.ShapePose``'s trust)."""
    lo, hi = band
    r = (hi - x) / max(hi - lo, 1e-9)
    if isinstance(r, np.ndarray):
        return np.clip(r, 0.0, 1.0)
    return min(max(r, 0.0), 1.0)  # a number (a live frame's): np.clip's overhead is 10x this


def gradient_step(gram: np.ndarray, lipschitz: float) -> np.ndarray:
    """``(E, E)``: FISTA's gradient step as one product, y - (y G - rhs) / L = y (I - G / L) +
    rhs / L (a live frame runs 30 iterations on one row: the calls, not the arithmetic, cost)."""
    return np.eye(len(gram)) - np.asarray(gram) / lipschitz


def fit_weights(
    gram: np.ndarray,
    rhs: np.ndarray,
    lipschitz: float,
    w0: np.ndarray | None = None,
    iters: int = 150,
    move: np.ndarray | None = None,
) -> np.ndarray:
    """Bounded least squares: ``w (T, E)`` in [0, 1] minimising ``w G w / 2 - w . rhs`` row by row
    (accelerated projected gradient, FISTA). ``gram (E, E)`` = AᵀA (+ ridge), ``rhs (T, E)`` = Aᵀb,
    ``lipschitz`` its largest eigenvalue; ``w0`` a warm start; ``move`` = ``gradient_step(gram,
    lipschitz)`` when the caller keeps it."""
    w = np.zeros_like(rhs) if w0 is None else np.clip(w0, 0.0, 1.0)
    y, t = w.copy(), 1.0
    step = 1.0 / lipschitz
    if move is None:
        move = gradient_step(gram, lipschitz)
    push = step * rhs
    for _ in range(iters):
        w_next = y @ move
        w_next += push
        np.minimum(np.maximum(w_next, 0.0, out=w_next), 1.0, out=w_next)
        t_next = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * t * t))
        y = np.subtract(w_next, w, out=y)
        y *= (t - 1.0) / t_next
        y += w_next
        w, t = w_next, t_next
    return w


class ExpressionPrior:
    """The prior for one control set on one face (see the module docstring).

    Args:
        face: the target face.
        basis: its expression shapes (mirrored copies added when ``mirror`` and the face is symmetric).
        markers: ``(K,)`` the marker control vertices.
        avoid: vertices no virtual control may take (the anchors).
        n_virtual, ridge, trust: see the module constants.

    Attributes:
        vertices: ``(N,)`` the virtual control vertices.
        shapes: ``(E, V, 3)`` the shapes fitted (with mirrors).
    """

    def __init__(
        self,
        face: Face,
        basis: ExpressionBasis,
        markers: np.ndarray,
        avoid: np.ndarray | None = None,
        *,
        mirror: bool = True,
        n_virtual: int = N_VIRTUAL,
        ridge: float = RIDGE,
        trust: tuple[float, float] = TRUST,
    ):
        mm = face.mm_per_unit
        skin = face.parts.get("skin")
        skin = np.arange(face.n_vertices) if skin is None or not len(skin) else np.asarray(skin)
        deltas = basis.deltas
        motion = np.linalg.norm(deltas[:, skin], axis=2).max(axis=1) * mm
        keep = motion >= MIN_MOTION_MM
        deltas = deltas[keep]
        self.names = [n for n, k in zip(basis.names, keep) if k]
        mirror_idx = mirror_map(face) if mirror else None
        if mirror_idx is not None and len(deltas):
            deltas = np.concatenate([deltas, mirrored(deltas, mirror_idx)])
            self.names += [f"{n}~mirror" for n in self.names]
        if not len(deltas):
            raise InputError("the expression basis moves no skin", where="prior")
        self.shapes = deltas.astype(np.float32)
        self.markers = np.asarray(markers, dtype=np.int64)
        self.trust = trust
        # virtual controls: skin the shapes move, denser where they move more, away from markers
        moves = np.linalg.norm(self.shapes[:, skin], axis=2).max(axis=0) * mm
        cand = skin[moves > MIN_MOTION_MM]
        taken = np.r_[self.markers, np.asarray(avoid if avoid is not None else [], np.int64)]
        mask = ~np.isin(cand, taken)
        cand, cmove = cand[mask], moves[moves > MIN_MOTION_MM][mask]
        v = face.vertices.astype(np.float64)
        pick = (
            farthest_points(v[cand], n_virtual, seed_points=v[self.markers], weights=np.sqrt(cmove))
            if n_virtual > 0 and len(cand)
            else np.zeros(0, np.int64)
        )
        self.vertices = cand[np.sort(pick)].astype(np.int64)
        a = self.shapes[:, self.markers].reshape(len(self.shapes), -1).T.astype(np.float64)
        self._a = a  # (3K, E)
        scale = float((a**2).sum(axis=0).mean())
        self._gram = a.T @ a + ridge * scale * np.eye(a.shape[1])
        self._lip = float(np.linalg.eigvalsh(self._gram)[-1])
        self._move = gradient_step(self._gram, self._lip)  # (``fit_weights``', once)
        self._virt = self.shapes[:, self.vertices].reshape(len(self.shapes), -1).astype(np.float64)
        self._interp: np.ndarray | None = None
        self._last: np.ndarray | None = None
        self.last_fit: np.ndarray | None = None  # ``fit``'s last frame at the markers (K, 3)
        self.last_residual = 0.0  # and its relative residual
        self.fits: np.ndarray | None = None  # the same for each frame of the last call (T, K, 3)
        self.residuals: np.ndarray | None = None  # (T,)
        self.channel: Shapes | None = None  # set_channel

    @property
    def n_virtual(self) -> int:
        return len(self.vertices)

    def set_channel(self, op: Operator, controls: np.ndarray, face: Face) -> None:
        """The direct per-vertex channel (``channel``): ``op`` the engine's operator over
        ``controls`` (the rig's control vertices: the markers, the virtual controls, then anchors
        that never move). Each shape's channel delta is what the engine misses of it when its
        controls take the shape's displacements: ``B_e - E B_e(controls)`` over the skin it
        touches (the face's deformable, head-carried vertices where it exceeds ``CHANNEL_MM``).
        A frame's output is then ``E d + trust (B - E B_m) w`` (markers at ``d``, virtual controls
        at their blend): where the fit is trusted, the shapes' own skin plus the engine's
        interpolation of what the shapes leave unexplained at the markers."""
        controls = np.asarray(controls, dtype=np.int64)
        values = np.zeros((len(self.shapes), len(controls), 3), np.float64)
        n = len(self.markers) + self.n_virtual
        values[:, :n] = self.shapes[:, controls[:n]]
        spread = apply_operator(op, values)  # (E, V, 3)
        delta = self.shapes - spread.astype(np.float32)
        where = face.deformable & (face.rigid_group == 0)
        size = np.abs(delta).max(axis=(0, 2)) * face.mm_per_unit
        keep = np.flatnonzero(where & (size > CHANNEL_MM))
        self.channel = Shapes(keep, np.ascontiguousarray(delta[:, keep], dtype=np.float32))

    def set_interpolation(self, rows: np.ndarray) -> None:
        """``rows (N, K, 3)``: per axis, how the markers alone interpolate to the virtual vertices
        (the engine's rows there): the fall-back when the shapes do not explain a frame."""
        rows = np.asarray(rows, dtype=np.float64)
        self._interp = np.ascontiguousarray(rows.transpose(2, 1, 0))  # (3, K, N)

    def weights(self, d: np.ndarray, warm: bool = False) -> np.ndarray:
        """``(T, E)`` shape weights fitted to marker displacements ``d (T, K, 3)`` (face units);
        ``warm``: start from the previous call's last frame (live)."""
        b = d.reshape(len(d), -1).astype(np.float64)
        w0 = None
        if warm and self._last is not None:
            w0 = np.repeat(self._last[None], len(d), axis=0)
        iters = WARM_ITERS if warm else 200
        w = fit_weights(self._gram, b @ self._a, self._lip, w0, iters=iters, move=self._move)
        self._last = w[-1].copy()
        return w

    def fit(self, d: np.ndarray, warm: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(weights (T, E), trust (T,))`` for marker displacements ``d (T, K, 3)`` (face units):
        the shape weights and how far the fit is trusted (1 below ``trust[0]`` relative residual,
        0 above ``trust[1]``, linear between; 1 for a frame at rest)."""
        d = np.asarray(d, dtype=np.float64)
        w = self.weights(d, warm)
        fit = (w @ self._a.T).reshape(d.shape)
        size = np.linalg.norm(d.reshape(len(d), -1), axis=1)
        rel = np.linalg.norm((d - fit).reshape(len(d), -1), axis=1) / np.maximum(size, 1e-12)
        beta = ramp(rel, self.trust)
        beta[size <= 1e-12] = 1.0
        # the last frame's fit at the markers and its relative residual (the live path's
        # ``live.TOWARD_FIT``)
        self.last_fit, self.last_residual = fit[-1], float(rel[-1]) if size[-1] > 1e-12 else 0.0
        self.fits, self.residuals = fit, rel  # every frame's (0 at rest: w = 0, fit = 0)
        return w, beta

    def solve(
        self, d: np.ndarray, warm: bool = False
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(virtual displacements (T, N, 3) float32 or None without virtual controls, channel
        weights (T, E) float32 or None without the direct channel)`` for marker displacements
        ``d (T, K, 3)`` (face units): what a ``FaceState`` carries (``controls`` after the markers',
        ``shape_weights`` of ``channel``)."""
        d = np.asarray(d, dtype=np.float64)
        w, beta = self.fit(d, warm)
        virtual = self._virtual(d, w, beta)[0] if self.n_virtual else None
        weights = None if self.channel is None else (beta[:, None] * w).astype(np.float32)
        return virtual, weights

    def virtual(self, d: np.ndarray, warm: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(virtual displacements (T, N, 3) float32, trust (T,))`` for marker displacements
        ``d (T, K, 3)`` (face units): the fitted shapes', blended towards the markers' own
        interpolation as the fit residual grows (module docstring)."""
        d = np.asarray(d, dtype=np.float64)
        w, beta = self.fit(d, warm)
        return self._virtual(d, w, beta)

    def _virtual(
        self, d: np.ndarray, w: np.ndarray, beta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        shaped = (w @ self._virt).reshape(len(d), -1, 3)
        if self._interp is None:
            out = beta[:, None, None] * shaped
        else:  # per axis: (T, K) @ (K, N)
            own = np.stack([d[:, :, c] @ self._interp[c] for c in range(3)], axis=2)
            out = beta[:, None, None] * shaped + (1.0 - beta[:, None, None]) * own
        return out.astype(np.float32), beta
