"""CalibrationLoop: every transition of the loop's state machine (pure, no rclpy)."""
import numpy as np
import pytest

import body_schema
from active_selector.loop import CalibrationLoop, LoopSettings, LoopStateError, Phase
from active_selector.planner import Planner, PlannerSettings
from body_schema.acquisition import SelectorConfig
from body_schema.noise import PoseDependentNoise
from calibration_interfaces.outcome import Outcome

ARM = body_schema.load_robot()
START = np.mean(ARM.calibration_box, axis=1)
TOL = 0.002


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def loop():
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    lp = CalibrationLoop(planner, LoopSettings(iterations=2, settle_tolerance=TOL, settle_timeout=3.0,
                                               settle_time=0.1, outcome_timeout=1.0), Clock())
    lp.joint_state(0.0, START)
    return lp


def _command(lp: CalibrationLoop) -> np.ndarray:
    target = lp.select(None, None, None)
    assert lp.phase is Phase.MOVING
    return target


def _settle(lp: CalibrationLoop, target: np.ndarray, t: float = 1.0) -> None:
    """The arm arrives at ``t`` and is still one joint state later."""
    lp.clock.t = t
    lp.joint_state(t, target + 0.5 * TOL)
    assert lp.phase is Phase.MOVING, 'arrived but still moving is not settled'
    lp.clock.t = t + 0.01
    lp.joint_state(t + 0.01, target + 0.5 * TOL)
    assert lp.phase is Phase.AWAITING_OUTCOME


def test_select_needs_a_joint_state_and_the_waiting_phase():
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random')))
    lp = CalibrationLoop(planner, LoopSettings(), Clock())
    with pytest.raises(LoopStateError, match='joint state'):
        lp.select(None, None, None)
    lp.joint_state(0.0, START)
    lp.select(None, None, None)
    assert np.array_equal(planner.start, START)                 # the first joint state is the start
    with pytest.raises(LoopStateError, match="'moving'"):
        lp.select(None, None, None)


def test_success_needs_a_seen_hand_and_a_verdict_at_the_reached_configuration(loop):
    target = _command(loop)
    assert ARM.within_limits(target)
    loop.joint_state(0.5, START)                                # still at the start
    assert loop.phase is Phase.MOVING
    _settle(loop, target)
    assert loop.markers(1.05, True) is None                     # before settle_time: not the attempt frame
    assert loop.detected is None
    assert loop.markers(1.12, True) is None                     # seen; the verdict is still to come
    assert loop.estimator_outcome('accepted', target + 0.1) is None     # another configuration
    assert loop.estimator_outcome('duplicate', target) is None          # not a final verdict
    loop.clock.t = 1.3
    it = loop.estimator_outcome('accepted', target, 'mahalanobis 1.2')
    assert it is not None and loop.phase is Phase.WAITING
    assert it.attempt.outcome == 'accepted' and it.attempt.detected and it.reason == 'mahalanobis 1.2'
    assert np.allclose(it.attempt.reached, target + 0.5 * TOL)
    assert it.move_s == pytest.approx(1.01) and it.outcome_s == pytest.approx(0.29)
    assert it.record['outcome'] == 'accepted' and it.record['discarded'] == 0
    assert it.record['move_sim_s'] == it.move_s and it.record['sim_time'] == 1.3
    assert loop.planner.occlusion.n_configs == 1


def test_each_eyes_verdict_on_the_deciding_frame_reaches_the_planner():
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4),
                                                                 occlusion_per_eye=True), eyes=('left', 'right'))
    lp = CalibrationLoop(planner, LoopSettings(iterations=4, settle_tolerance=TOL, settle_time=0.1), Clock())
    lp.joint_state(0.0, START)
    target = _command(lp)
    _settle(lp, target)
    lp.eye_verdicts(1.1, {'left': True, 'right': True})         # an earlier frame
    lp.markers(1.2, True)
    lp.eye_verdicts(1.2 + 1e-10, {'left': False, 'right': True})  # the deciding one's, after it ('%.9f' stamp)
    it = lp.estimator_outcome('accepted', target)
    assert it.record['eyes'] == {'left': False, 'right': True}
    assert planner.eye_occlusion['left'].attempts[1].tolist() == [False]
    assert planner.eye_occlusion['right'].attempts[1].tolist() == [True]
    # A failed frame whose per-eye verdicts have not arrived (the iteration ends on the frame): every eye failed.
    target = _command(lp)
    _settle(lp, target, 3.0)
    it = lp.markers(3.2, False)
    assert it.record['eyes'] is None and planner.eye_occlusion['right'].attempts[1].tolist() == [True, False]
    # The estimator's verdict first, then the frame ends the attempt, then the per-eye verdicts come
    # (after the next command, even): they still teach the eyes' models, once.
    target = _command(lp)
    _settle(lp, target, 5.0)
    assert lp.estimator_outcome('accepted', target) is None
    it = lp.markers(5.2, True)
    assert it.record['eyes'] is None and len(planner.eye_occlusion['left'].attempts[1]) == 2
    lp.joint_state(5.3, target)
    lp.eye_verdicts(5.2, {'left': True})
    lp.eye_verdicts(5.2, {'left': True})
    assert planner.eye_occlusion['left'].attempts[1].tolist() == [False, False, True]
    assert len(planner.eye_occlusion['right'].attempts[1]) == 2


