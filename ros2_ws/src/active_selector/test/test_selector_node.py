"""The selector node in-process, driven by probe publishers: it waits for its inputs and says
why, commands a target, and ends an iteration as failed, accepted (the estimator's verdict at
the reached configuration) or unreachable, publishing one progress record each."""
from __future__ import annotations

import json

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

import body_schema
from active_selector.selector_node import Phase, SelectorNode
from calibration_interfaces.node_util import qos_profile
from calibration_interfaces.outcome import DETECTOR_DIAGNOSTIC, FrameStatus, Outcome, encode_frame, encode_status

ARM = body_schema.load_robot()


class Probe:
    """Publishers of the selector's inputs and recorders of its outputs."""

    def __init__(self, ros, **params) -> None:
        self.ros = ros
        self.node = ros.add(SelectorNode(context=ros.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()]))
        p = ros.node('probe')
        self.commands: list[JointTrajectory] = []
        self.progress: list[dict] = []
        p.create_subscription(JointTrajectory, '/arm/command', self.commands.append, qos_profile('/arm/command'))
        p.create_subscription(String, '/calibration/progress', lambda m: self.progress.append(json.loads(m.data)),
                              qos_profile('/calibration/progress'))
        self.js = p.create_publisher(JointState, '/joint_states', 10)
        self.markers = p.create_publisher(PoseArray, '/markers', qos_profile('/markers'))
        self.status = p.create_publisher(DiagnosticStatus, '/body_schema/update_status',
                                         qos_profile('/body_schema/update_status'))
        self.cam = p.create_publisher(PoseStamped, '/camera/left/pose', qos_profile('/camera/left/pose'))
        self.diagnostics = p.create_publisher(DiagnosticArray, '/diagnostics', qos_profile('/diagnostics'))
        ros.spin_until(lambda: self.js.get_subscription_count() > 0 and self.markers.get_subscription_count() > 0
                       and self.status.get_subscription_count() > 0
                       and self.diagnostics.get_subscription_count() > 0, 10.0, 'discovery')

    def stamp(self, ahead: float = 0.0):
        t = self.node.get_clock().now().nanoseconds + int(ahead * 1e9)
        msg = JointState().header.stamp
        msg.sec, msg.nanosec = divmod(t, 10**9)
        return msg

    def joints(self, q: np.ndarray, ahead: float = 0.0) -> None:
        msg = JointState(name=list(ARM.joint_names), position=np.asarray(q).tolist())
        msg.header.stamp = self.stamp(ahead)
        self.js.publish(msg)

    def target(self) -> np.ndarray:
        """Start the arm at the box centre; the target the node then commands."""
        q0 = np.mean(ARM.calibration_box, axis=1)
        self.ros.spin_until(lambda: self.joints(q0) or self.commands, 10.0, 'a command')
        return np.array(self.commands[-1].points[-1].positions)

    def settle(self, q: np.ndarray) -> None:
        for k in range(2):
            self.joints(q, ahead=0.01 * (k + 1))
        self.ros.spin_until(lambda: self.node.phase is not Phase.MOVING, 5.0, 'settling')

    def frame(self, n_markers: int) -> None:
        msg = PoseArray(poses=[Pose() for _ in range(n_markers)])
        msg.header.stamp = self.stamp(ahead=1.0)          # well after settle_time
        self.markers.publish(msg)

    def bad_frame(self, kind: str) -> None:
        """What the detector publishes for a frame it cannot judge: no /markers, an ERROR status."""
        stamp = self.stamp(ahead=1.0)
        values = encode_frame(FrameStatus.BAD_INPUT, stamp.sec + stamp.nanosec * 1e-9, kind)
        msg = DiagnosticArray(status=[DiagnosticStatus(
            level=bytes([FrameStatus.BAD_INPUT.level]), name=DETECTOR_DIAGNOSTIC, message=f'left: {kind}: bad',
            hardware_id='left', values=[KeyValue(key=k, value=v) for k, v in values.items()])])
        msg.header.stamp = stamp
        self.diagnostics.publish(msg)

    def verdict(self, outcome: Outcome, q: np.ndarray) -> None:
        """The estimator's verdict on the attempt frame (stamped as :meth:`frame` stamps it: after the command)."""
        stamp = self.stamp(ahead=1.0)
        kv = encode_status(outcome, stamp.sec + stamp.nanosec * 1e-9, q, 1.0, 0.001,
                           {'updates': 1, 'rejected': 0, 'duplicates': 0})
        self.status.publish(DiagnosticStatus(message='mahalanobis 1.000',
                                             values=[KeyValue(key=k, value=v) for k, v in kv.items()]))


