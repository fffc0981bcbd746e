"""dh_estimator node: online estimate of the arm's 28 DH parameters (MAP by default, or the EKF).

Pairs each hand-pose observation with the joint state at the image's stamp (buffered and
interpolated), makes one update per static configuration and publishes the estimate. The
default estimator (``estimator: map``) re-solves prior + all observations after each one with a
robust loss and detects body changes; ``estimator: ekf`` is the paper's filter.

Subscriptions
-------------
/joint_states : sensor_msgs/JointState
    Buffered by stamp; names are matched to the robot description's joints. A stamp more than
    ``clock_tolerance`` ahead of the node's clock is refused (a throttled warning with the
    count); the clock stepping back (a simulator restart) restarts the buffer with a warning.
/hand_pose : geometry_msgs/PoseWithCovarianceStamped
    Hand pose in root_link, stamp = image stamp, covariance from the detector's noise model;
    refused like a joint state when stamped in the future.
/arm/command : trajectory_msgs/JointTrajectory
    The latest commanded target: with ``require_command`` only observations taken while the
    arm rests at it are measurement attempts (not the start pose, not a pose passed on the way).

Publications
------------
/body_schema/estimate : std_msgs/Float64MultiArray (reliable, transient local)
    7 x 4 DH table (a, d, alpha, offset), after every attempt. The initial one (with the covariance
    and the description) only once the first joint state has arrived and a ``/hand_pose``
    publisher is matched: it says the estimator can pair observations, and a selector waits for
    it before its first command (an attempt stamped before the estimator's first joint state, or
    imaged before its subscription matched the detector, would be lost online but used by the
    bag's re-run, whose recorder started first: a launched run under load missed its first
    attempt so, and the run check called it unhealthy).
/body_schema/covariance : std_msgs/Float64MultiArray (reliable, transient local)
    28 x 28 covariance, row-major, same order; with ``camera_prior`` / ``marker_prior`` the
    camera's and the marker's 6-D corrections follow the table (34 or 40 square for the iCub; the
    selector is told the same priors and reads it so).
/body_schema/robot_description : std_msgs/String (reliable, transient local)
    URDF of the estimated arm, links under ``estimate/`` (a translucent orange ghost in a 3D
    view), with every estimate.
/body_schema/update_status : diagnostic_msgs/DiagnosticStatus (reliable)
    One per attempt, values keyed by :class:`calibration_interfaces.outcome.StatusKey`: outcome
    (accepted / outlier / rejected / moving / invalid), image stamp, joints, Mahalanobis distance,
    counters (updates, rejected, duplicates, outliers, body changes detected).

Services
--------
~/export : std_srvs/Trigger
    Writes the calibrated model (DH YAML with one-sigma, URDF) to ``export_dir``.

Parameters
----------
Declared from :mod:`dh_estimator.node_settings` (robot, initial guess, files),
:class:`calibration_interfaces.noise.NoiseSettings` (``noise_model``: ``pose_dependent`` takes the
covariance of ``/hand_pose``, ``constant`` the CN baseline), :class:`dh_estimator.estimator.EstimatorSettings`
(filter) and :class:`dh_estimator.pairing.PairingSettings` (which observation is an attempt); the
table of docs/nodes/estimator.md lists them with defaults and ranges. ``config/estimator.yaml`` sets a run's values.
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import sys
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from body_schema import load_robot, sampling
from body_schema.arm_visuals import description_urdf
from calibration_interfaces.contract import ESTIMATE_FRAME_PREFIX, RELIABLE, SENSOR
from calibration_interfaces.dh_file import read_dh_file
from calibration_interfaces.messages import covariance_to_msg, table_to_msg
from calibration_interfaces.node_util import WarnOnce, WarnThrottled, declare_settings, qos_profile, spin_node
from calibration_interfaces.noise import NoiseSettings
from calibration_interfaces.outcome import Outcome, encode_status

from .estimator import EstimatorSettings, OnlineEstimator
from .node_settings import EstimatorNodeSettings
from .pairing import MessageError, MessageFeeder, ObservationPairer, ObservationResult, PairingSettings

#: Seconds between two warnings of one kind (the first at once; each carries the running count).
THROTTLE_S = 2.0

# Best effort matches any publisher; the deep queue keeps the rest window intact under bursts.
JOINT_STATES_QOS = qos_profile(SENSOR, depth=200)


#: The estimated arm's colour in a 3D view: translucent orange over the real (white) arm.
GHOST_RGBA = (1.0, 0.55, 0.1, 0.45)


class EstimatorNode(Node):
    """Thin ROS wrapper around :class:`~dh_estimator.estimator.OnlineEstimator`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('dh_estimator', **kwargs)
        self.settings = declare_settings(self, EstimatorNodeSettings)
        self.noise = declare_settings(self, NoiseSettings)
        settings = declare_settings(self, EstimatorSettings)
        pairing = declare_settings(self, PairingSettings)
        s = self.settings
        self.model = load_robot(s.robot)
        x0 = self._initial_guess(s)
        self.estimator = OnlineEstimator(self.model, x0, sampling.initial_covariance(self.model.n_joints, *s.widths),
                                         settings)
        self.pairer = ObservationPairer(self.estimator, pairing)
        self.feeder = MessageFeeder(self.pairer, self.model.joint_names,
                                    self.noise.build() if self.noise.constant else None)
        self.checkpoint = Path(s.checkpoint_path) if s.checkpoint_path else None
        self.export_dir = Path(s.export_dir) if s.export_dir else None
        self.export_on_shutdown = s.export_on_shutdown
        if self.checkpoint is not None and self.checkpoint.exists():
            self.estimator.load_checkpoint(self.checkpoint)
            self.get_logger().info(f'resumed from checkpoint {self.checkpoint}: {self.estimator.counters}')

        self.last_update_s = 0.0
        self._warn_once = WarnOnce(self)
        self._warn = WarnThrottled(self, THROTTLE_S)
        self.pub_estimate = self.create_publisher(Float64MultiArray, '/body_schema/estimate',
                                                  qos_profile('/body_schema/estimate'))
        self.pub_cov = self.create_publisher(Float64MultiArray, '/body_schema/covariance',
                                             qos_profile('/body_schema/covariance'))
        self.pub_description = self.create_publisher(String, '/body_schema/robot_description',
                                                     qos_profile('/body_schema/robot_description'))
        self.pub_status = self.create_publisher(DiagnosticStatus, '/body_schema/update_status',
                                                qos_profile('/body_schema/update_status'))
        self.create_subscription(JointState, '/joint_states', self.on_joint_state, JOINT_STATES_QOS)
        self.sub_hand_pose = self.create_subscription(PoseWithCovarianceStamped, '/hand_pose', self.on_hand_pose,
                                                      qos_profile('/hand_pose'))
        self.create_subscription(JointTrajectory, '/arm/command', self.on_command, qos_profile(RELIABLE))
        self.create_service(Trigger, '~/export', self.on_export)
        self._announced = False     # the initial estimate waits for a joint state and a hand-pose publisher
        extras = self.estimator.extrinsics
        ms = self.estimator.map.settings if self.estimator.map is not None else None
        self.get_logger().info(f'estimating {self.model.n_params} DH parameters of {self.model.name} '
                               + (f'with the {" and ".join(extras.blocks)} pose ({extras.n} more) '
                                  if extras is not None else '') +
                               f'with the {settings.estimator.upper()} estimator (initial guess: '
                               f'{s.initial_guess}, noise: {self.noise.noise_model}'
                               + (f', covariance: {ms.covariance}, loss: {ms.loss} at {ms.loss_scale:g} sigma'
                                  if ms is not None else '') + ')')

    def _initial_guess(self, s: EstimatorNodeSettings) -> np.ndarray:
        if s.initial_guess == 'nominal':
            return self.model.dh.copy()
        if s.initial_guess == 'perturbed':
            return sampling.perturb_dh(self.model.dh, s.initial_seed, *s.widths)
        return read_dh_file(s.initial_dh_file, self.model.n_joints).dh     # 'file' (the choices are checked)

    # ---------------------------------------------------------------------------------------

    def _now(self) -> float | None:
        """The node's clock [s]; None before a simulated clock has started (no /clock yet)."""
        ns = self.get_clock().now().nanoseconds
        return ns * 1e-9 if ns else None

    def _feed(self, topic: str, msg: Any) -> None:
        resets = self.pairer.counters['clock_resets']
        try:
            results = self.feeder.feed(topic, msg, self._now())
        except MessageError as exc:
            if exc.once:
                self._warn_once(exc.key, str(exc))
            else:
                self._warn(exc.key, str(exc))
            return
        if self.pairer.counters['clock_resets'] != resets:
            self.get_logger().warning(f'the clock stepped back (now {self._now():.3f} s): joint states of the '
                                      f'old timeline forgotten ({self.pairer.counters["clock_resets"]} restarts)')
        self._handle(results)

    def on_joint_state(self, msg: JointState) -> None:
        self._feed('/joint_states', msg)
        if not self._announced and self.pairer.buffer.latest is not None:
            # Matched, not merely discovered: a hand pose published before the match is lost.
            if self.sub_hand_pose.get_publisher_count() > 0:
                self.publish_estimate()
            else:
                self.get_logger().info('joint states heard; waiting for a /hand_pose publisher before '
                                       'announcing the initial estimate', once=True)

    def on_command(self, msg: JointTrajectory) -> None:
        self._feed('/arm/command', msg)

    def on_hand_pose(self, msg: PoseWithCovarianceStamped) -> None:
        self._feed('/hand_pose', msg)

    def _handle(self, results: list[ObservationResult]) -> None:
        for a in results:
            if a.outcome is Outcome.DROPPED:
                self._warn('dropped', f'hand pose at {a.stamp:.3f} s dropped: {a.message}')
                continue
            if a.outcome is Outcome.DUPLICATE:
                continue                             # the same static configuration: not new evidence
            self.last_update_s = a.update_seconds
            if a.outcome is Outcome.INVALID:
                self._warn('invalid', f'hand pose at {a.stamp:.3f} s rejected as invalid input: {a.message}')
            elif a.outcome.updated:
                if a.outcome is not Outcome.ACCEPTED:      # an outlier (MAP) or gated out (EKF)
                    self.get_logger().warning(f'{a.outcome.value} at {a.stamp:.3f} s: {a.message} '
                                              f'(counters {self.estimator.counters})')
                if self.checkpoint is not None:
                    self.estimator.save_checkpoint(self.checkpoint)
                self.publish_estimate()
            self._status(a.stamp, a.joints, a.outcome, a.message)

    def _status(self, t: float, q: np.ndarray, outcome: Outcome, message: str) -> None:
        level = DiagnosticStatus.OK if outcome is Outcome.ACCEPTED else DiagnosticStatus.WARN
        kv = encode_status(outcome, t, q, self.estimator.mahalanobis, self.last_update_s,
                           self.estimator.counters)
        self.pub_status.publish(DiagnosticStatus(level=level, name='dh_estimator', message=message,
                                                 hardware_id=self.model.name,
                                                 values=[KeyValue(key=k, value=v) for k, v in kv.items()]))

    def publish_estimate(self) -> None:
        self._announced = True
        self.pub_estimate.publish(table_to_msg(self.estimator.dh))
        self.pub_cov.publish(covariance_to_msg(self.estimator.P))
        self.pub_description.publish(String(data=description_urdf(
            self.model, self.estimator.dh, prefix=ESTIMATE_FRAME_PREFIX, rgba=GHOST_RGBA)))

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
    spin_node(EstimatorNode, args)


if __name__ == '__main__':
    main(sys.argv)