def test_a_verdict_that_came_before_the_frame_still_counts(loop):
    target = _command(loop)
    _settle(loop, target)
    assert loop.estimator_outcome('rejected', target, 'gate') is None   # hand not yet seen
    it = loop.markers(1.2, True)
    assert it is not None and it.attempt.outcome == 'rejected'


def test_an_empty_frame_after_settling_fails_the_iteration(loop):
    target = _command(loop)
    _settle(loop, target)
    it = loop.markers(1.2, False)
    assert it.attempt.outcome == 'failed' and not it.attempt.detected
    assert it.record['discarded'] == 1 and loop.planner.discarded == 1
    assert loop.estimator_outcome('accepted', target) is None   # too late: the iteration is over
    assert len(loop.planner.history) == 1


def test_a_verdict_on_an_earlier_image_does_not_end_a_near_repeat():
    """UCSAL repetition 18 (docs/results/stereo-50): targets 0.1 deg apart, within twice the settle
    tolerance, so the previous attempt's verdict matched the new reached configuration and ended
    the iteration before the estimator had judged its image (and the next selection ran without
    it). A verdict counts only for an image stamped after the iteration's command."""
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    lp = CalibrationLoop(planner, LoopSettings(iterations=4, settle_tolerance=TOL, settle_time=0.1), Clock())
    lp.joint_state(0.0, START)
    planner.queue_poses([START + 0.1, START + 0.1 + 1.5 * TOL])
    first = _command(lp)
    _settle(lp, first)
    assert lp.markers(1.12, True) is None
    it = lp.estimator_outcome('accepted', first + 0.5 * TOL, 'mahalanobis 1.4', stamp=1.12)
    assert it is not None and it.attempt.outcome == 'accepted'
    lp.clock.t = 1.5
    second = _command(lp)
    assert np.max(np.abs(second - first)) < 2 * TOL                    # a near-repeat
    _settle(lp, second, t=2.0)
    assert lp.markers(2.12, True) is None, 'ended on the verdict on the image of 1.12 s'
    it = lp.estimator_outcome('outlier', second + 0.5 * TOL, 'mahalanobis 166.9', stamp=2.12)
    assert it is not None and it.attempt.outcome == 'outlier' and it.reason == 'mahalanobis 166.9'
    # Without a stamp (the ROS-free study loop) the joints alone decide, as before.
    lp.clock.t = 2.5
    third = lp.select(None, None, None)
    _settle(lp, third, t=3.0)
    lp.markers(3.12, True)
    assert lp.estimator_outcome('accepted', third + 0.5 * TOL) is not None


@pytest.mark.parametrize('watchdog', [True, False])
def test_a_target_not_reached_in_time_is_unreachable_and_the_watchdog_stops_the_run(loop, watchdog):
    loop.settings = LoopSettings(**{**loop.settings.__dict__, 'stop_on_unreachable': watchdog})
    target = _command(loop)
    deadline = loop.duration + 3.0                              # the commanded motion, then settle_timeout
    assert loop.duration > 0.5
    loop.clock.t = deadline - 0.1
    far = target.copy()
    far[3] += np.radians(10.0)
    loop.joint_state(deadline - 0.1, far)
    assert loop.tick() is None                                  # within settle_timeout
    loop.clock.t = deadline + 0.1
    it = loop.tick()
    assert it.attempt.outcome == 'unreachable'
    assert f'{ARM.joint_names[3]} is 10.00 deg away' in it.reason
    assert np.array_equal(it.attempt.reached, far) and it.outcome_s == 0.0
    assert it.move_s == pytest.approx(deadline + 0.1)
    assert loop.planner.occlusion.n_configs == 0                # an unreached pose teaches nothing
    if watchdog:
        assert loop.phase is Phase.STOPPED and loop.done and loop.stopped
        assert loop.stop_reason.startswith('watchdog: iteration 1') and 'deg away' in loop.stop_reason
    else:
        assert loop.phase is Phase.WAITING and not loop.done


