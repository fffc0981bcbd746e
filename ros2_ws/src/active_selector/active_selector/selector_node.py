"""active_selector node: chooses where the arm goes next and drives the calibration loop.

One iteration (DESIGN.md section 3): select a target with the strategy, command it, wait until
``/joint_states`` shows the arm settled there (or give up: timeout), take the attempt's outcome
(failure: the first ``/markers`` frame captured after settling is empty; success: the estimator's
update at this configuration), feed the occlusion model, account the movement. After
``iterations`` iterations it logs a summary and the process exits with status 0.

Subscriptions
-------------
/joint_states : sensor_msgs/JointState
/body_schema/estimate, /body_schema/covariance : std_msgs/Float64MultiArray (transient local)
/camera/<eye>/pose : geometry_msgs/PoseStamped (transient local)
/markers : geometry_msgs/PoseArray
/body_schema/update_status : diagnostic_msgs/DiagnosticStatus

Publications
------------
/arm/command : trajectory_msgs/JointTrajectory (reliable, transient local depth 1: the current target
    is a fact; a recorder that matches late still gets the first command)
/calibration/progress : std_msgs/String (reliable), one JSON object per iteration

Parameters
----------
robot, strategy ('random' | 'al' | 'ucsal' | 'ccsal'), iterations, seed, gamma, delta,
penalty_a, penalty_b, algorithm, max_evals, occlusion_length_scale, occlusion_a0, occlusion_b0,
occlusion_mode ('paper' | 'expected'), noise_model ('pose_dependent' | 'constant'),
pdn_a_pos, pdn_b_pos, pdn_a_rot, pdn_b_rot, cn_sigma_pos, cn_sigma_rot_deg, eye,
settle_tolerance (rad), settle_timeout (s, sim), settle_time (s, sim), outcome_timeout (s, sim),
progress_file,
wait_report_period (s, wall).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_schema import load_robot
from body_schema.acquisition import DIRECT_ALGORITHMS, SelectorConfig
from body_schema.noise import ConstantNoise, PoseDependentNoise
from dh_estimator.messages import (MessageFormatError, msg_to_covariance, msg_to_table, pose_msg_to_matrix,
                                   stamp_to_seconds)

from .loop import CalibrationLoop, Iteration, LoopSettings, Phase
from .planner import Planner, PlannerSettings

_CN = ConstantNoise()      # fitted CN defaults live in body_schema.noise
_DEF = PlannerSettings()   # measured selector defaults live in the planner
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
_PDN = PoseDependentNoise()


def _float(desc: str, lo: float, hi: float) -> ParameterDescriptor:
    return ParameterDescriptor(description=desc,
                               floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi)])


def _int(desc: str, lo: int, hi: int) -> ParameterDescriptor:
    return ParameterDescriptor(description=desc, integer_range=[IntegerRange(from_value=lo, to_value=hi)])


class SelectorNode(Node):
    """Drives the loop; the decisions are in :class:`~active_selector.planner.Planner`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('active_selector', **kwargs)
        p = self.declare_parameter
        p('robot', 'icub_right_arm', ParameterDescriptor(description='Packaged robot name or YAML path'))
        p('strategy', 'al', ParameterDescriptor(description="'random', 'al', 'ucsal' or 'ccsal'"))
        p('iterations', 50, _int('Iterations (measurement attempts) of the run', 1, 100000))
        p('seed', 0, _int('Seed of the random strategy and randomised DIRECT', 0, 2**31 - 1))
        p('gamma', _DEF.selector.gamma, _float('UCSAL weight of the normalised L1 movement', 0.0, 1e9))
        p('delta', _DEF.selector.delta, _float('CCSAL half-width of the box around the previous configuration (normalised)', 1e-6, 1.0))
        p('penalty_a', _DEF.penalty_a, _float('Weight a of the a*arctan(b*p_x) penalty on hands behind the body', 0.0, 1e6))
        p('penalty_b', _DEF.penalty_b, _float('Slope b of the arctan penalty [1/m]', 0.0, 1e6))
        p('algorithm', _DEF.selector.algorithm, ParameterDescriptor(description=f'NLopt algorithm: {sorted(DIRECT_ALGORITHMS)}'))
        p('max_evals', _DEF.selector.max_evals, _int('Cost evaluations per selection', 10, 10**7))
        p('occlusion_length_scale', _DEF.occlusion_length_scale, _float('Occlusion kernel length scale (normalised joints)', 1e-4, 10.0))
        p('occlusion_a0', _DEF.occlusion_a0, _float('Beta prior successes', 1e-6, 1e6))
        p('occlusion_b0', _DEF.occlusion_b0, _float('Beta prior failures', 1e-6, 1e6))
        p('occlusion_mode', _DEF.occlusion_mode, ParameterDescriptor(description="'paper' (C0 / eta) or 'expected'"))
        p('noise_model', 'pose_dependent', ParameterDescriptor(description="R predicted by 'pose_dependent' or 'constant'"))
        p('pdn_a_pos', _PDN.a_pos, _float('Pose-dependent position variance per r^2', 0.0, 1.0))
        p('pdn_b_pos', _PDN.b_pos, _float('Pose-dependent position variance per (phi-45)^2', 0.0, 1.0))
        p('pdn_a_rot', _PDN.a_rot, _float('Pose-dependent orientation variance per r^2', 0.0, 10.0))
        p('pdn_b_rot', _PDN.b_rot, _float('Pose-dependent orientation variance per (phi-45)^2', 0.0, 1.0))
        p('cn_sigma_pos', _CN.sigma_pos, _float('CN position standard deviation [m]', 1e-6, 1.0))
        p('cn_sigma_rot_deg', float(np.degrees(_CN.sigma_rot)), _float('CN orientation standard deviation [deg]', 1e-4, 90.0))
        p('eye', 'left', ParameterDescriptor(description='Which eye the detector uses: left or right'))
        p('settle_tolerance', 0.002, _float('Max joint error counted as arrived [rad]', 1e-6, 0.5))
        p('settle_timeout', 30.0, _float('Sim seconds to reach a target before giving up', 0.1, 1e4))
        p('settle_time', 0.1, _float('Sim seconds the arm rests before the attempt image '
                                     '(match the estimator\'s static_window)', 0.0, 10.0))
        p('outcome_timeout', 5.0, _float('Sim seconds after settling to get an outcome', 0.1, 1e4))
        p('progress_file', '', ParameterDescriptor(description='JSON-lines file, one object per iteration'))
        p('wait_report_period', 2.0, _float('Wall seconds between "waiting for" reports', 0.1, 3600.0))

        gp = lambda name: self.get_parameter(name).value  # noqa: E731
        self.model = load_robot(gp('robot'))
        noise = (ConstantNoise(gp('cn_sigma_pos'), np.radians(gp('cn_sigma_rot_deg')))
                 if gp('noise_model') == 'constant' else
                 PoseDependentNoise(gp('pdn_a_pos'), gp('pdn_b_pos'), gp('pdn_a_rot'), gp('pdn_b_rot'),
                                    _PDN.floor_pos, _PDN.floor_rot))
        if gp('noise_model') not in ('pose_dependent', 'constant'):
            raise ValueError(f"noise_model must be 'pose_dependent' or 'constant', got {gp('noise_model')!r}")
        config = SelectorConfig(strategy=gp('strategy'), gamma=gp('gamma'), delta=gp('delta'),
                                algorithm=gp('algorithm'), max_evals=gp('max_evals'), seed=gp('seed'))
        self.planner = Planner(self.model, noise, PlannerSettings(
            selector=config, penalty_a=gp('penalty_a'), penalty_b=gp('penalty_b'),
            occlusion_length_scale=gp('occlusion_length_scale'), occlusion_a0=gp('occlusion_a0'),
            occlusion_b0=gp('occlusion_b0'), occlusion_mode=gp('occlusion_mode')))
        self.iterations = gp('iterations')
        self.loop = CalibrationLoop(self.planner, LoopSettings(
            iterations=gp('iterations'), settle_tolerance=gp('settle_tolerance'),
            settle_timeout=gp('settle_timeout'), settle_time=gp('settle_time'),
            outcome_timeout=gp('outcome_timeout')), self.now)
        self.progress_file = Path(gp('progress_file')) if gp('progress_file') else None
        if self.progress_file is not None:
            self.progress_file.parent.mkdir(parents=True, exist_ok=True)
            self.progress_file.write_text('')

        self.dh: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.camera_pose: np.ndarray | None = None
        self._last_wait_report = 0.0
        self._warned: set[str] = set()

        self.pub_cmd = self.create_publisher(JointTrajectory, '/arm/command', LATCHED)
        self.pub_progress = self.create_publisher(String, '/calibration/progress', 10)
        self.create_subscription(JointState, '/joint_states', self.on_joint_state, qos_profile_sensor_data)
        self.create_subscription(Float64MultiArray, '/body_schema/estimate', self.on_estimate, LATCHED)
        self.create_subscription(Float64MultiArray, '/body_schema/covariance', self.on_covariance, LATCHED)
        self.create_subscription(PoseStamped, f"/camera/{gp('eye')}/pose", self.on_camera_pose, LATCHED)
        self.create_subscription(PoseArray, '/markers', self.on_markers, 10)
        self.create_subscription(DiagnosticStatus, '/body_schema/update_status', self.on_status, 10)
        # A steady (wall) timer: reports and timeouts must run even when sim time stands still.
        self.create_timer(0.05, self.step, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'{config.strategy.value} run of {self.iterations} iterations '
                               f'(DIRECT {config.algorithm}, {config.max_evals} evaluations)')

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
        if self.planner.strategy.value != 'random':
            if self.dh is None:
                missing.append('/body_schema/estimate')
            if self.P is None:
                missing.append('/body_schema/covariance')
            if self.camera_pose is None:
                missing.append(f"/camera/{self.get_parameter('eye').value}/pose")
        return missing

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def on_joint_state(self, msg: JointState) -> None:
        names = list(msg.name)
        try:
            q = np.array([msg.position[names.index(n)] for n in self.model.joint_names], dtype=float)
        except (ValueError, IndexError):
            self._warn_once('names', f'/joint_states does not carry all of {self.model.joint_names}; ignored')
            return
        if not np.all(np.isfinite(q)):
            return
        self.loop.joint_state(stamp_to_seconds(msg.header.stamp), q)

    def on_estimate(self, msg: Float64MultiArray) -> None:
        try:
            self.dh = msg_to_table(msg, self.model.n_joints)
        except MessageFormatError as exc:
            self.get_logger().warning(f'/body_schema/estimate ignored: {exc}')

    def on_covariance(self, msg: Float64MultiArray) -> None:
        try:
            self.P = msg_to_covariance(msg, self.model.n_params)
        except MessageFormatError as exc:
            self.get_logger().warning(f'/body_schema/covariance ignored: {exc}')

    def on_camera_pose(self, msg: PoseStamped) -> None:
        try:
            self.camera_pose = pose_msg_to_matrix(msg.pose)
        except ValueError as exc:
            self.get_logger().warning(f'camera pose ignored: {exc}')

    def on_markers(self, msg: PoseArray) -> None:
        self._report(self.loop.markers(stamp_to_seconds(msg.header.stamp), len(msg.poses) > 0))

    def on_status(self, msg: DiagnosticStatus) -> None:
        kv = {v.key: v.value for v in msg.values}
        if 'outcome' not in kv:
            return
        try:
            joints = np.array([float(v) for v in kv.get('joints', '').split()])
        except ValueError:
            self._warn_once('status', f"/body_schema/update_status joints {kv.get('joints')!r} are not numbers; ignored")
            return
        self._report(self.loop.estimator_outcome(kv['outcome'], joints, msg.message))

    # ---------------------------------------------------------------------------------- loop

    def step(self) -> None:
        """Periodic: start iterations, report what is missing, enforce timeouts."""
        if self.phase is Phase.WAITING:
            missing = self.waiting_for
            if missing:
                t = time.monotonic()
                if t - self._last_wait_report >= self.get_parameter('wait_report_period').value:
                    self._last_wait_report = t
                    self.get_logger().info(f'waiting for {", ".join(missing)} before selecting')
                return
            self._select_and_command()
        else:
            self._report(self.loop.tick())

    def _select_and_command(self) -> None:
        target = self.loop.select(self.dh, self.P, self.camera_pose)
        traj = JointTrajectory()
        traj.header.stamp = self.get_clock().now().to_msg()
        traj.joint_names = list(self.model.joint_names)
        traj.points = [JointTrajectoryPoint(positions=target.tolist(), time_from_start=Duration())]
        self.pub_cmd.publish(traj)

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


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = SelectorNode()
        while rclpy.ok() and not node.done:
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main(sys.argv)
