"""The calibration loop as a pure state machine: select, command, settle, outcome, record (no rclpy).

One iteration (docs/architecture.md, "The loop"): in :attr:`Phase.WAITING` the caller asks
:meth:`CalibrationLoop.select` for the next target and commands it (:attr:`Phase.MOVING`); joint
states (:meth:`~CalibrationLoop.joint_state`) show when the arm has settled at the target
(:attr:`Phase.AWAITING_OUTCOME`); the first marker frame stamped ``settle_time`` after settling
(:meth:`~CalibrationLoop.markers`) decides whether the hand was seen (not seen: outcome
``failed``); a frame the detector could not judge (:meth:`~CalibrationLoop.bad_frame`: bad image
or camera_info) decides nothing, the loop waits for the next one, and if only such frames come
before the timeout the iteration ends ``bad_input``, which does not teach the occlusion model;
each eye's own verdict on that frame (:meth:`~CalibrationLoop.eye_verdicts`, from the detector's
diagnostics) goes with it to the planner's per-eye occlusion models;
if the hand was seen, the estimator's verdict for this configuration
(:meth:`~CalibrationLoop.estimator_outcome`: ``accepted``, ``outlier`` or ``rejected``, on an
image taken after the iteration's command) ends the iteration.
:meth:`~CalibrationLoop.tick` ends a stuck one: ``unreachable`` when the target is not reached
within ``settle_timeout``, ``timeout`` when no outcome follows within ``outcome_timeout``. Every
ended iteration goes to the :class:`~active_selector.planner.Planner` (occlusion model, movement)
and comes back as an :class:`Iteration`; after ``iterations`` of them the loop is
:attr:`Phase.DONE`.

Time comes from an injected clock (sim seconds in the node; a counter in the study harness and
the tests); joint-state and marker times are the messages' stamps on the same clock.
"""
from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration_interfaces.outcome import Outcome
from calibration_interfaces.parameters import setting

from body_schema.acquisition import Selection

from .planner import Attempt, Planner

__all__ = ['Phase', 'LoopSettings', 'Iteration', 'LoopStateError', 'CalibrationLoop']


def _same_stamp(a: float, b: float) -> bool:
    """Whether two stamps [s] name one frame: they come through different messages (a header, a
    '%.9f' string), so equal to a microsecond rather than bit for bit."""
    return abs(a - b) < 1e-6


class Phase(enum.Enum):
    WAITING = 'waiting for inputs'
    MOVING = 'moving'
    AWAITING_OUTCOME = 'awaiting outcome'
    DONE = 'done'
    STOPPED = 'stopped by the watchdog'


class LoopStateError(RuntimeError):
    """A loop method called in a phase where it makes no sense (names the phase)."""