def test_a_command_the_arm_never_started_on_is_sent_once_more(loop):
    loop.settings = LoopSettings(**{**loop.settings.__dict__, 'resend_after': 0.5, 'settle_timeout': 30.0})
    target = _command(loop)
    loop.clock.t = 0.4
    loop.joint_state(0.4, START)
    assert not loop.resend_due()                                # not yet: the arm may just be starting
    loop.clock.t = 0.6
    assert not loop.resend_due()                                # no joint state since the deadline
    loop.joint_state(0.6, START + 0.1 * TOL)                    # still where it was commanded from
    assert loop.resend_due()
    loop.clock.t = 2.0
    loop.joint_state(2.0, START)
    assert not loop.resend_due()                                # once per iteration: then the watchdog
    _settle(loop, target, 2.5)                                  # the second command arrived
    assert not loop.resend_due()


def test_joint_states_queued_during_a_long_selection_do_not_resend():
    # In the node the loop clock is sim time, read from /clock, which stands still while a selection
    # blocks the node; the joint states queued meanwhile (stamped up to the selection's length after
    # the stale command time) arrive at once after the command and show an arm that has had no
    # chance to move. Only a still arm seen resend_after of wall time after the command is resent.
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    wall = Clock()
    wall.t = 100.0
    lp = CalibrationLoop(planner, LoopSettings(settle_tolerance=TOL, resend_after=1.0), Clock(), wall)
    lp.joint_state(0.0, START)
    wall.t = 101.5                                              # selecting took 1.5 s: sim time went on
    lp.select(None, None, None)
    wall.t = 101.51
    lp.joint_state(1.5, START)                                  # queued before the command went out
    assert not lp.resend_due()
    wall.t = 102.6
    lp.joint_state(2.6, START)                                  # a second after the command: still there
    assert lp.resend_due()


@pytest.mark.parametrize('moved', ['started', 'at the target', 'never'])
def test_an_arm_that_moves_or_needs_no_motion_is_not_commanded_again(moved):
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    lp = CalibrationLoop(planner, LoopSettings(settle_tolerance=TOL, resend_after=0.0 if moved == 'never' else 0.5),
                         Clock())
    lp.joint_state(0.0, START)
    target = lp.select(None, None, None)
    lp.clock.t = 1.0
    q = {'started': START + 0.05 * (target - START), 'at the target': target, 'never': START}[moved]
    lp.joint_state(1.0, q)
    assert not lp.resend_due()


def test_resend_after_must_not_be_negative():
    with pytest.raises(ValueError, match='resend_after.*-1'):
        LoopSettings(resend_after=-1.0)


@pytest.mark.parametrize('scale', [1.0, 0.25])
def test_commands_are_timed_at_the_scaled_joint_speed(scale):
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    lp = CalibrationLoop(planner, LoopSettings(max_joint_speed_deg=30.0, speed_scale=scale), Clock())
    lp.joint_state(0.0, START)
    target = lp.select(None, None, None)
    assert lp.duration == pytest.approx(np.degrees(np.max(np.abs(target - START))) / (30.0 * scale))
    with pytest.raises(ValueError, match='speed_scale'):
        LoopSettings(speed_scale=0.0)


def test_joint_states_from_before_the_command_do_not_settle(loop):
    loop.clock.t = 5.0
    target = _command(loop)
    loop.joint_state(4.0, target)
    loop.joint_state(4.5, target)
    assert loop.phase is Phase.MOVING


@pytest.mark.parametrize('frame, reason', [(None, 'no /markers frame after settling'),
                                           (True, 'markers seen but no estimator update')])
