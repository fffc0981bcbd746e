"""ROS 2 node: the live 3D view of a calibration, served to a browser (viser).

Subscribes to the topic contract, keeps the latest of each in a
:class:`~calibration_viz.scene.SceneState` and redraws a :class:`~calibration_viz.live_view.LiveView`
at ``redraw_rate`` (wall clock) when something changed. Open ``http://<host>:<port>`` in a browser.
Nothing subscribes to this node; it never slows the loop beyond its own callbacks.

Topics subscribed
-----------------
/joint_states : sensor_msgs/JointState
    Best effort (matches any publisher); both arms are drawn at these joints.
/body_schema/true : std_msgs/Float64MultiArray
    The real arm (latched); the error curve is scored against it.
/body_schema/estimate : std_msgs/Float64MultiArray
    Each estimate (latched): the orange arm and a point of the error curve.
/hand_pose : geometry_msgs/PoseWithCovarianceStamped
    Observed hand poses, drawn with 3-sigma position ellipsoids (the last ``history``).
/camera/<eye>/pose, /camera/<eye>/camera_info : geometry_msgs/PoseStamped, sensor_msgs/CameraInfo
    Latched; the frustums.
/camera/<eye>/image_raw : sensor_msgs/Image
    Sensor data QoS; any camera encoding (:mod:`calibration_interfaces.image_conversion`), shown
    in the frustum at most ``image_rate`` times a second. With ``transport: compressed``
    ``/camera/<eye>/image_raw/compressed`` (sensor_msgs/CompressedImage) instead.

Parameters
----------
Declared (read-only) from :class:`calibration_viz.settings.VizSettings`: robot, host, port,
redraw_rate, image_rate, history, error_configs, cameras, transport.
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import time
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray

from body_schema.robot import CameraIntrinsics, load_robot
from calibration_interfaces.contract import SENSOR, image_topic
from calibration_interfaces.image_conversion import ImageConversionError, message_to_array
from calibration_interfaces.messages import (MessageFormatError, joints_in_order, msg_to_table,
                                             pose_msg_to_matrix)
from calibration_interfaces.node_util import WarnOnce, declare_settings, qos_profile, spin_node

from .live_view import LiveView
from .plan_view import obstacle_meshes
from .scene import SceneState
from .settings import VizSettings


class VizNode(Node):
    """The live view node; ``kwargs`` go to :class:`rclpy.node.Node` (context, overrides)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('calibration_viz', **kwargs)
        s = self.settings = declare_settings(self, VizSettings, read_only=True)
        self.model = load_robot(s.robot)
        self.state = SceneState(self.model, history=s.history, n_configs=s.error_configs)
        self._warn = WarnOnce(self)
        self.view = LiveView(s.host, s.port)
        self.view.add_obstacles(obstacle_meshes(self.model))
        self._image_period = 1.0 / s.image_rate if s.image_rate > 0 else float('inf')
        self._last_image: dict[str, float] = {}

        self.create_subscription(JointState, '/joint_states', self._on_joints, qos_profile(SENSOR, depth=10))
        self.create_subscription(Float64MultiArray, '/body_schema/true', self._on_true,
                                 qos_profile('/body_schema/true'))
        self.create_subscription(Float64MultiArray, '/body_schema/estimate', self._on_estimate,
                                 qos_profile('/body_schema/estimate', depth=100))
        self.create_subscription(PoseWithCovarianceStamped, '/hand_pose', self._on_hand_pose,
                                 qos_profile('/hand_pose'))
        for eye in s.cameras:
            self.create_subscription(PoseStamped, f'/camera/{eye}/pose',
                                     lambda m, e=eye: self._on_camera_pose(e, m), qos_profile(f'/camera/{eye}/pose'))
            self.create_subscription(CameraInfo, f'/camera/{eye}/camera_info',
                                     lambda m, e=eye: self._on_camera_info(e, m),
                                     qos_profile(f'/camera/{eye}/camera_info'))
            topic = image_topic(eye, s.transport)
            self.create_subscription(Image if s.transport == 'raw' else CompressedImage, topic,
                                     lambda m, e=eye: self._on_image(e, m), qos_profile(topic))
        # Wall clock: the view keeps redrawing even when sim time stands still.
        self.create_timer(1.0 / s.redraw_rate, self._redraw, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'live view of {self.model.name} at {self.view.url}')

    def _on_joints(self, msg: JointState) -> None:
        q = joints_in_order(msg.name, msg.position, self.model.joint_names)
        if q is not None and np.all(np.isfinite(q)):
            self.state.set_joints(q)

    def _table(self, msg: Float64MultiArray, topic: str) -> np.ndarray | None:
        try:
            return msg_to_table(msg, self.model.n_joints)
        except MessageFormatError as exc:
            self._warn(topic, f'ignored {topic}: {exc}')
            return None

    def _on_true(self, msg: Float64MultiArray) -> None:
        dh = self._table(msg, '/body_schema/true')
        if dh is not None:
            self.state.set_true(dh)

    def _on_estimate(self, msg: Float64MultiArray) -> None:
        dh = self._table(msg, '/body_schema/estimate')
        if dh is not None:
            self.state.set_estimate(dh)

    def _on_hand_pose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            self.state.add_observation(pose_msg_to_matrix(msg.pose.pose), np.asarray(msg.pose.covariance))
        except ValueError as exc:
            self._warn('/hand_pose', f'ignored a /hand_pose: {exc}')

    def _on_camera_pose(self, eye: str, msg: PoseStamped) -> None:
        self.state.set_camera_pose(eye, pose_msg_to_matrix(msg.pose))

    def _on_camera_info(self, eye: str, msg: CameraInfo) -> None:
        k = msg.k
        self.state.set_camera_intrinsics(eye, CameraIntrinsics(int(msg.width), int(msg.height), float(k[0]),
                                                               float(k[4]), float(k[2]), float(k[5])))

    def _on_image(self, eye: str, msg: Image | CompressedImage) -> None:
        now = time.monotonic()
        if now - self._last_image.get(eye, -np.inf) < self._image_period:
            return
        try:
            rgb = message_to_array(msg, 'rgb8')
        except ImageConversionError as exc:
            self._warn(f'image {eye} {exc.field}', f'{image_topic(eye, self.settings.transport)}: not shown ({exc})')
            return
        self._last_image[eye] = now
        self.state.set_image(eye, rgb)

    def _redraw(self) -> None:
        self.view.draw(self.state)

    def destroy_node(self) -> None:
        self.view.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    spin_node(VizNode, args)


if __name__ == '__main__':
    main()
