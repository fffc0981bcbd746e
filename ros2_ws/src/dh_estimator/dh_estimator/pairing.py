"""Pairs hand-pose observations with joint states and turns them into EKF updates (no rclpy).

The estimator node and the offline evaluation (:mod:`dh_estimator.evaluate`) both feed their
messages (live rclpy messages, or objects decoded from a bag: same field names) through
:class:`MessageFeeder` into :class:`ObservationPairer`, so a bag re-run makes exactly the decisions
the online node made: which image counts as a measurement attempt (the arm rests at the commanded
target), which joint state belongs to it (interpolated at the image stamp) and what the filter
did with it.

Time is judged on the receiver's clock (``now``: the node's clock online, the recorder's log time
offline): a stamp further ahead of it than ``clock_tolerance`` is refused and counted, and a
clock that steps back restarts the joint buffer (:class:`~dh_estimator.joint_buffer.JointStateBuffer`).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
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
from .joint_buffer import JointStateBuffer, StampInFuture, StampOutOfRange

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
    clock_tolerance : float
        How far a stamp may lead the receiver's clock before the message is refused, and how
        far that clock may step back before the joint buffer restarts [s].
    max_pending : int
        Observations kept while waiting for the joint states that cover their stamp.
    """

    static_window: float = setting(0.1, 'The arm must be still this long before the image stamp [s]', (0.0, 5.0))
    static_tol: float = setting(1e-4, 'Joint motion tolerated as still [rad]', (0.0, 0.1), name='static_tolerance')
    require_command: bool = setting(True, 'Only use observations taken at the latest /arm/command target')
    target_tol: float = setting(0.005, 'Max joint distance from the commanded target [rad]', (0.0, 0.5),
                                name='target_tolerance')
    clock_tolerance: float = setting(1.0, 'A stamp further ahead of the node clock is refused; a clock step back '
                                          'beyond it restarts the joint buffer [s]', (0.0, 3600.0))
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

    Attributes
    ----------
    counters : dict of str to int
        Time faults met: ``future_joint_states`` and ``future_hand_poses`` (refused, stamped
        beyond the tolerance ahead of the clock), ``clock_resets`` (the clock stepped back)
        and ``pending_dropped`` (images that never got their joint states).
    """

    def __init__(self, estimator: OnlineEstimator, settings: PairingSettings = PairingSettings()) -> None:
        self.estimator = estimator
        self.settings = settings
        self.buffer = JointStateBuffer(estimator.model.n_joints, future_tolerance=settings.clock_tolerance)
        self.target: NDArray[np.float64] | None = None
        self._pending: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
        self.counters = dict.fromkeys(('future_joint_states', 'future_hand_poses', 'clock_resets',
                                       'pending_dropped'), 0)

    def command(self, target: ArrayLike) -> None:
        """The latest commanded joint target, shape (L,) [rad]."""
        self.target = np.asarray(target, dtype=float).copy()

    def joint_state(self, t: float, q: ArrayLike, now: float | None = None) -> list[ObservationResult]:
        """Add joint positions ``q`` (L,) at time ``t`` [s]; returns attempts it completed.

        ``now`` is the receiver's clock [s] (None: stamps are not checked against time).

        Raises
        ------
        StampInFuture
            If ``t`` leads ``now`` by more than ``clock_tolerance``; counted, the buffer is unchanged.
        """
        done = self._clock(now)
        try:
            self.buffer.add(t, q, now)
        except StampInFuture:
            self.counters['future_joint_states'] += 1
            raise
        return done + self._process() if self._pending else done

    def hand_pose(self, t: float, pose: ArrayLike, R: ArrayLike,  # noqa: N803
                  now: float | None = None) -> list[ObservationResult]:
        """Add a hand pose (4, 4) in the root frame with covariance ``R`` (6, 6) at image stamp ``t``.

        Returns the attempts this completed (none while the joint states of ``t`` are not in).

        Raises
        ------
        StampInFuture
            If ``t`` leads ``now`` by more than ``clock_tolerance`` (it would wait for joint
            states that do not come); counted, nothing is kept.
        """
        done = self._clock(now)
        t = float(t)
        if now is not None and t > now + self.settings.clock_tolerance:
            self.counters['future_hand_poses'] += 1
            raise StampInFuture(f'stamp {t:.3f} s is {t - now:.3f} s ahead of the clock ({now:.3f} s; '
                                f'tolerance {self.settings.clock_tolerance:g} s)')
        self._pending.append((t, np.asarray(pose, dtype=float), np.asarray(R, dtype=float)))
        return done + self._process()

    def _clock(self, now: float | None) -> list[ObservationResult]:
        """Read the clock; after a step back, the pending images of the old timeline are dropped."""
        if now is None or not self.buffer.observe_clock(now):
            return []
        self.counters['clock_resets'] += 1
        dropped, self._pending = self._pending, []
        return self._dropped(dropped, f'the clock stepped back to {now:.3f} s; joint states restarted')

    def _dropped(self, items: list[tuple[float, Any, Any]], why: str) -> list[ObservationResult]:
        self.counters['pending_dropped'] += len(items)
        return [ObservationResult(t, None, Outcome.DROPPED, why) for t, _, _ in items]

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
        n = len(keep) - self.settings.max_pending
        if n > 0:                                    # the oldest waited longest: they go first
            done += self._dropped(keep[:n], f'no joint state covered it while {self.settings.max_pending} '
                                            'newer images arrived')
        self._pending = keep[max(n, 0):]
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
        message = 'same configuration as the previous attempt' if outcome is Outcome.DUPLICATE \
            else self.estimator.describe_last()
        return ObservationResult(t, q, outcome, message, time.perf_counter() - t0)


class MessageError(ValueError):
    """A message the pairer cannot use.

    Attributes
    ----------
    key : str
        What is wrong, for grouping repeats (a node warns once per key when ``once``).
    once : bool
        A property of the stream (warn once) rather than of this message (warn each time).
    throttled : bool
        Possibly many in a row (a clock fault): warn at a limited rate; the text carries the count.
    """

    def __init__(self, key: str, text: str, once: bool = True, throttled: bool = False) -> None:
        super().__init__(text)
        self.key, self.once, self.throttled = key, once and not throttled, throttled


class MessageFeeder:
    """Feeds ``/joint_states``, ``/arm/command`` and ``/hand_pose`` messages to a pairer.

    Parameters
    ----------
    pairer : ObservationPairer
    joint_names : sequence of str
        The estimated joints, in the estimator's order.
    constant_noise : ConstantNoise, optional
        Use its covariance (the paper's CN baseline) instead of the one in ``/hand_pose``.
    covariance_of : callable, optional
        ``R = covariance_of(pose)`` (4, 4) -> (6, 6) instead of the one in ``/hand_pose``: another
        noise law applied at each observed hand pose, as the detector would have.
    """

    def __init__(self, pairer: ObservationPairer, joint_names: Sequence[str],
                 constant_noise: ConstantNoise | None = None,
                 covariance_of: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None) -> None:
        self.pairer = pairer
        self.joint_names = list(joint_names)
        self.constant_noise = constant_noise
        self.covariance_of = covariance_of

    def _future(self, topic: str, counter: str, exc: StampInFuture) -> MessageError:
        return MessageError(counter, f'{topic} {exc}; ignored ({self.pairer.counters[counter]} so far)',
                            throttled=True)

    def joint_state(self, msg: Any, now: float | None = None) -> list[ObservationResult]:
        """A sensor_msgs/JointState received at clock time ``now`` [s]; returns the attempts it completed.

        Raises
        ------
        MessageError
            If joints are missing, names and positions differ in length, a position is not
            finite, or the stamp is too far ahead of ``now``; the pairer is unchanged.
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
        try:
            return self.pairer.joint_state(stamp_to_seconds(msg.header.stamp), q, now)
        except StampInFuture as exc:
            raise self._future('/joint_states', 'future_joint_states', exc) from exc

    def command(self, msg: Any) -> None:
        """A trajectory_msgs/JointTrajectory: its last point is the target.

        Partial or empty commands are ignored (the simulator rejects them).
        """
        q = joints_in_order(msg.joint_names, msg.points[-1].positions, self.joint_names) if msg.points else None
        if q is not None:
            self.pairer.command(q)

    def hand_pose(self, msg: Any, now: float | None = None) -> list[ObservationResult]:
        """A geometry_msgs/PoseWithCovarianceStamped received at ``now`` [s]; returns the attempts it completed.

        Raises
        ------
        MessageError
            If the pose is not valid (NaN, zero quaternion) or its stamp too far ahead of ``now``.
        """
        try:
            pose = pose_msg_to_matrix(msg.pose.pose)
        except ValueError as exc:
            raise MessageError('pose', f'/hand_pose with an invalid pose rejected: {exc}', once=False) from exc
        if self.constant_noise is not None:
            R = self.constant_noise.covariance(0.0, 45.0)  # noqa: N806
        elif self.covariance_of is not None:
            R = np.asarray(self.covariance_of(pose), dtype=float)  # noqa: N806
        else:
            R = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)  # noqa: N806
        try:
            return self.pairer.hand_pose(stamp_to_seconds(msg.header.stamp), pose, R, now)
        except StampInFuture as exc:
            raise self._future('/hand_pose', 'future_hand_poses', exc) from exc

    def feed(self, topic: str, msg: Any, now: float | None = None) -> list[ObservationResult]:
        """Dispatch a message of one of the three topics by name; ``now``: the receiver's clock [s]."""
        if topic == '/joint_states':
            return self.joint_state(msg, now)
        if topic == '/arm/command':
            self.command(msg)
            return []
        if topic == '/hand_pose':
            return self.hand_pose(msg, now)
        raise ValueError(f'MessageFeeder takes /joint_states, /arm/command or /hand_pose, not {topic!r}')