@dataclass(frozen=True)
class LoopSettings:
    """When the arm counts as arrived and how long each phase may take.

    Attributes
    ----------
    iterations : int
        Iterations (measurement attempts) of the run.
    settle_tolerance : float
        Max joint error counted as arrived [rad]; the arm also must have moved less than a tenth
        of it since the previous joint state. An estimator outcome matches the reached
        configuration within twice this.
    settle_timeout : float
        Seconds (loop clock) beyond the commanded motion's duration to reach a target before the
        iteration is ``unreachable``.
    settle_time : float
        Seconds the arm rests before the attempt's marker frame (match the estimator's
        ``static_window``).
    outcome_timeout : float
        Seconds after settling to get an outcome before the iteration is ``timeout``.
    max_joint_speed_deg : float
        The robot's joint speed limit [deg/s]: a command's ``time_from_start`` is the largest
        joint move at ``speed_scale`` times this.
    speed_scale : float
        Fraction of ``max_joint_speed_deg`` the commanded motions use (0, 1].
    stop_on_unreachable : bool
        The watchdog: a target not reached in time stops the run (phase STOPPED; the node holds
        the arm where it is and exits non-zero) instead of going on with the next one.
    resend_after : float
        Seconds after a command with the arm still where it was before the command is sent once
        more (:meth:`CalibrationLoop.resend_due`): a command lost to late discovery or a dropped
        connection, not a slow arm (an arm that has started moving is never re-commanded). Counted
        on both clocks: the still joint state must be stamped this long after the command and have
        arrived this long after it on the wall clock. 0 never re-sends.
    """

    iterations: int = setting(50, 'Iterations (measurement attempts) of the run', (1, 100000))
    settle_tolerance: float = setting(0.002, 'Max joint error counted as arrived [rad]', (1e-6, 0.5))
    settle_timeout: float = setting(30.0, 'Seconds (sim) beyond the commanded duration to reach a target before '
                                    'giving up', (0.1, 1e4))
    settle_time: float = setting(0.1, "Seconds (sim) the arm rests before the attempt image (match the "
                                 "estimator's static_window)", (0.0, 10.0))
    outcome_timeout: float = setting(5.0, 'Seconds (sim) after settling to get an outcome', (0.1, 1e4))
    max_joint_speed_deg: float = setting(30.0, "The robot's joint speed limit [deg/s] commands are timed with "
                                         "(the simulator's max_joint_speed_deg)", (0.1, 3600.0))
    speed_scale: float = setting(1.0, 'Fraction of max_joint_speed_deg the commanded motions use', (0.001, 1.0))
    stop_on_unreachable: bool = setting(True, 'Watchdog: a target not reached within settle_timeout beyond the '
                                              'commanded duration stops the run (the arm is held where it is, the '
                                              'node exits with status 3) instead of going on')
    resend_after: float = setting(1.0, 'Seconds (sim and wall) after a command with the arm not yet moving before the '
                                  'command is sent once more (a lost command); 0 never re-sends', (0.0, 1e4))

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f'iterations must be >= 1, got {self.iterations}')
        for name in ('settle_tolerance', 'settle_timeout', 'outcome_timeout'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        if self.settle_time < 0:
            raise ValueError(f'settle_time must be >= 0, got {self.settle_time}')
        if not self.resend_after >= 0:
            raise ValueError(f'resend_after must be >= 0, got {self.resend_after}')
        if not 0 < self.speed_scale <= 1:
            raise ValueError(f'speed_scale must be in (0, 1], got {self.speed_scale}')
        if not self.max_joint_speed_deg > 0:
            raise ValueError(f'max_joint_speed_deg must be > 0, got {self.max_joint_speed_deg}')

    @property
    def speed(self) -> float:
        """The commanded joint speed [rad/s]."""
        return float(np.radians(self.max_joint_speed_deg) * self.speed_scale)


@dataclass(frozen=True)
class Iteration:
    """One ended iteration.

    Attributes
    ----------
    attempt : Attempt
        What the planner recorded (target, reached configuration, outcome, movement).
    reason : str
        Why it ended this way, for the log.
    move_s : float
        Loop-clock seconds from the command to settling (to the end if it never settled).
    outcome_s : float
        Seconds from settling to the outcome (0 if it never settled).
    time : float
        Loop-clock time at the end.
    record : dict
        The progress record (JSON-ready) the node publishes on ``/calibration/progress``.
    """

    attempt: Attempt
    reason: str
    move_s: float
    outcome_s: float
    time: float
    record: dict[str, Any]


class CalibrationLoop:
    """Phase, target and timing of the calibration loop around a :class:`Planner`.

    Parameters
    ----------
    planner : Planner
        Selects targets and records attempts; ``planner.start`` is set from the first joint
        state if unset.
    settings : LoopSettings
    clock : callable
        Current time [s] on the clock of the joint-state and marker stamps.
    wall_clock : callable, optional
        Current wall (steady) time [s], read when a command goes out and when a joint state
        arrives; None reads ``clock``. In the node ``clock`` is sim time, which stands still while a
        selection blocks the node: the joint states queued meanwhile arrive at once after the
        command, stamped up to the selection's length after the stale command time, and must not
        count as an arm that ignored it.
    """

    def __init__(self, planner: Planner, settings: LoopSettings, clock: Callable[[], float],
                 wall_clock: Callable[[], float] | None = None) -> None:
        self.planner = planner
        self.settings = settings
        self.clock = clock
        self.wall_clock = clock if wall_clock is None else wall_clock
        self.phase = Phase.WAITING
        self.q: NDArray[np.float64] | None = None
        self.q_prev: NDArray[np.float64] | None = None
        self.q_time = 0.0
        self.q_wall = 0.0                   # when the last joint state arrived (wall clock)
        self.target: NDArray[np.float64] | None = None
        self.reached: NDArray[np.float64] | None = None
        self.selection_seconds = 0.0
        self.selection: Selection | None = None
        #: Seconds the commanded motion takes at the commanded speed (its ``time_from_start``).
        self.duration = 0.0
        self.stop_reason = ''
        self.t_command = 0.0
        self.w_command = 0.0                # when the command went out (wall clock)
        self.q_command: NDArray[np.float64] | None = None   # where the arm was when commanded
        self.resent = False
        self.t_settled = 0.0
        self.detected: bool | None = None
        self.frame_stamp: float | None = None   # the frame that decided ``detected`` ...
        self.frame_eyes: dict[str, bool] | None = None   # ... and each eye's verdict on it, once known
        self.bad_frames = 0                 # frames after settling the detector could not judge
        self.bad_reason = ''
        # Recent estimator verdicts (outcome, joints, message, image stamp or None): a verdict may
        # come before the frame.
        self._outcomes: deque[tuple[Outcome, NDArray[np.float64], str, float | None]] = deque(maxlen=50)
        # Recent frames' per-eye verdicts (stamp, {eye: seen}): they may come before or after the frame.
        self._eye_verdicts: deque[tuple[float, dict[str, bool]]] = deque(maxlen=50)
        # A seen attempt recorded before its frame's per-eye verdicts came (stamp, reached joints).
        self._late: tuple[float, NDArray[np.float64]] | None = None
        self._last_now = -np.inf            # the last clock reading (a jump back re-bases the times)

    @property
    def done(self) -> bool:
        """Finished, or stopped by the watchdog."""
        return self.phase in (Phase.DONE, Phase.STOPPED)

    @property
    def stopped(self) -> bool:
        """Stopped by the watchdog (a target not reached in time)."""
        return self.phase is Phase.STOPPED

    @property
    def iteration(self) -> int:
        """Iterations ended so far."""
        return len(self.planner.history)

    # ------------------------------------------------------------------------------ inputs

    def joint_state(self, t: float, q: ArrayLike) -> None:
        """Joint positions ``q`` (L,) [rad] stamped ``t``; may settle a move."""
        self._now()
        self.q_prev, self.q, self.q_time = self.q, np.asarray(q, dtype=float), float(t)
        self.q_wall = self.wall_clock()
        if self.phase is Phase.MOVING:
            self._check_settled()

    def select(self, dh: ArrayLike | None, P: ArrayLike | None,  # noqa: N803
               camera_pose: ArrayLike | None) -> NDArray[np.float64]:
        """Select the next target (L,) [rad, within the limits] and enter :attr:`Phase.MOVING`.

        The caller commands the returned target. ``dh`` (L, 4), ``P`` (4L, 4L) and
        ``camera_pose`` (4, 4) may be None for the random strategy.

        Raises
        ------
        LoopStateError
            If the loop is not :attr:`Phase.WAITING` or no joint state has arrived yet.
        """
        if self.phase is not Phase.WAITING:
            raise LoopStateError(f'select() needs phase {Phase.WAITING.value!r}, the loop is {self.phase.value!r}')
        if self.q is None:
            raise LoopStateError('select() needs a joint state first (the start of the movement)')
        if self.planner.start is None:
            self.planner.start = self.q.copy()
        model = self.planner.model
        sel = self.planner.select(dh, P, camera_pose)
        self.selection = sel
        self.target = np.clip(sel.theta, model.limits[:, 0], model.limits[:, 1])
        self.selection_seconds = sel.seconds
        self.duration = float(np.max(np.abs(self.target - self.q))) / self.settings.speed
        self.phase = Phase.MOVING
        self.t_command, self.w_command = self._now(), self.wall_clock()
        self.q_command, self.resent = self.q.copy(), False
        self.detected = self.frame_stamp = self.frame_eyes = None
        self.bad_frames, self.bad_reason = 0, ''
        self._check_settled()
        return self.target

    def markers(self, t: float, detected: bool) -> Iteration | None:
        """A marker frame stamped ``t``: ``detected`` if it holds the hand.

        Only the first frame at least ``settle_time`` after settling counts; an empty one ends
        the iteration as ``failed``.
        """
        self._now()
        if self.phase is Phase.AWAITING_OUTCOME and self.detected is None \
                and t >= self.t_settled + self.settings.settle_time:
            self.detected = bool(detected)
            self.frame_stamp = float(t)
            self.frame_eyes = next((e for te, e in reversed(self._eye_verdicts) if self._same_frame(te)), None)
            if not self.detected:
                return self._finish(Outcome.FAILED, 'no marker detected after settling')
            return self._match_outcome()
        return None

    def eye_verdicts(self, t: float, eyes: dict[str, bool]) -> None:
        """Whether each eye saw the hand in the frame stamped ``t`` (an eye not named was not
        judged); the planner's per-eye occlusion models learn them with the attempt that frame decides."""
        eyes = {str(k): bool(v) for k, v in eyes.items()}
        if self._late is not None and _same_stamp(t, self._late[0]):
            self.planner.learn_eyes(self._late[1], eyes)     # the attempt ended on its frame and verdict
            self._late = None
        elif self._same_frame(t):
            self.frame_eyes = eyes              # after the frame that decided the attempt
        else:
            self._eye_verdicts.append((float(t), eyes))      # perhaps before the frame

    def _same_frame(self, t: float) -> bool:
        """Whether ``t`` stamps the frame that decided the attempt."""
        return self.frame_stamp is not None and _same_stamp(t, self.frame_stamp)

    def bad_frame(self, t: float, reason: str) -> bool:
        """A frame stamped ``t`` the detector could not judge (``reason``): not evidence either way.

        Counted (returns True) when it is one the iteration waits for; the next judged frame
        decides instead.
        """
        self._now()
        if self.phase is Phase.AWAITING_OUTCOME and self.detected is None \
                and t >= self.t_settled + self.settings.settle_time:
            self.bad_frames += 1
            self.bad_reason = reason
            return True
        return False

    def estimator_outcome(self, outcome: Outcome | str, joints: ArrayLike, message: str = '',
                          stamp: float | None = None) -> Iteration | None:
        """The estimator's verdict on an observation at configuration ``joints`` (L,) [rad] of the
        image stamped ``stamp`` [s, loop clock] (None: not known).

        It ends the iteration when the filter evaluated the observation (accepted, outlier,
        rejected; others, e.g. duplicate, leave the iteration to its timeout), the hand was seen,
        ``joints`` is the reached configuration (within twice the settle tolerance) and the image
        was taken after the iteration's command. Without the stamp a verdict on the previous
        attempt's image matches a target closer than that to the previous one (UCSAL's near
        repeats): the iteration would end before its own image is judged, with the previous
        verdict, and the next selection would not have its observation.

        Raises
        ------
        ValueError
            If ``outcome`` is not an :class:`~calibration_interfaces.outcome.Outcome` value.
        """
        self._now()                         # a jump back re-bases the stored stamps, not this one
        self._outcomes.append((Outcome(outcome), np.asarray(joints, dtype=float).ravel(), message,
                               None if stamp is None else float(stamp)))
        if self.phase is Phase.AWAITING_OUTCOME and self.detected:
            return self._match_outcome()
        return None

    def resend_due(self) -> bool:
        """Whether to send the current command once more (call periodically while moving).

        True once per iteration, when a joint state stamped ``resend_after`` seconds after the command,
        and arrived that long after it on the wall clock, shows the arm still within
        ``settle_tolerance`` of where it was commanded from, and the target is elsewhere: the
        command was most likely never delivered (a subscriber discovered late misses a command
        published before it matched). The caller publishes ``target`` with ``duration`` again; the
        watchdog's deadline is unchanged.
        """
        s = self.settings
        if (self.phase is not Phase.MOVING or self.resent or s.resend_after <= 0 or self.q_command is None
                or self.q is None or self.q_time < self.t_command + s.resend_after
                or self.q_wall < self.w_command + s.resend_after):
            return False
        tol = s.settle_tolerance
        if np.max(np.abs(self.q - self.q_command)) > tol or np.max(np.abs(self.q - self.target)) <= tol:
            return False
        self.resent = True
        return True

    def tick(self) -> Iteration | None:
        """Enforce the timeouts (call periodically)."""
        s = self.settings
        if self.phase is Phase.MOVING and self._now() - self.t_command > self.duration + s.settle_timeout:
            err = np.abs(self.q - self.target)
            j = int(np.argmax(err))
            it = self._finish(Outcome.UNREACHABLE, f'target not reached within {self.duration + s.settle_timeout:.1f} s '
                              f'({self.duration:.1f} s commanded): {self.planner.model.joint_names[j]} is '
                              f'{np.degrees(err[j]):.2f} deg away')
            if s.stop_on_unreachable:
                self.phase = Phase.STOPPED
                self.stop_reason = f'watchdog: iteration {it.attempt.iteration}: {it.reason}'
            return it
        if self.phase is Phase.AWAITING_OUTCOME and self._now() - self.t_settled > s.outcome_timeout:
            if self.detected is None and self.bad_frames:
                return self._finish(Outcome.BAD_INPUT, f'{self.bad_frames} frame(s) after settling were bad '
                                    f'input, none judged (last: {self.bad_reason})')
            why = ('no /markers frame after settling' if self.detected is None
                   else 'markers seen but no estimator update for this configuration')
            return self._finish(Outcome.TIMEOUT, why)
        return None

    # ------------------------------------------------------------------------------ transitions

    def _now(self) -> float:
        """The clock; if it went back since the last reading (a simulator reset), the iteration's
        times and the stored verdicts' image stamps go back with it, so that the images taken after
        the jump still count as taken after the command (and timeouts keep their meaning)."""
        now = self.clock()
        if now < self._last_now:
            self._rebase(self._last_now - now)
        self._last_now = now
        return now

    def _rebase(self, back: float) -> None:
        """Move the iteration's times and the stored verdicts' stamps ``back`` seconds earlier."""
        self.t_command -= back
        self.t_settled -= back
        self._outcomes = deque(((o, q, m, None if st is None else st - back) for o, q, m, st in self._outcomes),
                               maxlen=self._outcomes.maxlen)

    def _check_settled(self) -> None:
        if self.q is None or self.q_prev is None or self.q_time < self.t_command:
            return
        tol = self.settings.settle_tolerance
        if np.max(np.abs(self.q - self.target)) <= tol and np.max(np.abs(self.q - self.q_prev)) <= tol * 0.1:
            self.phase = Phase.AWAITING_OUTCOME
            self.t_settled = self.q_time
            self.reached = self.q.copy()

    def _match_outcome(self) -> Iteration | None:
        for outcome, q, message, stamp in reversed(self._outcomes):
            if not outcome.updated or (stamp is not None and stamp < self.t_command):
                continue                    # not a verdict, or one on an image from before this move
            if q.shape == self.reached.shape and \
                    np.max(np.abs(q - self.reached)) <= 2 * self.settings.settle_tolerance:
                return self._finish(outcome, message)
        return None

    def _finish(self, outcome: Outcome, why: str) -> Iteration:
        now = self._now()
        settled = self.phase is Phase.AWAITING_OUTCOME
        reached = self.reached if settled else self.q.copy()
        sel = self.selection
        source = '' if sel is None else ('pose_list' if sel.optimizer.startswith('pose_list') else sel.optimizer)
        eyes = self.frame_eyes
        late = self.detected and eyes is None and outcome.informs_visibility
        self._late = (self.frame_stamp, reached) if late else None
        a = self.planner.record(self.target, reached, outcome, self.detected, self.selection_seconds,
                                0 if sel is None else sel.refused, 0 if sel is None else sel.refused_paths, source,
                                eyes)
        move_s = (self.t_settled if settled else now) - self.t_command
        outcome_s = now - self.t_settled if settled else 0.0
        record = {'iteration': a.iteration, 'strategy': self.planner.strategy.value, 'outcome': outcome.value,
                  'detected': a.detected, 'reason': why, 'target_deg': np.degrees(a.target).tolist(),
                  'reached_deg': np.degrees(a.reached).tolist(), 'movement_deg': a.movement_deg,
                  'selection_s': a.selection_seconds, 'discarded': self.planner.discarded,
                  'move_sim_s': move_s, 'outcome_sim_s': outcome_s, 'sim_time': now,
                  'source': source, 'collision_check': self.planner.safety is not None,
                  'refused': a.refused, 'refused_paths': a.refused_paths,
                  'safety_s': 0.0 if sel is None else sel.safety_seconds, 'command_s': self.duration,
                  'eyes': eyes}
        self.phase = Phase.DONE if a.iteration >= self.settings.iterations else Phase.WAITING
        return Iteration(a, why, move_s, outcome_s, now, record)
