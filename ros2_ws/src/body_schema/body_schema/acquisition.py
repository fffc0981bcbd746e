"""Active selection of the next joint configuration (paper sec. III-B).

A-optimality (eq. costPmatrix): the cost of measuring at ``theta`` is the expected trace of the
EKF covariance after that measurement,

    C0(theta) = tr(P) - tr((H P)^T S^-1 (H P)),   S = H P H^T + R(theta),

with ``H`` the pose Jacobian w.r.t. the DH parameters and ``R(theta)`` the noise model's
prediction for the hand pose the current estimate expects at ``theta`` (computed in closed form;
no covariance copy per evaluation). The paper's full cost (eq. changedActiveLearning) divides by
the occlusion model's success probability and penalises hands behind the body (root x points
backward):

    C(theta) = C0(theta) / eta(theta) + a * arctan(b * p_x(theta)).

Strategies:

* ``random`` (R): uniform in the calibration box.
* ``al`` (AL, eq. ALgeneralCost): minimise ``C`` over the box.
* ``ucsal`` (UCSAL, eq. csALgeneralCost): minimise ``C + gamma * d(theta, theta_prev)``, with ``d``
  the **L1 norm in normalised joint space** (each joint scaled to [0, 1] by the box), the same
  norm as the accumulated-movement metric, made unit-free so joints with wide ranges do not
  dominate.
* ``ccsal`` (CCSAL, eq. ALConstrained): minimise ``C`` over ``box ∩ [u_prev - delta, u_prev + delta]``
  in normalised units.

The minimisation is global, with NLopt's DIRECT family (DIRECT-L by default). DIRECT is
deterministic; the randomised variant is seeded through ``nlopt.srand``.
"""
from __future__ import annotations

import enum
import time
from dataclasses import dataclass, field
from typing import Sequence

import nlopt
import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import kinematics
from .noise import NoiseModel
from .occlusion import OcclusionModel
from .robot import MarkerPlacement
from .sampling import as_rng

__all__ = ['Strategy', 'DIRECT_ALGORITHMS', 'expected_trace', 'AcquisitionCost', 'SelectorConfig',
           'Selection', 'JointSelector']


class Strategy(str, enum.Enum):
    """Joint-selection strategies of the paper."""

    RANDOM = 'random'
    AL = 'al'
    UCSAL = 'ucsal'
    CCSAL = 'ccsal'

    @classmethod
    def parse(cls, name: str) -> 'Strategy':
        try:
            return cls(name.lower())
        except ValueError:
            raise ValueError(f'unknown strategy {name!r}; expected one of '
                             f'{[s.value for s in cls]}') from None


#: NLopt global algorithms accepted by name.
DIRECT_ALGORITHMS = {
    'DIRECT': nlopt.GN_DIRECT,
    'DIRECT_L': nlopt.GN_DIRECT_L,
    'DIRECT_L_RAND': nlopt.GN_DIRECT_L_RAND,
    'DIRECT_NOSCAL': nlopt.GN_DIRECT_NOSCAL,
    'DIRECT_L_NOSCAL': nlopt.GN_DIRECT_L_NOSCAL,
    'ORIG_DIRECT': nlopt.GN_ORIG_DIRECT,
    'ORIG_DIRECT_L': nlopt.GN_ORIG_DIRECT_L,
}


def expected_trace(P: NDArray[np.float64], H: NDArray[np.float64], R: NDArray[np.float64],  # noqa: N803
                   trace_P: float | None = None) -> float:  # noqa: N803
    """Trace of the covariance after one update, without forming it.

    Parameters
    ----------
    P : ndarray, shape (n, n)
    H : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
    trace_P : float, optional
        ``tr(P)`` if already known.

    Returns
    -------
    float
        ``tr(P) - tr((H P)^T S^-1 (H P))``.
    """
    hp = H @ P
    s = hp @ H.T + R
    reduction = float(np.sum(hp * np.linalg.solve(s, hp)))
    return (float(np.trace(P)) if trace_P is None else trace_P) - reduction


