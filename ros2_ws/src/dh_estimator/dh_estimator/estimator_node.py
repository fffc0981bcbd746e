"""dh_estimator node: online EKF over the arm's 28 DH parameters.

Pairs each hand-pose observation with the joint state at the image's stamp (buffered and
interpolated), makes one EKF update per static configuration and publishes the estimate.

Subscriptions
-------------
/joint_states : sensor_msgs/JointState
    Buffered; names are matched to the robot description's joints.
/hand_pose : geometry_msgs/PoseWithCovarianceStamped
    Hand pose in root_link, stamp = image stamp, covariance from the detector's noise model.
/arm/command : trajectory_msgs/JointTrajectory
    The latest commanded target: with ``require_command`` only observations taken while the
    arm rests at it are measurement attempts (not the start pose, not a pose passed on the way).

Publications
------------
/body_schema/estimate : std_msgs/Float64MultiArray (reliable, transient local)
    7 x 4 DH table (a, d, alpha, offset), after every attempt.
/body_schema/covariance : std_msgs/Float64MultiArray (reliable, transient local)
    28 x 28 covariance, row-major, same order.
/body_schema/update_status : diagnostic_msgs/DiagnosticStatus (reliable)
    One per attempt: outcome (accepted / rejected / duplicate / moving), image stamp, joints,
    Mahalanobis distance and counters.

Services
--------
~/export : std_srvs/Trigger
    Writes the calibrated model (DH YAML with one-sigma, URDF) to ``export_dir``.

Parameters
----------
robot (str), initial_guess ('perturbed' | 'nominal' | 'file'), initial_seed (int),
initial_dh_file (str), width_length (m), width_angle_deg (deg), q_length (m^2), q_angle (rad^2),
gate_probability, gate_warmup, iterations, noise_model ('message' | 'constant'), cn_sigma_pos (m),
cn_sigma_rot_deg (deg), static_window (s), static_tolerance (rad), same_config_tolerance (rad),
require_command (bool), target_tolerance (rad), checkpoint_path (str), export_dir (str),
export_on_shutdown (bool).
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from body_schema import load_robot, sampling
from body_schema.noise import ConstantNoise

from .estimator import EstimatorSettings, OnlineEstimator, Outcome
from .pairing import Attempt, ObservationPairer, PairingSettings
from .messages import covariance_to_msg, joints_in_order, pose_msg_to_matrix, stamp_to_seconds, table_to_msg

_CN = ConstantNoise()      # fitted CN defaults live in body_schema.noise
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Best effort matches any publisher; the deep queue keeps the rest window intact under bursts.
JOINT_STATES_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT)


def _float(desc: str, lo: float, hi: float) -> ParameterDescriptor:
    return ParameterDescriptor(description=desc,
                               floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi)])


class EstimatorNode(Node):
    """Thin ROS wrapper around :class:`~dh_estimator.estimator.OnlineEstimator`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('dh_estimator', **kwargs)
        p = self.declare_parameter
        p('robot', 'icub_right_arm', ParameterDescriptor(description='Packaged robot name or YAML path'))
        p('initial_guess', 'perturbed', ParameterDescriptor(
            description="'perturbed': seeded uniform draw around the description's table (paper); "
                        "'nominal': the description's table; 'file': initial_dh_file"))
        p('initial_seed', 0, ParameterDescriptor(description='Seed of the perturbed initial guess',
                                                 integer_range=[IntegerRange(from_value=0, to_value=2**31 - 1)]))
        p('initial_dh_file', '', ParameterDescriptor(description='DH table YAML (as exported) for initial_guess=file'))
        p('width_length', sampling.PAPER_WIDTH_LENGTH, _float('Full width of the a, d prior [m]', 1e-6, 1.0))
        p('width_angle_deg', 54.0, _float('Full width of the alpha, offset prior [deg]', 1e-4, 180.0))
        p('estimator', 'map', ParameterDescriptor(
            description="'map': online MAP smoother (re-solves prior + observations, robust loss; default); "
                        "'ekf': the paper's EKF (iterations=1 is the paper's form)"))
        p('q_length', 0.0, _float('Process-noise variance per update for a, d [m^2]', 0.0, 1.0))
        p('q_angle', 0.0, _float('Process-noise variance per update for alpha, offset [rad^2]', 0.0, 1.0))
        p('gate_probability', 0.999, _float('Chi-square gate probability (0 disables gating)', 0.0, 0.999999))
        p('gate_warmup', 10, ParameterDescriptor(description='Accepted updates before the gate may reject',
                                                 integer_range=[IntegerRange(from_value=0, to_value=100000)]))
        p('iterations', 5, ParameterDescriptor(description='Linearisations per update (1: the paper\'s EKF; >1: iterated EKF, measured better from the paper\'s wide prior)',
                                               integer_range=[IntegerRange(from_value=1, to_value=50)]))
        p('noise_model', 'message', ParameterDescriptor(
            description="'message': covariance of /hand_pose (the detector's pose-dependent model); "
                        "'constant': the CN baseline with cn_sigma_pos / cn_sigma_rot_deg"))
        p('cn_sigma_pos', _CN.sigma_pos, _float('CN position standard deviation [m]', 1e-6, 1.0))
        p('cn_sigma_rot_deg', float(np.degrees(_CN.sigma_rot)), _float('CN orientation standard deviation [deg]', 1e-4, 90.0))
        p('static_window', 0.1, _float('The arm must be still this long before the image stamp [s]', 0.0, 5.0))
        p('static_tolerance', 1e-4, _float('Joint motion tolerated as still [rad]', 0.0, 0.1))
        p('same_config_tolerance', 1e-3, _float('Closer than this to the previous attempt = same configuration [rad]', 0.0, 0.5))
        p('require_command', True, ParameterDescriptor(
            description='Only use observations taken at the latest /arm/command target'))
        p('target_tolerance', 0.005, _float('Max joint distance from the commanded target [rad]', 0.0, 0.5))
        p('checkpoint_path', '', ParameterDescriptor(description='State file rewritten after every update; resumed if it exists'))
        p('export_dir', '', ParameterDescriptor(description='Where ~/export and shutdown write the calibrated model'))
        p('export_on_shutdown', True, ParameterDescriptor(description='Export the calibrated model when the node stops'))

        gp = lambda name: self.get_parameter(name).value  # noqa: E731
        self.model = load_robot(gp('robot'))
        widths = (gp('width_length'), np.radians(gp('width_angle_deg')))
        x0 = self._initial_guess(gp('initial_guess'), gp('initial_seed'), gp('initial_dh_file'), widths)
        settings = EstimatorSettings(estimator=gp('estimator'), q_length=gp('q_length'), q_angle=gp('q_angle'),
                                     gate_probability=gp('gate_probability'), gate_warmup=gp('gate_warmup'),
                                     iterations=gp('iterations'),
                                     same_config_tol=gp('same_config_tolerance'))
        self.estimator = OnlineEstimator(self.model, x0, sampling.initial_covariance(self.model.n_joints, *widths),
                                         settings)
        self.noise_mode = gp('noise_model')
        if self.noise_mode not in ('message', 'constant'):
            raise ValueError(f"noise_model must be 'message' or 'constant', got {self.noise_mode!r}")
        self.cn = ConstantNoise(gp('cn_sigma_pos'), np.radians(gp('cn_sigma_rot_deg')))
        self.pairer = ObservationPairer(self.estimator, PairingSettings(
            static_window=gp('static_window'), static_tol=gp('static_tolerance'),
            require_command=gp('require_command'), target_tol=gp('target_tolerance')))
        self.checkpoint = Path(gp('checkpoint_path')) if gp('checkpoint_path') else None
        self.export_dir = Path(gp('export_dir')) if gp('export_dir') else None
        self.export_on_shutdown = gp('export_on_shutdown')
        if self.checkpoint is not None and self.checkpoint.exists():
            self.estimator.load_checkpoint(self.checkpoint)
            self.get_logger().info(f'resumed from checkpoint {self.checkpoint}: {self.estimator.counters}')

        self.last_update_s = 0.0
        self._warned: set[str] = set()
        self.pub_estimate = self.create_publisher(Float64MultiArray, '/body_schema/estimate', LATCHED)
        self.pub_cov = self.create_publisher(Float64MultiArray, '/body_schema/covariance', LATCHED)
        self.pub_status = self.create_publisher(DiagnosticStatus, '/body_schema/update_status', 10)
        self.create_subscription(JointState, '/joint_states', self.on_joint_state, JOINT_STATES_QOS)
        self.create_subscription(PoseWithCovarianceStamped, '/hand_pose', self.on_hand_pose, 10)
        self.create_subscription(JointTrajectory, '/arm/command', self.on_command, 10)
        self.create_service(Trigger, '~/export', self.on_export)
        self.publish_estimate()
        self.get_logger().info(f'estimating {self.model.n_params} DH parameters of {self.model.name} '
                               f'(initial guess: {gp("initial_guess")}, noise: {self.noise_mode})')

    def _initial_guess(self, kind: str, seed: int, path: str, widths: tuple[float, float]) -> np.ndarray:
        if kind == 'nominal':
            return self.model.dh.copy()
        if kind == 'perturbed':
            return sampling.perturb_dh(self.model.dh, seed, *widths)
        if kind == 'file':
            doc = yaml.safe_load(Path(path).read_text())
            rows = np.array([j['dh'] for j in doc['joints']], dtype=float)
            if rows.shape != self.model.dh.shape:
                raise ValueError(f'{path}: expected a {self.model.dh.shape} table, got {rows.shape}')
            rows[:, 2:] = np.radians(rows[:, 2:])
            return rows
        raise ValueError(f"initial_guess must be 'perturbed', 'nominal' or 'file', got {kind!r}")

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    # ---------------------------------------------------------------------------------------

    def on_joint_state(self, msg: JointState) -> None:
        q = joints_in_order(msg.name, msg.position, self.model.joint_names)
        if q is None:
            names = list(msg.name)
            missing = sorted(set(self.model.joint_names) - set(names))
            if missing:
                self._warn_once('names', f'/joint_states lacks joints {missing} (got {names}); ignored')
            else:
                self._warn_once('len', f'/joint_states has {len(names)} names but {len(msg.position)} '
                                       'positions; ignored')
            return
        if not np.all(np.isfinite(q)):
            self.get_logger().warning(f'/joint_states with non-finite positions {q}; ignored')
            return
        self._handle(self.pairer.joint_state(stamp_to_seconds(msg.header.stamp), q))

    def on_command(self, msg: JointTrajectory) -> None:
        q = joints_in_order(msg.joint_names, msg.points[-1].positions, self.model.joint_names) \
            if msg.points else None
        if q is not None:           # partial or empty commands are the simulator's to reject
            self.pairer.command(q)

    def on_hand_pose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            pose = pose_msg_to_matrix(msg.pose.pose)
        except ValueError as exc:
            self.get_logger().warning(f'/hand_pose with an invalid pose rejected: {exc}')
            return
        if self.noise_mode == 'constant':
            R = self.cn.covariance(0.0, 45.0)  # noqa: N806
        else:
            R = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)  # noqa: N806
        self._handle(self.pairer.hand_pose(stamp_to_seconds(msg.header.stamp), pose, R))

    def _handle(self, attempts: list[Attempt]) -> None:
        for a in attempts:
            if a.outcome == 'dropped':
                self.get_logger().warning(f'hand pose at {a.stamp:.3f} s dropped: {a.message}')
                continue
            if a.outcome == Outcome.DUPLICATE.value:
                continue                             # the same static configuration: not new evidence
            self.last_update_s = a.update_seconds
            if a.outcome == 'invalid':
                self.get_logger().warning(f'hand pose at {a.stamp:.3f} s rejected as invalid input: {a.message}')
            elif a.outcome in (Outcome.ACCEPTED.value, Outcome.OUTLIER.value, Outcome.REJECTED.value):
                if a.outcome != Outcome.ACCEPTED.value:
                    self.get_logger().warning(f'{a.outcome} at {a.stamp:.3f} s: {a.message} '
                                              f'(counters {self.estimator.counters})')
                if self.checkpoint is not None:
                    self.estimator.save_checkpoint(self.checkpoint)
                self.publish_estimate()
            self._status(a.stamp, a.joints, a.outcome, a.message)

    def _status(self, t: float, q: np.ndarray, outcome: str, message: str) -> None:
        c = self.estimator.counters
        level = DiagnosticStatus.OK if outcome == 'accepted' else DiagnosticStatus.WARN
        kv = {'outcome': outcome, 'stamp': f'{t:.9f}', 'joints': ' '.join(f'{v:.9f}' for v in q),
              'mahalanobis': f'{self.estimator.mahalanobis:.6f}', 'update_s': f'{self.last_update_s:.6f}',
              **{k: str(v) for k, v in c.items()}}
        self.pub_status.publish(DiagnosticStatus(level=level, name='dh_estimator', message=message,
                                                 hardware_id=self.model.name,
                                                 values=[KeyValue(key=k, value=v) for k, v in kv.items()]))

    def publish_estimate(self) -> None:
        self.pub_estimate.publish(table_to_msg(self.estimator.dh))
        self.pub_cov.publish(covariance_to_msg(self.estimator.P))

    def on_export(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.export_dir is None:
            response.success, response.message = False, 'export_dir parameter is empty'
            return response
        paths = self.estimator.export(self.export_dir)
        response.success, response.message = True, ' '.join(str(p) for p in paths)
        return response

    def destroy_node(self) -> None:
        if self.export_on_shutdown and self.export_dir is not None:
            try:
                paths = self.estimator.export(self.export_dir)
                self.get_logger().info(f'calibrated model written to {paths[0]} and {paths[1]}')
            except OSError as exc:
                self.get_logger().error(f'export at shutdown failed: {exc}')
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = EstimatorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main(sys.argv)
