"""Extended Kalman Filter over the DH parameters (paper sec. III-A).

:class:`ExtendedKalmanFilter` is a generic EKF shaped like filterpy's: explicit ``x``, ``P``,
``Q``, ``R``; :meth:`~ExtendedKalmanFilter.predict` and :meth:`~ExtendedKalmanFilter.update`
take the model as callables; the covariance update is the Joseph form, symmetrised and checked
positive definite; the innovation ``y``, its covariance ``S``, the gain ``K``, the Mahalanobis
distance and NIS of the last update are exposed; an optional gate rejects outliers.

The state is the flattened DH table (random walk, ``x_{k+1} = x_k + w_k``). The observation is a
hand pose; :class:`HandPoseModel` supplies ``h``, its Jacobian and an SO(3)-aware residual
``(p_meas - p_pred, log(R_meas R_pred^T))``, so orientations are never compared as Euler angles.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from . import kinematics

__all__ = ['FilterError', 'InvalidInputError', 'ExtendedKalmanFilter', 'HandPoseModel',
           'chi2_gate', 'nees']


class FilterError(RuntimeError):
    """The filter reached a state it cannot continue from (e.g. P lost positive definiteness)."""


class InvalidInputError(ValueError):
    """An input to the filter is malformed or not finite; the filter state is unchanged."""


def _finite(name: str, a: NDArray[np.float64]) -> NDArray[np.float64]:
    if not np.all(np.isfinite(a)):
        raise InvalidInputError(f'{name} contains NaN or inf: {np.array2string(a, threshold=12)}')
    return a


def _check_cov(name: str, m: ArrayLike, n: int) -> NDArray[np.float64]:
    m = np.array(m, dtype=float)
    if m.shape != (n, n):
        raise InvalidInputError(f'{name} must have shape ({n}, {n}), got {m.shape}')
    _finite(name, m)
    # max|M - M^T| against the scale of M: what allclose would say, at a fraction of its cost.
    if np.max(np.abs(m - m.T), initial=0.0) > 1e-8 * np.max(np.abs(m), initial=0.0) + 1e-12:
        raise InvalidInputError(f'{name} is not symmetric')
    return m


def chi2_gate(dim_z: int, probability: float = 0.999) -> float:
    """Mahalanobis-distance gate that passes ``probability`` of consistent innovations."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f'gate probability must be in (0, 1), got {probability}')
    return float(np.sqrt(chi2.ppf(probability, dim_z)))


def nees(x_true: ArrayLike, x: ArrayLike, P: ArrayLike) -> float:  # noqa: N803
    """Normalised estimation error squared ``(x - x_true)^T P^-1 (x - x_true)``.

    For a consistent filter its expectation is ``len(x)``.
    """
    e = np.asarray(x, dtype=float) - np.asarray(x_true, dtype=float)
    return float(e @ np.linalg.solve(np.asarray(P, dtype=float), e))