def test_waits_for_estimate_and_says_why(ros, capfd):
    probe = Probe(ros, strategy='al', wait_report_period=0.2)
    node = probe.node
    pose = PoseStamped()
    pose.header.frame_id = 'root_link'
    pose.pose.orientation.w = 1.0
    probe.cam.publish(pose)
    q = np.mean(ARM.calibration_box, axis=1)
    ros.spin_until(lambda: probe.joints(q) or node.q is not None and node.camera_pose is not None, 10.0,
                   'joints and camera pose')
    ros.spin_for(0.6)
    assert node.phase is Phase.WAITING
    assert node.waiting_for == ['/body_schema/estimate', '/body_schema/covariance']
    assert probe.commands == []
    err = capfd.readouterr().err
    assert 'waiting for /body_schema/estimate, /body_schema/covariance before selecting' in err


def test_random_waits_for_the_estimator_when_asked(ros):
    """wait_for_estimator: even the random strategy, which selects without an estimate, commands
    only once the estimator has published one (it does so on its first joint state)."""
    from std_msgs.msg import Float64MultiArray

    from calibration_interfaces.messages import table_to_msg

    probe = Probe(ros, strategy='random', seed=3, wait_for_estimator=True)
    q = np.mean(ARM.calibration_box, axis=1)
    ros.spin_until(lambda: probe.joints(q) or probe.node.q is not None, 10.0, 'joints')
    ros.spin_for(0.4)
    assert probe.node.waiting_for == ['/body_schema/estimate'] and probe.commands == []
    estimate = ros.node('estimator').create_publisher(Float64MultiArray, '/body_schema/estimate',
                                                      qos_profile('/body_schema/estimate'))
    estimate.publish(table_to_msg(ARM.dh))
    probe.target()                                          # the first command follows


def test_stereo_plans_with_both_eyes_once_both_poses_arrived(ros):
    """use_right_eye: the node waits for both eyes' poses, then plans with the pair (2, 4, 4)."""
    from std_msgs.msg import Float64MultiArray

    from body_schema.sampling import initial_covariance
    from calibration_interfaces.messages import covariance_to_msg, matrix_to_pose_msg, table_to_msg

    probe = Probe(ros, strategy='al', use_right_eye=True, n_candidates=64, refine_starts=1)
    node = probe.node
    est = ros.node('estimator')
    for name, msg in (('/body_schema/estimate', table_to_msg(ARM.dh)),
                      ('/body_schema/covariance', covariance_to_msg(initial_covariance(ARM.n_joints)))):
        est.create_publisher(Float64MultiArray, name, qos_profile(name)).publish(msg)
    right = est.create_publisher(PoseStamped, '/camera/right/pose', qos_profile('/camera/right/pose'))
    poses = {}
    for eye, pub in (('left', probe.cam), ('right', right)):
        poses[eye] = PoseStamped(pose=matrix_to_pose_msg(ARM.camera_pose(eye)))
        poses[eye].header.frame_id = 'root_link'
    probe.cam.publish(poses['left'])
    q = np.mean(ARM.calibration_box, axis=1)
    ros.spin_until(lambda: probe.joints(q) or node.q is not None and 'left' in node.camera_poses
                   and node.P is not None, 10.0, 'joints, left pose and the estimate')
    ros.spin_for(0.3)
    assert node.waiting_for == ['/camera/right/pose'] and node.camera_pose is None and probe.commands == []
    right.publish(poses['right'])
    probe.target()
    np.testing.assert_allclose(node.camera_pose, np.stack([ARM.camera_pose('left'), ARM.camera_pose('right')]),
                               atol=1e-12)


def test_stereo_is_ignored_for_a_fixed_camera(ros):
    node = ros.add(SelectorNode(context=ros.context, parameter_overrides=[
        Parameter('robot', value='ur5e'), Parameter('use_right_eye', value=True)]))
    assert node.eyes == ('left',)


def test_an_empty_frame_after_settling_fails_the_iteration(ros, tmp_path):
    probe = Probe(ros, strategy='random', iterations=2, seed=3, progress_file=str(tmp_path / 'p.jsonl'))
    target = probe.target()
    assert ARM.within_limits(target)
    probe.settle(target)
    assert probe.node.phase is Phase.AWAITING_OUTCOME
    probe.frame(0)
    ros.spin_until(lambda: probe.progress, 5.0, 'a progress record')
    [rec] = probe.progress
    assert (rec['iteration'], rec['outcome'], rec['detected']) == (1, 'failed', False)
    assert np.allclose(np.radians(rec['target_deg']), target) and rec['discarded'] == 1
    assert json.loads((tmp_path / 'p.jsonl').read_text()) == rec
    assert probe.node.phase is not Phase.DONE                 # one of two iterations
    ros.spin_until(lambda: len(probe.commands) == 2, 5.0, 'the next command')