def test_no_outcome_in_time_is_a_timeout(loop, frame, reason):
    target = _command(loop)
    _settle(loop, target)
    if frame is not None:
        loop.markers(1.2, frame)
    loop.clock.t = 1.9
    assert loop.tick() is None
    loop.clock.t = 2.1
    it = loop.tick()
    assert it.attempt.outcome == 'timeout' and reason in it.reason
    assert it.attempt.detected is bool(frame)
    # Without a judged frame nothing is known about visibility (main taught a failure here).
    assert loop.planner.occlusion.n_configs == (0 if frame is None else 1)


def test_bad_input_frames_decide_nothing_and_teach_the_occlusion_model_nothing(loop):
    """On main a bad frame came as an empty /markers: a failed attempt the occlusion model learnt."""
    target = _command(loop)
    _settle(loop, target)
    loop.bad_frame(1.2, 'left: image.encoding: unsupported')
    assert loop.phase is Phase.AWAITING_OUTCOME and loop.detected is None
    it = loop.markers(1.3, False)                   # the next judged frame decides
    assert it.attempt.outcome == 'failed' and loop.planner.occlusion.n_configs == 1
    target = _command(loop)
    _settle(loop, target, t=3.0)
    loop.bad_frame(3.2, 'left: camera_info.D: distortion coefficients must be finite')
    loop.bad_frame(3.3, 'left: camera_info.D: distortion coefficients must be finite')
    loop.clock.t = 4.1
    it = loop.tick()
    assert it.attempt.outcome == Outcome.BAD_INPUT and not it.attempt.detected
    assert '2 frame(s)' in it.reason and 'camera_info.D' in it.reason
    assert loop.planner.occlusion.n_configs == 1    # unchanged: bad input is not a hidden hand


def test_a_bad_frame_before_settling_or_after_the_decision_is_ignored(loop):
    target = _command(loop)
    loop.bad_frame(0.5, 'early')                    # still moving
    _settle(loop, target)
    loop.bad_frame(1.05, 'before settle_time')
    assert loop.bad_frames == 0
    loop.markers(1.2, True)
    loop.bad_frame(1.3, 'after the decision')
    assert loop.bad_frames == 0


def test_the_loop_is_done_after_its_iterations(loop):
    for i in range(2):
        target = _command(loop)
        _settle(loop, target, t=2.0 * i + 1.0)
        it = loop.markers(2.0 * i + 1.2, False)
        assert it.attempt.iteration == i + 1
    assert loop.done and loop.phase is Phase.DONE
    loop.clock.t = 100.0
    assert loop.tick() is None
    with pytest.raises(LoopStateError):
        loop.select(None, None, None)
    moved = loop.planner.history[-1].movement_deg
    assert it.record['movement_deg'] == moved > 0


@pytest.mark.parametrize('field, value', [('iterations', 0), ('settle_tolerance', 0.0),
                                          ('settle_timeout', -1.0), ('settle_time', -0.1)])
def test_settings_reject_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        LoopSettings(**{field: value})


def test_a_clock_jumping_back_keeps_the_iterations_own_verdicts():
    """A simulator reset sends the clock back (tests/test_faults.py: 1.2 s): the iteration's times
    and the stored verdicts' stamps go back with it, so a verdict on an image taken after the jump
    (stamped before the command in the old timeline) still ends the iteration, a verdict on the
    previous attempt's image still does not, and the outcome timeout keeps its length."""
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='random', seed=4)))
    lp = CalibrationLoop(planner, LoopSettings(iterations=3, settle_tolerance=TOL, settle_time=0.1,
                                               outcome_timeout=1.0), Clock())
    lp.joint_state(0.0, START)
    planner.queue_poses([START + 0.1, START + 0.1 + 1.5 * TOL])
    first = _command(lp)
    _settle(lp, first)
    assert lp.markers(1.12, True) is None
    assert lp.estimator_outcome('accepted', first + 0.5 * TOL, 'first', stamp=1.12) is not None
    lp.clock.t = 2.5
    second = _command(lp)                                        # a near repeat, commanded at 2.5 s
    _settle(lp, second, t=3.0)
    assert lp.markers(3.12, True) is None
    lp.clock.t = 1.92                                            # the jump: 1.2 s back
    lp.joint_state(1.92, second + 0.5 * TOL)
    assert lp.tick() is None, 'the outcome timeout counted across the jump'
    assert lp.estimator_outcome('accepted', second + 0.5 * TOL, 'first', stamp=1.12) is None
    it = lp.estimator_outcome('accepted', second + 0.5 * TOL, 'after the jump', stamp=2.02)
    assert it is not None and it.reason == 'after the jump'