class ExtendedKalmanFilter:
    """Generic EKF with a random-walk (identity) process model.

    Parameters
    ----------
    x : array_like, shape (n,)
        Initial state.
    P : array_like, shape (n, n)
        Initial covariance (symmetric positive definite).
    Q : array_like, shape (n, n), optional
        Process-noise covariance added by :meth:`predict` (default zeros).
    R : array_like, shape (m, m), optional
        Default measurement covariance used when :meth:`update` gets none.
    gate : float, optional
        Mahalanobis distance above which an update is rejected (``None``: never).

    Attributes
    ----------
    y, S, K : ndarray
        Innovation (m,), its covariance (m, m) and the gain (n, m) of the last update attempt.
    mahalanobis : float
        ``sqrt(y^T S^-1 y)`` of the last update attempt.
    nis : float
        ``y^T S^-1 y`` (normalised innovation squared) of the last update attempt.
    n_updates, n_rejected : int
        Accepted updates and gated-out attempts so far.
    """

    def __init__(self, x: ArrayLike, P: ArrayLike, Q: ArrayLike | None = None,  # noqa: N803
                 R: ArrayLike | None = None, gate: float | None = None) -> None:  # noqa: N803
        self.x = _finite('x', np.array(x, dtype=float).ravel())
        n = self.x.size
        self.P = _check_cov('P', P, n)
        if np.linalg.eigvalsh(self.P)[0] <= 0:
            raise InvalidInputError('P must be positive definite')
        self.Q = np.zeros((n, n)) if Q is None else _check_cov('Q', Q, n)
        self.R = None if R is None else np.array(R, dtype=float)
        if gate is not None and not gate > 0:
            raise InvalidInputError(f'gate must be positive, got {gate}')
        self.gate = gate
        self.y = np.zeros(0)
        self.S = np.zeros((0, 0))
        self.K = np.zeros((n, 0))
        self.mahalanobis = 0.0
        self.nis = 0.0
        self.n_updates = 0
        self.n_rejected = 0

    @property
    def dim_x(self) -> int:
        return self.x.size

    def predict(self, Q: ArrayLike | None = None) -> None:  # noqa: N803
        """``x`` unchanged (the parameters are constant), ``P <- P + Q``."""
        q = self.Q if Q is None else _check_cov('Q', Q, self.dim_x)
        self.P = self.P + q

    def update(self, z: Any, HJacobian: Callable[..., NDArray[np.float64]],  # noqa: N803
               Hx: Callable[..., Any], R: ArrayLike | None = None,  # noqa: N803
               args: Sequence[Any] = (), hx_args: Sequence[Any] = (),
               residual: Callable[[Any, Any], NDArray[np.float64]] = np.subtract,
               iterations: int = 1) -> bool:
        """One EKF update with observation ``z``.

        Parameters
        ----------
        z : array_like
            Observation (anything ``residual`` understands).
        HJacobian : callable
            ``HJacobian(x, *args)`` -> (m, n) Jacobian of ``h`` at ``x``.
        Hx : callable
            ``Hx(x, *hx_args)`` -> predicted observation.
        R : array_like, shape (m, m), optional
            Measurement covariance (default ``self.R``).
        residual : callable
            ``residual(z, Hx(x))`` -> innovation, shape (m,).
        iterations : int
            1 is the EKF of the paper. More makes it an iterated EKF: the measurement is
            relinearised about the updated estimate (Gauss-Newton on the one-step MAP problem),
            which copes far better with large initial parameter errors. Gating and the exposed
            ``y``, ``S``, ``mahalanobis`` use the first (prior) linearisation.

        Returns
        -------
        bool
            ``True`` if applied, ``False`` if rejected by the gate (state unchanged).

        Raises
        ------
        InvalidInputError
            On non-finite or mis-shaped inputs; the state is unchanged.
        FilterError
            If the updated covariance is not positive definite (the state is unchanged).
        """
        if iterations < 1:
            raise InvalidInputError(f'iterations must be >= 1, got {iterations}')
        if R is None:
            if self.R is None:
                raise InvalidInputError('no measurement covariance: pass R or set filter.R')
            R = self.R  # noqa: N806
        x0 = self.x
        xi = x0
        for it in range(iterations):
            H = _finite('H', np.asarray(HJacobian(xi, *args), dtype=float))  # noqa: N806
            if H.ndim != 2 or H.shape[1] != self.dim_x:
                raise InvalidInputError(f'H must have shape (m, {self.dim_x}), got {H.shape}')
            m = H.shape[0]
            if it == 0:
                R = _check_cov('R', R, m)  # noqa: N806
            r = _finite('innovation', np.asarray(residual(z, Hx(xi, *hx_args)), dtype=float).ravel())
            if r.shape != (m,):
                raise InvalidInputError(f'innovation must have shape ({m},), got {r.shape}')
            PHt = self.P @ H.T  # noqa: N806
            S = H @ PHt + R  # noqa: N806
            try:
                c = np.linalg.cholesky(S)
            except np.linalg.LinAlgError as exc:
                raise InvalidInputError('innovation covariance S is not positive definite '
                                        '(check R)') from exc
            # K = P H^T S^-1 through the Cholesky factor (S is small: m x m).
            K = np.linalg.solve(c.T, np.linalg.solve(c, PHt.T)).T  # noqa: N806
            if it == 0:
                w = np.linalg.solve(c, r)
                self.y, self.S, self.K = r, S, K
                self.nis = float(w @ w)
                self.mahalanobis = float(np.sqrt(self.nis))
                if self.gate is not None and self.mahalanobis > self.gate:
                    self.n_rejected += 1
                    return False
            # Linearised about xi: z ~ h(xi) + H (x - xi)  =>  x = x0 + K (r - H (x0 - xi)).
            xi = x0 + K @ (r - H @ (x0 - xi))

        ikh = np.eye(self.dim_x) - K @ H
        P = ikh @ self.P @ ikh.T + K @ R @ K.T  # noqa: N806  (Joseph form)
        P = 0.5 * (P + P.T)  # noqa: N806
        try:
            np.linalg.cholesky(P)
        except np.linalg.LinAlgError as exc:
            raise FilterError('updated covariance lost positive definiteness') from exc
        self.x = _finite('updated state', xi)
        self.P = P
        self.n_updates += 1
        return True