def test_a_bad_input_frame_is_not_a_hidden_hand(ros):
    """Only bad-input frames after settling: the iteration ends bad_input and the occlusion model
    records no failure (on main the detector's empty /markers for such a frame, or the timeout
    that follows silence, taught it the hand was hidden there)."""
    probe = Probe(ros, strategy='random', iterations=2, seed=3, outcome_timeout=1.0)
    target = probe.target()
    probe.settle(target)
    probe.bad_frame('image.encoding')
    ros.spin_until(lambda: probe.node.loop.bad_frames >= 1, 5.0, 'the bad frame counted')
    assert probe.node.phase is Phase.AWAITING_OUTCOME             # waits for a judged frame
    ros.spin_until(lambda: probe.progress, 10.0, 'the iteration to end')
    [rec] = probe.progress
    assert rec['outcome'] == 'bad_input' and 'image.encoding' in rec['reason'], rec
    assert probe.node.planner.occlusion.n_configs == 0
    # The next attempt: a bad frame, then an empty judged one, which does fail.
    ros.spin_until(lambda: (probe.joints(probe.node.q), len(probe.commands) == 2)[1], 5.0, 'the next command')
    target = np.array(probe.commands[-1].points[-1].positions)
    probe.settle(target)
    probe.bad_frame('camera_info.D')
    ros.spin_until(lambda: probe.node.loop.bad_frames >= 1, 5.0, 'the bad frame counted')
    probe.frame(0)
    ros.spin_until(lambda: len(probe.progress) == 2, 5.0, 'the second record')
    assert probe.progress[1]['outcome'] == 'failed' and probe.node.planner.occlusion.n_configs == 1


def test_the_next_target_is_selected_on_the_first_joint_state_after_an_iteration(ros):
    # With its periodic step cancelled the node can only select from the joint-state callback: a
    # simulator faster than real time must not tick on idle until the next wall-clock step.
    probe = Probe(ros, strategy='random', iterations=2, seed=3)
    target = probe.target()
    for timer in probe.node.timers:
        timer.cancel()
    probe.settle(target)
    probe.frame(0)
    ros.spin_until(lambda: probe.progress, 5.0, 'the first progress record')
    assert len(probe.commands) == 1 and probe.node.phase is Phase.WAITING
    probe.joints(target, ahead=0.05)
    ros.spin_until(lambda: len(probe.commands) == 2, 5.0, 'the second command')
    assert probe.node.phase is Phase.MOVING


def test_the_verdict_at_the_reached_configuration_ends_the_last_iteration(ros):
    probe = Probe(ros, strategy='random', iterations=1, seed=4)
    target = probe.target()
    probe.settle(target)
    probe.frame(1)
    probe.verdict(Outcome.ACCEPTED, target + 0.5)             # another configuration: not this attempt
    probe.verdict(Outcome.DUPLICATE, target)                  # not a verdict that ends an iteration
    ros.spin_for(0.3)
    assert probe.progress == []
    probe.verdict(Outcome.REJECTED, target)
    ros.spin_until(lambda: probe.progress, 5.0, 'the progress record')
    assert probe.node.done
    [rec] = probe.progress
    assert (rec['outcome'], rec['detected'], rec['reason']) == ('rejected', True, 'mahalanobis 1.000')


def test_a_malformed_status_is_reported_once_and_ignored(ros, capfd):
    probe = Probe(ros, strategy='random', iterations=1, seed=5)
    target = probe.target()
    probe.settle(target)
    probe.frame(1)
    bad = DiagnosticStatus(values=[KeyValue(key='outcome', value='accepted')])   # no joints, no stamp
    for _ in range(3):
        probe.status.publish(bad)
    ros.spin_for(0.3)
    assert probe.progress == [] and probe.node.phase is Phase.AWAITING_OUTCOME
    assert capfd.readouterr().err.count('/body_schema/update_status ignored') == 1


def test_a_target_not_reached_in_time_is_unreachable_and_the_watchdog_holds_the_arm(ros):
    probe = Probe(ros, strategy='random', iterations=3, seed=6, settle_timeout=0.3)
    target = probe.target()
    first = probe.commands[-1].points[-1].time_from_start
    duration = first.sec + first.nanosec * 1e-9          # timed at the commanded speed, not 0
    assert duration > 0.1
    stuck = target.copy()
    stuck[0] = target[0] + np.radians(5.0) * (1 if target[0] < 0 else -1)
    probe.joints(stuck)
    ros.spin_until(lambda: probe.progress, 5.0 + duration, 'the timeout')
    [rec] = probe.progress
    assert rec['outcome'] == 'unreachable' and f'{ARM.joint_names[0]} is 5.00 deg away' in rec['reason']
    # The watchdog: the run stops (no further target) and the arm is held where it is.
    ros.spin_until(lambda: len(probe.commands) >= 2, 5.0, 'the hold command')
    np.testing.assert_allclose(probe.commands[-1].points[-1].positions, stuck)
    assert probe.node.done and probe.node.loop.stopped and 'watchdog' in probe.node.loop.stop_reason
    ros.spin_for(0.3)
    assert len(probe.progress) == 1 and len(probe.commands) == 2