@dataclass
class AcquisitionCost:
    """The paper's cost ``C(theta)`` for the current estimate.

    Parameters
    ----------
    base : ndarray, shape (4, 4)
    dh : ndarray, shape (L, 4)
        Current DH estimate.
    P : ndarray, shape (4 L, 4 L)
        Current estimate covariance.
    noise : NoiseModel
        Predicts ``R(theta)`` from the expected hand pose.
    camera_pose : ndarray, shape (4, 4)
        Camera optical frame in the root frame.
    markers : sequence of MarkerPlacement
    occlusion : OcclusionModel, optional
        ``eta(theta)``; ``None`` means ``eta = 1``.
    penalty_a, penalty_b : float
        ``a * arctan(b * p_x)`` penalty (``a = 0`` disables it).
    occlusion_mode : {'paper', 'expected'}
        ``'paper'``: ``C0 / eta`` (eq. changedActiveLearning). ``'expected'``: the expected
        posterior trace when the attempt fails with probability ``1 - eta``,
        ``tr(P) - eta (tr(P) - C0)`` (an extension, not the paper's).
    """

    base: NDArray[np.float64]
    dh: NDArray[np.float64]
    P: NDArray[np.float64]
    noise: NoiseModel
    camera_pose: NDArray[np.float64]
    markers: Sequence[MarkerPlacement]
    occlusion: OcclusionModel | None = None
    penalty_a: float = 0.0
    penalty_b: float = 1.0
    occlusion_mode: str = 'paper'
    _trace_p: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.dh = np.asarray(self.dh, dtype=float)
        self.P = np.asarray(self.P, dtype=float)
        n = self.dh.size
        if self.P.shape != (n, n):
            raise ValueError(f'P must have shape ({n}, {n}) for a {self.dh.shape} DH table, '
                             f'got {self.P.shape}')
        if not (np.all(np.isfinite(self.dh)) and np.all(np.isfinite(self.P))):
            raise ValueError('estimate or covariance contains NaN or inf')
        if self.occlusion_mode not in ('paper', 'expected'):
            raise ValueError(f"occlusion_mode must be 'paper' or 'expected', got {self.occlusion_mode!r}")
        self._trace_p = float(np.trace(self.P))

    def terms(self, theta: ArrayLike) -> tuple[float, float, float]:
        """``(C0, eta, p_x)`` at one configuration ``theta`` (L,)."""
        frames = kinematics.chain_frames(self.base, self.dh, theta)
        hand = frames[-1]
        H = kinematics.pose_jacobian_from_frames(frames)  # noqa: N806
        R = self.noise.hand_covariance(self.camera_pose, hand, self.markers)  # noqa: N806
        c0 = expected_trace(self.P, H, R, self._trace_p)
        eta = 1.0 if self.occlusion is None else float(self.occlusion.mean(theta))
        return c0, eta, float(hand[0, 3])

    def __call__(self, theta: ArrayLike) -> float:
        """``C(theta)``."""
        c0, eta, px = self.terms(theta)
        if self.occlusion_mode == 'paper':
            c = c0 / max(eta, 1e-12)
        else:
            c = self._trace_p - eta * (self._trace_p - c0)
        return c + self.penalty_a * float(np.arctan(self.penalty_b * px))


@dataclass(frozen=True)
class SelectorConfig:
    """Parameters of a joint selector.

    Attributes
    ----------
    strategy : Strategy
    gamma : float
        UCSAL movement weight on the normalised L1 distance.
    delta : float
        CCSAL half-width of the allowed box per joint, normalised units in (0, 1].
    algorithm : str
        A key of :data:`DIRECT_ALGORITHMS`.
    max_evals : int
        Cost evaluations per selection.
    seed : int
        Seeds the random strategy and randomised DIRECT variants.
    """

    strategy: Strategy = Strategy.AL
    gamma: float = 0.005
    delta: float = 0.2
    algorithm: str = 'DIRECT_L'
    max_evals: int = 1000
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, 'strategy', Strategy.parse(str(getattr(self.strategy, 'value', self.strategy))))
        if self.algorithm not in DIRECT_ALGORITHMS:
            raise ValueError(f'unknown algorithm {self.algorithm!r}; expected one of {sorted(DIRECT_ALGORITHMS)}')
        if not (np.isfinite(self.gamma) and self.gamma >= 0):
            raise ValueError(f'gamma must be finite and >= 0, got {self.gamma}')
        if not 0.0 < self.delta <= 1.0:
            raise ValueError(f'delta must be in (0, 1], got {self.delta}')
        if self.max_evals < 10:
            raise ValueError(f'max_evals must be at least 10, got {self.max_evals}')


