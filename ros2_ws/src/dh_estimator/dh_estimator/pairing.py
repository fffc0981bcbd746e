"""Pairs hand-pose observations with joint states and turns them into EKF updates (no rclpy).

The estimator node and the offline evaluation (:mod:`dh_estimator.evaluate`) both feed their
messages (live rclpy messages, or objects decoded from a bag: same field names) through
:class:`MessageFeeder` into :class:`ObservationPairer`, so a bag re-run makes exactly the decisions
the online node made: which image counts as a measurement attempt (the arm rests at the commanded
target), which joint state belongs to it (interpolated at the image stamp) and what the filter
did with it.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema import ekf as ekf_mod
from body_schema.noise import ConstantNoise

from calibration_interfaces.messages import joints_in_order, pose_msg_to_matrix, stamp_to_seconds
from calibration_interfaces.outcome import Outcome
from calibration_interfaces.parameters import setting

from .estimator import OnlineEstimator
from .joint_buffer import JointStateBuffer, StampOutOfRange

__all__ = ['PairingSettings', 'ObservationResult', 'ObservationPairer', 'MessageError', 'MessageFeeder']


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

    static_window: float = setting(0.1, 'The arm must be still this long before the image stamp [s]', (0.0, 5.0))
    static_tol: float = setting(1e-4, 'Joint motion tolerated as still [rad]', (0.0, 0.1), name='static_tolerance')
    require_command: bool = setting(True, 'Only use observations taken at the latest /arm/command target')
    target_tol: float = setting(0.005, 'Max joint distance from the commanded target [rad]', (0.0, 0.5),
                                name='target_tolerance')
    max_pending: int = 10


@dataclass(frozen=True)
class ObservationResult:
    """What became of one observation that was a measurement attempt.

    ``outcome`` is the estimator's (accepted, rejected, duplicate) or the pairing's: MOVING (arm
    not still at the stamp), INVALID (the filter refused the input) or DROPPED (no joint state
    covers the stamp).
    """

    stamp: float
    joints: NDArray[np.float64] | None
    outcome: Outcome
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

    def joint_state(self, t: float, q: ArrayLike) -> list[ObservationResult]:
        """Add joint positions ``q`` (L,) at time ``t`` [s]; returns attempts it completed."""
        self.buffer.add(t, q)
        return self._process() if self._pending else []

    def hand_pose(self, t: float, pose: ArrayLike, R: ArrayLike) -> list[ObservationResult]:  # noqa: N803
        """Add a hand pose (4, 4) in the root frame with covariance ``R`` (6, 6) at image stamp ``t``.

        Returns the attempts this completed (none while the joint states of ``t`` are not in).
        """
        self._pending.append((float(t), np.asarray(pose, dtype=float), np.asarray(R, dtype=float)))
        return self._process()

    def _process(self) -> list[ObservationResult]:
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

    def _attempt(self, t: float, pose: NDArray[np.float64], R: NDArray[np.float64]) -> ObservationResult | None:  # noqa: N803
        s = self.settings
        try:
            q = self.buffer.at(t)
        except StampOutOfRange as exc:
            return ObservationResult(t, None, Outcome.DROPPED, str(exc))
        if s.require_command and (self.target is None or np.max(np.abs(q - self.target)) > s.target_tol):
            return None             # not at a commanded target: not a measurement attempt
        if not self.buffer.is_static(t, s.static_window, s.static_tol):
            return ObservationResult(t, q, Outcome.MOVING, 'arm not still at the image stamp; observation not used')
        t0 = time.perf_counter()
        try:
            outcome = self.estimator.offer(q, pose, R)
        except (ValueError, ekf_mod.InvalidInputError, ekf_mod.FilterError) as exc:
            return ObservationResult(t, q, Outcome.INVALID, str(exc))
        f = self.estimator.ekf
        message = 'same configuration as the previous attempt' if outcome is Outcome.DUPLICATE \
            else f'mahalanobis {f.mahalanobis:.3f}'
        return ObservationResult(t, q, outcome, message, time.perf_counter() - t0)


class MessageError(ValueError):
    """A message the pairer cannot use.

    Attributes
    ----------
    key : str
        What is wrong, for grouping repeats (a node warns once per key when ``once``).
    once : bool
        A property of the stream (warn once) rather than of this message (warn each time).
    """

    def __init__(self, key: str, text: str, once: bool = True) -> None:
        super().__init__(text)
        self.key, self.once = key, once


class MessageFeeder:
    """Feeds ``/joint_states``, ``/arm/command`` and ``/hand_pose`` messages to a pairer.

    Parameters
    ----------
    pairer : ObservationPairer
    joint_names : sequence of str
        The estimated joints, in the estimator's order.
    constant_noise : ConstantNoise, optional
        Use its covariance (the paper's CN baseline) instead of the one in ``/hand_pose``.
    """

    def __init__(self, pairer: ObservationPairer, joint_names: Sequence[str],
                 constant_noise: ConstantNoise | None = None) -> None:
        self.pairer = pairer
        self.joint_names = list(joint_names)
        self.constant_noise = constant_noise

    def joint_state(self, msg: Any) -> list[ObservationResult]:
        """A sensor_msgs/JointState; returns the attempts it completed.

        Raises
        ------
        MessageError
            If joints are missing, names and positions differ in length, or a position is
            not finite; the pairer is unchanged.
        """
        q = joints_in_order(msg.name, msg.position, self.joint_names)
        if q is None:
            names = list(msg.name)
            missing = sorted(set(self.joint_names) - set(names))
            if missing:
                raise MessageError('names', f'/joint_states lacks joints {missing} (got {names}); ignored')
            raise MessageError('len', f'/joint_states has {len(names)} names but {len(msg.position)} '
                                      'positions; ignored')
        if not np.all(np.isfinite(q)):
            raise MessageError('nonfinite', f'/joint_states with non-finite positions {q}; ignored', once=False)
        return self.pairer.joint_state(stamp_to_seconds(msg.header.stamp), q)

    def command(self, msg: Any) -> None:
        """A trajectory_msgs/JointTrajectory: its last point is the target.

        Partial or empty commands are ignored (the simulator rejects them).
        """
        q = joints_in_order(msg.joint_names, msg.points[-1].positions, self.joint_names) if msg.points else None
        if q is not None:
            self.pairer.command(q)

    def hand_pose(self, msg: Any) -> list[ObservationResult]:
        """A geometry_msgs/PoseWithCovarianceStamped; returns the attempts it completed.

        Raises
        ------
        MessageError
            If the pose is not valid (NaN, zero quaternion).
        """
        try:
            pose = pose_msg_to_matrix(msg.pose.pose)
        except ValueError as exc:
            raise MessageError('pose', f'/hand_pose with an invalid pose rejected: {exc}', once=False) from exc
        if self.constant_noise is not None:
            R = self.constant_noise.covariance(0.0, 45.0)  # noqa: N806
        else:
            R = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)  # noqa: N806
        return self.pairer.hand_pose(stamp_to_seconds(msg.header.stamp), pose, R)

    def feed(self, topic: str, msg: Any) -> list[ObservationResult]:
        """Dispatch a message of one of the three topics by name."""
        if topic == '/joint_states':
            return self.joint_state(msg)
        if topic == '/arm/command':
            self.command(msg)
            return []
        if topic == '/hand_pose':
            return self.hand_pose(msg)
        raise ValueError(f'MessageFeeder takes /joint_states, /arm/command or /hand_pose, not {topic!r}')