@dataclass(frozen=True)
class HandPoseModel:
    """Observation model ``z = h(x, q)``: the hand pose of a DH chain at joint angles ``q``.

    Parameters
    ----------
    base : ndarray, shape (4, 4)
        Root to the frame before the first estimated link.
    n_links : int
    """

    base: NDArray[np.float64]
    n_links: int
    # h and H are evaluated at the same (x, q) in every linearisation: keep the last frames.
    _frames: dict[bytes, NDArray[np.float64]] = field(default_factory=dict, init=False,
                                                      repr=False, compare=False)

    def table(self, x: ArrayLike) -> NDArray[np.float64]:
        """The state as a DH table, shape (L, 4)."""
        return np.asarray(x, dtype=float).reshape(self.n_links, kinematics.PARAMS_PER_LINK)

    def frames(self, x: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
        """All chain frames at ``(x, q)``, shape (L + 1, 4, 4); the last evaluation is cached."""
        x, q = np.asarray(x, dtype=float), np.asarray(q, dtype=float)
        key = x.tobytes() + q.tobytes()
        if key not in self._frames:
            self._frames.clear()
            self._frames[key] = kinematics.chain_frames(self.base, self.table(x), q)
        return self._frames[key]

    def hx(self, x: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
        """Predicted hand pose, shape (4, 4)."""
        return self.frames(x, q)[-1]

    def jacobian(self, x: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
        """``dh/dx``, shape (6, 4 L)."""
        return kinematics.pose_jacobian_from_frames(self.frames(x, q))

    @staticmethod
    def residual(z: ArrayLike, hx: ArrayLike) -> NDArray[np.float64]:
        """``(p_z - p_h, log(R_z R_h^T))`` for 4x4 poses, shape (6,)."""
        z = np.asarray(z, dtype=float)
        hx = np.asarray(hx, dtype=float)
        if z.shape != (4, 4):
            raise InvalidInputError(f'pose observation must be a 4x4 transform, got {z.shape}')
        _finite('pose observation', z)
        return np.concatenate([z[:3, 3] - hx[:3, 3], kinematics.rotation_vector_error(z[:3, :3], hx[:3, :3])])

    def update(self, ekf: ExtendedKalmanFilter, q: ArrayLike, pose: ArrayLike, R: ArrayLike,  # noqa: N803
               iterations: int = 1) -> bool:
        """Apply one hand-pose observation ``pose`` (4, 4) taken at joints ``q`` (L,)."""
        q = _finite('joint configuration', np.asarray(q, dtype=float))
        if q.shape != (self.n_links,):
            raise InvalidInputError(f'joint configuration must have shape ({self.n_links},), got {q.shape}')
        return ekf.update(pose, self.jacobian, self.hx, R=R, args=(q,), hx_args=(q,),
                          residual=self.residual, iterations=iterations)