def test_a_command_the_arm_never_started_on_is_sent_once_more(ros, capfd):
    # As when the arm driver matched /arm/command after the first command went out: it never moves.
    probe = Probe(ros, strategy='random', iterations=3, seed=6, resend_after=0.3, settle_timeout=30.0)
    target = probe.target()
    q0 = np.mean(ARM.calibration_box, axis=1)
    ros.spin_until(lambda: probe.joints(q0, ahead=0.4) or len(probe.commands) >= 2, 5.0, 'the command again')
    np.testing.assert_allclose(probe.commands[1].points[-1].positions, target)
    assert 'sending it again' in capfd.readouterr().err
    probe.joints(q0, ahead=1.0)
    ros.spin_for(0.3)
    assert len(probe.commands) == 2                       # once: a second silence is the watchdog's
    probe.settle(target)                                  # the arm goes; the iteration carries on
    assert probe.node.phase is Phase.AWAITING_OUTCOME


def test_joint_states_stamped_late_but_arriving_at_once_are_not_a_lost_command(ros, capfd):
    # As the joint states queued while a selection blocked the node: stamped past resend_after (on
    # the clock that stood still meanwhile), they arrive right after the command.
    probe = Probe(ros, strategy='random', iterations=3, seed=6, resend_after=2.0, settle_timeout=30.0)
    probe.target()
    q0 = np.mean(ARM.calibration_box, axis=1)
    probe.joints(q0, ahead=2.5)
    ros.spin_for(0.3)
    assert len(probe.commands) == 1 and 'sending it again' not in capfd.readouterr().err


@pytest.mark.parametrize('name, value', [('strategy', 'best'), ('noise_model', 'pdn'), ('eye', 'middle')])
def test_bad_choices_are_refused_by_name(ros, name, value):
    with pytest.raises(ValueError, match=value):
        SelectorNode(context=ros.context, parameter_overrides=[Parameter(name, value=value)])


def _record(i: int, q_deg: list[float], outcome: str, detected: bool, movement: float) -> dict:
    return {'iteration': i, 'strategy': 'random', 'outcome': outcome, 'detected': detected, 'reason': '',
            'target_deg': q_deg, 'reached_deg': q_deg, 'movement_deg': movement, 'selection_s': 0.1,
            'discarded': 0, 'move_sim_s': 1.0, 'outcome_sim_s': 0.5, 'sim_time': float(i)}


def test_resume_continues_the_recorded_iterations_and_the_occlusion_model(ros, tmp_path) -> None:
    """run_calibration.sh --resume: the selector's record is its state (count, movement, attempts)."""
    centre = np.degrees(np.mean(ARM.calibration_box, axis=1))
    records = [_record(1, (centre + 5).tolist(), 'accepted', True, 40.0),
               _record(2, (centre - 5).tolist(), 'failed', False, 75.0)]
    progress = tmp_path / 'progress.jsonl'
    progress.write_text(''.join(json.dumps(r) + '\n' for r in records) + '{"iteration": 3, "strat')   # torn line
    node = ros.add(SelectorNode(context=ros.context, parameter_overrides=[
        Parameter('strategy', value='random'), Parameter('iterations', value=4),
        Parameter('progress_file', value=str(progress)), Parameter('resume', value=True)]))
    assert node.loop.iteration == 2 and not node.done
    assert node.planner.movement_deg == 75.0 and node.planner.discarded == 1
    q, seen = node.planner.occlusion.attempts
    np.testing.assert_allclose(np.degrees(q), [centre + 5, centre - 5], atol=1e-9)
    assert seen.tolist() == [True, False]
    assert [json.loads(ln) for ln in progress.read_text().splitlines()] == records   # torn line dropped

    fresh = ros.add(SelectorNode(context=ros.context, parameter_overrides=[
        Parameter('progress_file', value=str(progress)), Parameter('iterations', value=4)]))
    assert fresh.loop.iteration == 0 and progress.read_text() == ''       # without resume: a new run


def test_resume_of_a_finished_run_is_refused(ros, tmp_path) -> None:
    progress = tmp_path / 'progress.jsonl'
    centre = np.degrees(np.mean(ARM.calibration_box, axis=1)).tolist()
    progress.write_text(json.dumps(_record(1, centre, 'accepted', True, 10.0)) + '\n')
    with pytest.raises(ValueError, match='1 iterations already'):
        SelectorNode(context=ros.context, parameter_overrides=[
            Parameter('iterations', value=1), Parameter('progress_file', value=str(progress)),
            Parameter('resume', value=True)])
