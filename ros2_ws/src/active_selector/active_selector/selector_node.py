"""active_selector node: chooses where the arm goes next and drives the calibration loop.

One iteration (docs/architecture.md, "The loop"; the state machine is
:class:`active_selector.loop.CalibrationLoop`): select a target with the strategy, command it, wait
until ``/joint_states`` shows the arm settled there (or give up: ``unreachable``), take the
attempt's outcome (``failed``: the first ``/markers`` frame captured after settling is empty;
otherwise the estimator's verdict at this configuration on ``/body_schema/update_status``, or
``timeout``), feed the occlusion model, account the movement. The next selection starts on the
first joint state after an iteration ends; a 20 Hz wall-clock step reports missing inputs and
enforces the timeouts. After ``iterations`` iterations it logs a summary and the process exits
with status 0. Safety (docs/real_robot_arm.md): no target inside the description's
collision margins nor behind one (``collision_check``; refusals are counted in each progress
record), poses of ``poses_file`` first, commands timed at ``speed_scale`` times
``max_joint_speed_deg``, a command sent once more when the arm has not started moving
``resend_after`` seconds after it (a command lost to late discovery), and a watchdog
(``stop_on_unreachable``): a target not reached within ``settle_timeout`` beyond its commanded
duration, or no safe target at all, holds the arm where it is and ends the process with status 3. Topics and QoS: the contract
(:mod:`calibration_interfaces.contract`).

Subscriptions
-------------
/joint_states : sensor_msgs/JointState (best effort: matches any publisher)
/body_schema/estimate, /body_schema/covariance : std_msgs/Float64MultiArray (transient local); the
    informed strategies select on them, and with ``wait_for_estimator`` every strategy waits for
    the first estimate, which the estimator sends once it hears the arm
/camera/<eye>/pose : geometry_msgs/PoseStamped (transient local); with ``use_right_eye`` both
    ``/camera/left/pose`` and ``/camera/right/pose``
/markers : geometry_msgs/PoseArray
/diagnostics : diagnostic_msgs/DiagnosticArray, the detector's per-frame verdicts (statuses named
    calibration_interfaces.outcome.DETECTOR_DIAGNOSTIC): a ``bad_input`` frame after settling is
    not a failed detection; the loop waits for a judged frame and otherwise ends the iteration
    ``bad_input`` (warned), which the occlusion model ignores; each eye's own verdict on the frame
    that decided an attempt teaches that eye's occlusion model (``occlusion_per_eye``)
/body_schema/update_status : diagnostic_msgs/DiagnosticStatus (keys: calibration_interfaces.outcome.StatusKey)

Publications
------------
/arm/command : trajectory_msgs/JointTrajectory (reliable, transient local depth 1: the current target
    is a fact; a recorder that matches late still gets the first command)
/calibration/progress : std_msgs/String (reliable), one JSON object per iteration

Parameters
----------
Declared from the settings dataclasses of :mod:`active_selector.node_settings` (one default, one
description and one range each): robot, eye, use_right_eye, progress_file, wait_for_recorder, wait_for_estimator, resume,
wait_report_period, camera_prior, marker_prior, collision_check, collision_margin, poses_file
(SelectorNodeSettings); strategy ('random' | 'al' | 'ucsal' | 'ccsal'), seed, gamma, delta,
optimizer, algorithm, max_evals, n_candidates, refine_starts, refine_evals, local_algorithm,
repeat_tolerance (StrategySettings); penalty_a, penalty_b, occlusion_length_scale,
occlusion_a0, occlusion_b0, occlusion_prior ('flat' | 'geometric'), occlusion_mode ('paper' |
'expected' | 'gain'), criterion ('a_optimal' | 'v_optimal'), box_samples, q_length, q_angle, visibility_margin,
visibility_marker_widths, eye_correlation, occlusion_per_eye, eye_occlusion_length_scale (PlannerSettings);
iterations, settle_tolerance (rad), settle_timeout (s, sim), settle_time (s, sim),
outcome_timeout (s, sim), max_joint_speed_deg, speed_scale, stop_on_unreachable, resend_after (s, sim and wall)
(LoopSettings);
noise_model ('pose_dependent' | 'constant'), cn_sigma_pos, cn_sigma_rot_deg, pdn_a_pos, pdn_b_pos, pdn_a_rot, pdn_b_rot (NoiseSettings,
PoseDependentSettings; the pdn_* negative by default: the robot description's fitted law).
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration as RclpyDuration
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_schema import load_robot
from body_schema.acquisition import UnsafeSelection
from body_schema.extrinsics import Extrinsics, parse_std
from calibration_interfaces.contract import SENSOR
from calibration_interfaces.messages import (MessageFormatError, joints_in_order, msg_to_covariance, msg_to_table,
                                             pose_msg_to_matrix, stamp_to_seconds)
from calibration_interfaces.node_util import WarnOnce, WarnThrottled, declare_settings, qos_profile, spin_node
from calibration_interfaces.noise import NoiseSettings, PoseDependentSettings
from calibration_interfaces.outcome import (DETECTOR_DIAGNOSTIC, FrameStatus, StatusFormatError, decode_frame,
                                             decode_status)
from calibration_interfaces.pose_list import read_pose_list

from .loop import CalibrationLoop, Iteration, LoopSettings, Phase
from .node_settings import SelectorNodeSettings, StrategySettings
from .planner import Planner, PlannerSettings

__all__ = ['SelectorNode', 'Phase', 'main']


class SelectorNode(Node):
    """Drives the loop (:class:`~active_selector.loop.CalibrationLoop`); the decisions are in
    :class:`~active_selector.planner.Planner`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('active_selector', **kwargs)
        self.settings = declare_settings(self, SelectorNodeSettings)
        strategy = declare_settings(self, StrategySettings)
        planner_settings = declare_settings(self, PlannerSettings, selector=strategy.config())
        loop_settings = declare_settings(self, LoopSettings)
        noise_settings = declare_settings(self, NoiseSettings)
        pdn = declare_settings(self, PoseDependentSettings)

        self.model = load_robot(self.settings.robot)
        #: The cameras the cost plans for: one eye, or the stereo pair the detector fuses.
        self.eyes = self.settings.planned_eyes(self.model)
        if self.settings.use_right_eye and len(self.eyes) == 1:
            self.get_logger().info(f'use_right_eye ignored: robot {self.model.name} has a fixed camera, no eyes')
        noise = noise_settings.build(self.model, pdn)
        # Extrinsics the estimator estimates with the table: their columns enter the cost.
        priors = [parse_std(v, k) for k, v in (('camera_prior', self.settings.camera_prior),
                                                ('marker_prior', self.settings.marker_prior))]
        extrinsics = (Extrinsics(self.model.camera_pose(self.settings.eye), self.model.markers[0].hand_T_marker,
                                 *priors) if any(p is not None for p in priors) else None)
        safety = None
        if self.settings.collision_check:
            from body_schema.collision import CollisionModel   # Pinocchio: only when checking

            margin = self.settings.collision_margin
            safety = CollisionModel(self.model, margin if margin >= 0 else None)
            self.get_logger().info(safety.describe())
        else:
            self.get_logger().warning('collision_check is off: targets are not checked against the obstacles '
                                      'or the arm itself')
        self.planner = Planner(self.model, noise, planner_settings, extrinsics=extrinsics, safety=safety,
                               eyes=tuple(self.eyes))
        if self.settings.poses_file:
            poses = read_pose_list(self.settings.poses_file, self.model)
            self.planner.queue_poses(poses.positions)
            self.get_logger().info(f'{len(poses.positions)} poses of {self.settings.poses_file} first, then '
                                   f'{strategy.strategy}')
        self.n_covariance = self.model.n_params + (0 if extrinsics is None else extrinsics.n)
        self.iterations = loop_settings.iterations
        self.loop = CalibrationLoop(self.planner, loop_settings, self.now, time.monotonic)
        self.progress_file = Path(self.settings.progress_file) if self.settings.progress_file else None
        resumed = 0
        if self.progress_file is not None:
            self.progress_file.parent.mkdir(parents=True, exist_ok=True)
            if self.settings.resume and self.progress_file.exists():
                resumed = self._resume(self.progress_file)
            else:
                self.progress_file.write_text('')

        self.dh: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.camera_poses: dict[str, np.ndarray] = {}
        self._last_wait_report = 0.0
        self._held = False                  # the arm held after a stop
        self._warn_once = WarnOnce(self)
        self._warn = WarnThrottled(self)

        self.pub_cmd = self.create_publisher(JointTrajectory, '/arm/command', qos_profile('/arm/command'))
        self.pub_progress = self.create_publisher(String, '/calibration/progress',
                                                  qos_profile('/calibration/progress'))
        # Best effort matches any joint-state publisher.
        self.create_subscription(JointState, '/joint_states', self.on_joint_state, qos_profile(SENSOR))
        for name, callback in (('/body_schema/estimate', self.on_estimate),
                               ('/body_schema/covariance', self.on_covariance)):
            self.create_subscription(Float64MultiArray, name, callback, qos_profile(name))
        for eye in self.eyes:
            topic = f'/camera/{eye}/pose'
            self.create_subscription(PoseStamped, topic, lambda m, e=eye: self.on_camera_pose(m, e),
                                     qos_profile(topic))
        self.create_subscription(PoseArray, '/markers', self.on_markers, qos_profile('/markers'))
        self.create_subscription(DiagnosticArray, '/diagnostics', self.on_diagnostics, qos_profile('/diagnostics'))
        self.create_subscription(DiagnosticStatus, '/body_schema/update_status', self.on_status,
                                 qos_profile('/body_schema/update_status'))
        # A steady (wall) timer: reports and timeouts must run even when sim time stands still.
        self.create_timer(0.05, self.step, clock=Clock(clock_type=ClockType.STEADY_TIME))
        config = strategy.config()
        self.get_logger().info(f'{config.strategy.value} run of {self.iterations} iterations '
                               f'({config.search}; {self.planner.settings.criterion}, occlusion '
                               f'{self.planner.settings.occlusion_mode}; body penalty '
                               + (f'{self.planner.penalty_a:g} arctan({self.planner.settings.penalty_b:g} p_x))'
                                  if self.planner.model.body_penalty else
                                  'off: the description has no body (selection.body_penalty))')
                               + (f', resumed after iteration {resumed}' if resumed else ''))

    def _resume(self, path: Path) -> int:
        """Account the iterations recorded in ``path`` (movement, occlusion model, count); their number.

        A record cut short by the interruption (the last line) is dropped; the next iteration
        number follows the records kept, the movement continues from the recorded total and from
        the last configuration reached. (The strategy's random stream starts anew.)

        Raises
        ------
        ValueError
            If a record lacks a field, or the file holds the whole run already.
        """
        lines = path.read_text().splitlines()
        records = []
        for i, line in enumerate(lines):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                if i < len(lines) - 1:
                    raise ValueError(f'{path}: line {i + 1} is not JSON: {line[:80]!r}') from None
        for r in records:
            try:
                if self.planner.start is None:      # movement is the recorded total (below), not re-derived
                    self.planner.start = np.radians(r['reached_deg'])
                self.planner.record(np.radians(r['target_deg']), np.radians(r['reached_deg']), r['outcome'],
                                    bool(r['detected']), float(r['selection_s']), eyes=r.get('eyes'))
            except KeyError as exc:
                raise ValueError(f'{path}: iteration record without {exc}: {r}') from None
        if records:
            self.planner.movement_deg = float(records[-1]['movement_deg'])
        if len(records) >= self.iterations:
            raise ValueError(f'{path} records {len(records)} iterations already; nothing to resume '
                             f'(iterations: {self.iterations})')
        path.write_text(''.join(json.dumps(r) + '\n' for r in records))      # without a torn last line
        return len(records)

    # ---------------------------------------------------------------------------------- inputs

    @property
    def phase(self) -> Phase:
        return self.loop.phase

    @property
    def done(self) -> bool:
        return self.loop.done

    @property
    def q(self) -> np.ndarray | None:
        """The latest joint positions (L,) [rad], None before the first joint state."""
        return self.loop.q

    @property
    def waiting_for(self) -> list[str]:
        """Inputs still missing before the first selection."""
        missing = []
        if self.q is None:
            missing.append('/joint_states')
        informed = self.planner.strategy.value != 'random'
        if self.dh is None and (informed or self.settings.wait_for_estimator):
            missing.append('/body_schema/estimate')
        if informed:
            if self.P is None:
                missing.append('/body_schema/covariance')
            missing.extend(f'/camera/{eye}/pose' for eye in self.eyes if eye not in self.camera_poses)
        if self.settings.wait_for_recorder and self.pub_progress.get_subscription_count() == 0:
            missing.append('a subscriber of /calibration/progress (the recorder)')
        return missing

    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def on_joint_state(self, msg: JointState) -> None:
        q = joints_in_order(msg.name, msg.position, self.model.joint_names)
        if q is None:
            self._warn_once('names', f'/joint_states does not carry all of {self.model.joint_names}; ignored')
            return
        if not np.all(np.isfinite(q)):
            return
        self.loop.joint_state(stamp_to_seconds(msg.header.stamp), q)
        if self.phase is Phase.WAITING:
            # Select on the first joint state after an iteration ends rather than on the next
            # wall-clock step: a simulator running faster than real time would otherwise tick on
            # idle for up to a step period. The estimator publishes its estimate before its
            # verdict, so the estimate of that verdict has arrived by now.
            self.step()

    def on_estimate(self, msg: Float64MultiArray) -> None:
        try:
            self.dh = msg_to_table(msg, self.model.n_joints)
        except MessageFormatError as exc:
            self._warn('estimate', f'/body_schema/estimate ignored: {exc}')

    def on_covariance(self, msg: Float64MultiArray) -> None:
        try:
            self.P = msg_to_covariance(msg, self.n_covariance)
        except MessageFormatError as exc:
            self._warn('covariance', f'/body_schema/covariance ignored: {exc}')

    @property
    def camera_pose(self) -> np.ndarray | None:
        """The planned-for camera pose (4, 4), or the stereo pair's (2, 4, 4); None until every one arrived."""
        if any(eye not in self.camera_poses for eye in self.eyes):
            return None
        poses = np.stack([self.camera_poses[eye] for eye in self.eyes])
        return poses[0] if len(poses) == 1 else poses

    def on_camera_pose(self, msg: PoseStamped, eye: str | None = None) -> None:
        eye = eye or self.eyes[0]
        try:
            self.camera_poses[eye] = pose_msg_to_matrix(msg.pose)
        except ValueError as exc:
            self._warn(f'camera_pose.{eye}', f'{eye} camera pose ignored: {exc}')

    def on_markers(self, msg: PoseArray) -> None:
        self._report(self.loop.markers(stamp_to_seconds(msg.header.stamp), len(msg.poses) > 0))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name != DETECTOR_DIAGNOSTIC:
                continue                              # other nodes' diagnostics
            try:
                frame = decode_frame({v.key: v.value for v in status.values})
            except StatusFormatError as exc:
                self._warn_once('frame', f'/diagnostics {DETECTOR_DIAGNOSTIC} status ignored: {exc}')
                continue
            if frame.eyes:
                self.loop.eye_verdicts(frame.stamp, {eye: v is FrameStatus.DETECTED for eye, v in frame.eyes.items()
                                                     if v is not FrameStatus.BAD_INPUT})
            if frame.status is FrameStatus.BAD_INPUT and self.loop.bad_frame(frame.stamp, status.message):
                self._warn(f'bad_input.{frame.kind}', f'the attempt frame at {frame.stamp:.3f} s was bad input '
                           f'({status.message}); not counted as the hand hidden, waiting for the next')

    def on_status(self, msg: DiagnosticStatus) -> None:
        try:
            status = decode_status({v.key: v.value for v in msg.values})
        except StatusFormatError as exc:
            self._warn_once('status', f'/body_schema/update_status ignored: {exc}')
            return
        self._report(self.loop.estimator_outcome(status.outcome, status.joints, msg.message, status.stamp))

    # ---------------------------------------------------------------------------------- loop

    def step(self) -> None:
        """Periodic: start iterations, report what is missing, enforce timeouts."""
        if self.phase is Phase.WAITING:
            missing = self.waiting_for
            if missing:
                t = time.monotonic()
                if t - self._last_wait_report >= self.settings.wait_report_period:
                    self._last_wait_report = t
                    self.get_logger().info(f'waiting for {", ".join(missing)} before selecting')
                return
            self._select_and_command()
        else:
            if self.loop.resend_due():
                self.get_logger().warning(f'the arm has not moved {self.loop.settings.resend_after:g} s after the '
                                          f'command of iteration {self.loop.iteration + 1}: sending it again '
                                          '(was it delivered? is the arm driver up?)')
                self._command(self.loop.target, self.loop.duration)
            self._report(self.loop.tick())
        if self.loop.stopped and self.q is not None and not self._held:
            self._held = True
            self._command(self.q, 0.0)
            self.get_logger().error(f'{self.loop.stop_reason}; the arm is held where it is and the run stops')

    def _select_and_command(self) -> None:
        skipped = len(self.planner.skipped)
        try:
            target = self.loop.select(self.dh, self.P, self.camera_pose)
        except UnsafeSelection as exc:
            self._stop(f'no safe target: {exc}')
            return
        for index, why in self.planner.skipped[skipped:]:
            self.get_logger().warning(f'pose {index} of {self.settings.poses_file} skipped: {why}')
        self._command(target, self.loop.duration)

    def _command(self, target: np.ndarray, duration: float) -> None:
        traj = JointTrajectory()
        traj.header.stamp = self.get_clock().now().to_msg()
        traj.joint_names = list(self.model.joint_names)
        traj.points = [JointTrajectoryPoint(positions=target.tolist(),
                                            time_from_start=RclpyDuration(seconds=duration).to_msg())]
        self.pub_cmd.publish(traj)

    def _stop(self, why: str) -> None:
        """Hold the arm where it is and end the run (exit status :data:`STOPPED_STATUS`)."""
        from .loop import Phase as _Phase

        self.loop.phase = _Phase.STOPPED
        self.loop.stop_reason = why
        self._held = True
        if self.q is not None:
            self._command(self.q, 0.0)
        self.get_logger().error(f'{why}; the arm is held where it is and the run stops')

    def _report(self, it: Iteration | None) -> None:
        """Log, publish and append the progress record of an ended iteration."""
        if it is None:
            return
        a = it.attempt
        msg = (f'iteration {a.iteration}/{self.iterations} {self.planner.strategy.value}: '
               f'target [{" ".join(f"{v:.1f}" for v in np.degrees(a.target))}] deg, outcome {a.outcome} '
               f'({it.reason}), movement {a.movement_deg:.1f} deg, selection {a.selection_seconds:.2f} s')
        if a.detected:      # rclpy binds one severity to each logging call site
            self.get_logger().info(msg)
        else:
            self.get_logger().warning(msg)
        self.pub_progress.publish(String(data=json.dumps(it.record)))
        if self.progress_file is not None:
            with self.progress_file.open('a') as f:
                f.write(json.dumps(it.record) + '\n')
        if self.done:
            self.get_logger().info(f'done: {a.iteration} iterations, movement {a.movement_deg:.1f} deg, '
                                   f'{self.planner.discarded} discarded')


#: Seconds the selector waits, once done, for its last records to be acknowledged.
FLUSH_TIMEOUT_S = 5.0

#: Exit status of a run the watchdog stopped (a target not reached in time, no safe target).
STOPPED_STATUS = 3


def _run_until_done(node: SelectorNode) -> None:
    while rclpy.ok() and not node.done:
        rclpy.spin_once(node, timeout_sec=0.1)
    if node.done:
        # The process ends next: a reliable record not yet acknowledged would die with it (the
        # recorder lost the last iteration's progress record that way in runs on a loaded machine).
        for pub in (node.pub_progress, node.pub_cmd):
            if not pub.wait_for_all_acked(RclpyDuration(seconds=FLUSH_TIMEOUT_S)):
                node.get_logger().warning(f'{pub.topic_name}: not every subscriber acknowledged the last '
                                          f'message within {FLUSH_TIMEOUT_S} s')
        if node.loop.stopped:
            raise SystemExit(STOPPED_STATUS)


def main(args: list[str] | None = None) -> None:
    spin_node(SelectorNode, args, _run_until_done)


if __name__ == '__main__':
    main(sys.argv)