@dataclass(frozen=True)
class Selection:
    """The outcome of one selection."""

    theta: NDArray[np.float64]
    cost: float
    evaluations: int
    seconds: float
    bounds: NDArray[np.float64]


class JointSelector:
    """Chooses the next configuration with one strategy.

    Parameters
    ----------
    box : array_like, shape (L, 2)
        Calibration box [rad].
    config : SelectorConfig
    """

    def __init__(self, box: ArrayLike, config: SelectorConfig = SelectorConfig()) -> None:
        self.box = np.asarray(box, dtype=float)
        if self.box.ndim != 2 or self.box.shape[1] != 2 or np.any(self.box[:, 1] <= self.box[:, 0]):
            raise ValueError(f'box must be (L, 2) with min < max, got {self.box.tolist()}')
        self.config = config
        self.span = self.box[:, 1] - self.box[:, 0]
        self._rng = as_rng(config.seed)

    def distance(self, theta: ArrayLike, previous: ArrayLike) -> float:
        """UCSAL's movement cost: L1 norm of the normalised joint difference."""
        return float(np.sum(np.abs((np.asarray(theta) - np.asarray(previous)) / self.span)))

    def bounds(self, previous: ArrayLike | None) -> NDArray[np.float64]:
        """Search bounds (L, 2): the box, or for CCSAL its intersection with the delta box."""
        if self.config.strategy is not Strategy.CCSAL or previous is None:
            return self.box.copy()
        prev = np.clip(np.asarray(previous, dtype=float), self.box[:, 0], self.box[:, 1])
        half = self.config.delta * self.span
        return np.stack([np.maximum(self.box[:, 0], prev - half),
                         np.minimum(self.box[:, 1], prev + half)], axis=1)

    def select(self, cost: AcquisitionCost | None, previous: ArrayLike | None = None) -> Selection:
        """The next configuration.

        Parameters
        ----------
        cost : AcquisitionCost or None
            The current cost; unused (may be ``None``) for the random strategy.
        previous : array_like, shape (L,), optional
            The previous configuration (needed by UCSAL and CCSAL).
        """
        t0 = time.perf_counter()
        strategy = self.config.strategy
        bounds = self.bounds(previous)
        if strategy is Strategy.RANDOM:
            theta = self._rng.uniform(bounds[:, 0], bounds[:, 1])
            return Selection(theta, float('nan'), 0, time.perf_counter() - t0, bounds)
        if cost is None:
            raise ValueError(f'strategy {strategy.value} needs an AcquisitionCost')
        if strategy in (Strategy.UCSAL, Strategy.CCSAL) and previous is None:
            raise ValueError(f'strategy {strategy.value} needs the previous configuration')

        if strategy is Strategy.UCSAL:
            prev = np.asarray(previous, dtype=float)
            gamma = self.config.gamma

            def objective(theta: NDArray[np.float64]) -> float:
                return cost(theta) + gamma * self.distance(theta, prev)
        else:
            objective = cost

        n_evals = 0
        best = (np.inf, 0.5 * (bounds[:, 0] + bounds[:, 1]))

        def f(theta: NDArray[np.float64], grad: NDArray[np.float64]) -> float:
            nonlocal n_evals, best
            n_evals += 1
            v = float(objective(theta))
            if not np.isfinite(v):
                v = 1e300  # keep DIRECT going; such points are never chosen
            if v < best[0]:
                best = (v, theta.copy())
            return v

        opt = nlopt.opt(DIRECT_ALGORITHMS[self.config.algorithm], self.box.shape[0])
        if self.config.algorithm.endswith('RAND'):
            nlopt.srand(int(self._rng.integers(2**31)))
        opt.set_lower_bounds(bounds[:, 0])
        opt.set_upper_bounds(bounds[:, 1])
        opt.set_min_objective(f)
        opt.set_maxeval(self.config.max_evals)
        try:
            opt.optimize(0.5 * (bounds[:, 0] + bounds[:, 1]))
        except nlopt.RoundoffLimited:
            pass  # the best point so far is still valid
        theta = np.clip(best[1], bounds[:, 0], bounds[:, 1])
        return Selection(theta, best[0], n_evals, time.perf_counter() - t0, bounds)
