"""Non-parametric occlusion model: kernel-smoothed Beta posterior (paper sec. III-C).

Each measurement attempt at joints ``theta_k`` records a success (marker detected) or a failure.
The probability ``eta`` of success at a new ``theta_*`` has the posterior

    Be(eta; sum_k K(theta_*, theta_k) S_k + a0,  sum_k K(theta_*, theta_k) U_k + b0)

with a squared-exponential kernel in normalised joint space (each joint scaled to [0, 1] by the
box), ``K = exp(-||u_* - u_k||^2 / (2 l^2))``, so ``K = 1`` at a visited configuration and decays
with distance. Repeated attempts at one configuration add to that configuration's counts, as in
the paper's ``S_k, U_k``. The posterior mean (eq. finalbeta) is what the acquisition uses.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.distance import cdist

__all__ = ['OcclusionModel']


class OcclusionModel:
    """Kernel-smoothed Beta model of the probability that the hand is detected.

    Parameters
    ----------
    box : array_like, shape (L, 2)
        Joint box used to normalise configurations to [0, 1]^L.
    length_scale : float
        Kernel length scale ``l`` in normalised units.
    a0, b0 : float
        Beta prior pseudo-counts for success and failure.
    """

    def __init__(self, box: ArrayLike, length_scale: float = 0.1, a0: float = 1.0, b0: float = 1.0) -> None:
        box = np.asarray(box, dtype=float)
        if box.ndim != 2 or box.shape[1] != 2 or np.any(box[:, 1] <= box[:, 0]):
            raise ValueError(f'box must be (L, 2) with min < max per joint, got {box.tolist()}')
        for name, v in (('length_scale', length_scale), ('a0', a0), ('b0', b0)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'OcclusionModel.{name} must be finite and > 0, got {v}')
        self.lower = box[:, 0]
        self.span = box[:, 1] - box[:, 0]
        self.length_scale = float(length_scale)
        self.a0, self.b0 = float(a0), float(b0)
        self._u = np.zeros((0, box.shape[0]))       # normalised visited configurations
        self._s = np.zeros(0)                        # successes at each
        self._f = np.zeros(0)                        # failures at each

    @property
    def n_configs(self) -> int:
        """Distinct configurations with recorded attempts."""
        return self._u.shape[0]

    @property
    def counts(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Successes and failures per recorded configuration, each shape (K,)."""
        return self._s.copy(), self._f.copy()

    def normalise(self, theta: ArrayLike) -> NDArray[np.float64]:
        """Joint angles -> [0, 1]^L box coordinates, shape preserved."""
        return (np.asarray(theta, dtype=float) - self.lower) / self.span

    def add(self, theta: ArrayLike, success: bool) -> None:
        """Record one attempt at ``theta`` (shape (L,)).

        An attempt at an already recorded configuration (to 1e-9 in normalised units) adds to
        its counts rather than creating a twin.
        """
        theta = np.asarray(theta, dtype=float)
        if theta.shape != self.lower.shape or not np.all(np.isfinite(theta)):
            raise ValueError(f'theta must be {self.lower.size} finite joint angles, got {theta!r}')
        u = self.normalise(theta)
        if self.n_configs:
            hit = np.nonzero(np.all(np.abs(self._u - u) < 1e-9, axis=1))[0]
            if hit.size:
                (self._s if success else self._f)[hit[0]] += 1.0
                return
        self._u = np.vstack([self._u, u])
        self._s = np.append(self._s, 1.0 if success else 0.0)
        self._f = np.append(self._f, 0.0 if success else 1.0)

    def kernel(self, theta: ArrayLike) -> NDArray[np.float64]:
        """Kernel weights to every recorded configuration.

        Parameters
        ----------
        theta : array_like, shape (L,) or (M, L)

        Returns
        -------
        ndarray, shape (K,) or (M, K)
        """
        u = self.normalise(theta)
        # cdist: ~10x faster than broadcasting (M, K, L) for the selector's thousands of candidates.
        d2 = cdist(np.atleast_2d(u), self._u, 'sqeuclidean').reshape(u.shape[:-1] + (self.n_configs,))
        return np.exp(-0.5 * d2 / self.length_scale ** 2)

    def posterior(self, theta: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Beta parameters ``(alpha, beta)`` at ``theta`` (shape (L,) or (M, L))."""
        k = self.kernel(theta)
        return k @ self._s + self.a0, k @ self._f + self.b0

    def mean(self, theta: ArrayLike) -> NDArray[np.float64]:
        """Posterior mean success probability ``eta_bar``, shape () or (M,)."""
        a, b = self.posterior(theta)
        return a / (a + b)
