"""Pairs hand-pose observations with joint states and turns them into EKF updates (no rclpy).

The estimator node and the offline evaluation (:mod:`dh_estimator.evaluate`) both feed their
messages through :class:`ObservationPairer`, so a bag re-run makes exactly the decisions the
online node made: which image counts as a measurement attempt (the arm rests at the commanded
target), which joint state belongs to it (interpolated at the image stamp) and what the filter
did with it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema import ekf as ekf_mod

from .estimator import OnlineEstimator, Outcome
from .joint_buffer import JointStateBuffer, StampOutOfRange

__all__ = ['PairingSettings', 'Attempt', 'ObservationPairer']


@dataclass(frozen=True)
class PairingSettings:
    """When an observation is a measurement attempt.

    Attributes
    ----------
    static_window : float
        The arm must have been still this long before the image stamp [s].
    static_tol : float
        Joint motion tolerated as still [rad].
    require_command : bool
        Only observations taken at the latest commanded target count (not the start pose,
        not a pose passed on the way).
    target_tol : float
        Max joint distance from the commanded target [rad].
    max_pending : int
        Observations kept while waiting for the joint states that cover their stamp.
    """

    static_window: float = 0.1
    static_tol: float = 1e-4
    require_command: bool = True
    target_tol: float = 0.005
    max_pending: int = 10


@dataclass(frozen=True)
class Attempt:
    """What became of one observation that was a measurement attempt.

    ``outcome`` is an :class:`~dh_estimator.estimator.Outcome` value (accepted, rejected,
    duplicate) or one of 'moving' (arm not still at the stamp), 'invalid' (the filter refused
    the input) and 'dropped' (no joint state covers the stamp).
    """

    stamp: float
    joints: NDArray[np.float64] | None
    outcome: str
    message: str
    update_seconds: float = 0.0


class ObservationPairer:
    """Buffers joint states, commands and hand poses; offers each attempt to the estimator.

    Parameters
    ----------
    estimator : OnlineEstimator
        Receives one :meth:`~OnlineEstimator.offer` per attempt.
    settings : PairingSettings
    """

    def __init__(self, estimator: OnlineEstimator, settings: PairingSettings = PairingSettings()) -> None:
        self.estimator = estimator
        self.settings = settings
        self.buffer = JointStateBuffer(estimator.model.n_joints)
        self.target: NDArray[np.float64] | None = None
        self._pending: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []

    def command(self, target: ArrayLike) -> None:
        """The latest commanded joint target, shape (L,) [rad]."""
        self.target = np.asarray(target, dtype=float).copy()

    def joint_state(self, t: float, q: ArrayLike) -> list[Attempt]:
        """Add joint positions ``q`` (L,) at time ``t`` [s]; returns attempts it completed."""
        self.buffer.add(t, q)
        return self._process() if self._pending else []

    def hand_pose(self, t: float, pose: ArrayLike, R: ArrayLike) -> list[Attempt]:  # noqa: N803
        """Add a hand pose (4, 4) in the root frame with covariance ``R`` (6, 6) at image stamp ``t``.

        Returns the attempts this completed (none while the joint states of ``t`` are not in).
        """
        self._pending.append((float(t), np.asarray(pose, dtype=float), np.asarray(R, dtype=float)))
        return self._process()

    def _process(self) -> list[Attempt]:
        latest = self.buffer.latest
        keep, done = [], []
        for item in self._pending:
            if latest is None or item[0] > latest[0]:
                keep.append(item)                    # joint states for this image not here yet
                continue
            attempt = self._attempt(*item)
            if attempt is not None:
                done.append(attempt)
        self._pending = keep[-self.settings.max_pending:]
        return done

    def _attempt(self, t: float, pose: NDArray[np.float64], R: NDArray[np.float64]) -> Attempt | None:  # noqa: N803
        s = self.settings
        try:
            q = self.buffer.at(t)
        except StampOutOfRange as exc:
            return Attempt(t, None, 'dropped', str(exc))
        if s.require_command and (self.target is None or np.max(np.abs(q - self.target)) > s.target_tol):
            return None             # not at a commanded target: not a measurement attempt
        if not self.buffer.is_static(t, s.static_window, s.static_tol):
            return Attempt(t, q, 'moving', 'arm not still at the image stamp; observation not used')
        t0 = time.perf_counter()
        try:
            outcome = self.estimator.offer(q, pose, R)
        except (ValueError, ekf_mod.InvalidInputError, ekf_mod.FilterError) as exc:
            return Attempt(t, q, 'invalid', str(exc))
        message = 'same configuration as the previous attempt' if outcome is Outcome.DUPLICATE \
            else self.estimator.describe_last()
        return Attempt(t, q, outcome.value, message, time.perf_counter() - t0)
