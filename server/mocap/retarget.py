"""Retargeting: an RBF map from the actor's neutral marker positions to the target face's.

Sánchez Lorenzo (2006) §4.3.2, Eq 4.13-4.14: ``Psi(x) = sum_j phi_j(|x - c_j|) w_j`` with centres
``c_j`` = the actor's neutral markers and the inverse multiquadric ``phi_j(r) = (r² + delta_j²)^-mu``
(delta_j = distance from centre j to its nearest other centre; the thesis writes delta_j, which is a
length, so it is squared here to keep the units consistent; mu = 2 in the thesis), or
``phi(r) = r``. An affine term is added (the thesis leaves it out; with it, a pure change of frame,
scale or units is carried exactly, and an identity retarget reproduces its input). Displacements
are retargeted along their whole path: ``d_t = Psi(c + d_s) - Psi(c)``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["RBFMap"]


class RBFMap:
    """Interpolating map ``(K, 3)`` source points -> ``(K, 3)`` target points.

    Args:
        src: ``(K, 3)`` centres (actor's neutral markers), any units.
        dst: ``(K, 3)`` their images (marker positions on the target face), any units.
        kernel: ``"imq"`` (inverse multiquadric) or ``"r"`` (biharmonic).
        mu: IMQ exponent.
        affine: add a linear polynomial term (needs K >= 4 non-coplanar points; dropped otherwise).
    """

    def __init__(
        self,
        src: np.ndarray,
        dst: np.ndarray,
        *,
        kernel: str = "imq",
        mu: float = 2.0,
        affine: bool = True,
    ):
        src = np.asarray(src, dtype=np.float64)
        dst = np.asarray(dst, dtype=np.float64)
        if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
            raise ValueError(f"src and dst must both be (K, 3), got {src.shape} and {dst.shape}")
        if kernel not in ("imq", "r"):
            raise ValueError(f"kernel must be 'imq' or 'r', not {kernel!r}")
        k = len(src)
        # Normalise the source so that the kernel does not depend on units.
        self.centre = src.mean(axis=0)
        self.scale = float(np.sqrt(((src - self.centre) ** 2).sum(axis=1).mean())) or 1.0
        self.c = (src - self.centre) / self.scale
        self.kernel, self.mu = kernel, mu
        if k > 1:
            d, _ = cKDTree(self.c).query(self.c, k=2)
            self.delta2 = np.maximum(d[:, 1], 1e-9) ** 2
        else:
            self.delta2 = np.ones(1)
        self.affine = affine and k >= 4 and np.linalg.matrix_rank(np.c_[self.c, np.ones(k)]) == 4
        phi = self._phi(self.c)
        if self.affine:
            p = np.c_[self.c, np.ones(k)]
            a = np.block([[phi, p], [p.T, np.zeros((4, 4))]])
            rhs = np.r_[dst, np.zeros((4, 3))]
        else:
            a, rhs = phi, dst
        sol = (
            np.linalg.lstsq(a, rhs, rcond=None)[0]
            if np.linalg.cond(a) > 1e13
            else np.linalg.solve(a, rhs)
        )
        self.w = sol[:k]
        self.poly = sol[k:] if self.affine else np.zeros((4, 3))
        self.dst = dst
        self.identity = bool(np.array_equal(src, dst))

    def _phi(self, x: np.ndarray) -> np.ndarray:
        """``(N, K)`` kernel values for normalised points ``(N, 3)``."""
        r2 = ((x[:, None, :] - self.c[None, :, :]) ** 2).sum(axis=2)
        if self.kernel == "imq":
            return (r2 + self.delta2[None, :]) ** (-self.mu)
        return np.sqrt(r2)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Map ``(..., 3)`` source points to target space."""
        x = np.asarray(x, dtype=np.float64)
        if self.identity:
            return x.copy()
        flat = (x.reshape(-1, 3) - self.centre) / self.scale
        out = self._phi(flat) @ self.w
        if self.affine:
            out += flat @ self.poly[:3] + self.poly[3]
        return out.reshape(x.shape)

    def displacements(self, moved: np.ndarray) -> np.ndarray:
        """Retarget ``(..., K, 3)`` moved source markers (same order as the centres) to target
        displacements ``Psi(moved) - dst``."""
        return self(moved) - self.dst
