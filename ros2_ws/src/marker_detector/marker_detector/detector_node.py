"""ROS 2 node: ArUco hand-pose detection with a pose-dependent noise model.

A thin layer over :mod:`marker_detector.detection` (geometry) and
:mod:`marker_detector.image_conversion` (what cv_bridge would do).

Subscribes
----------
``/camera/left/image_raw`` (sensor_msgs/Image, rgb8/bgr8/mono8; sensor-data QoS)
``/camera/left/camera_info`` (sensor_msgs/CameraInfo; sensor-data QoS, which matches both
reliable and best-effort publishers)
``/camera/left/pose`` (geometry_msgs/PoseStamped: optical frame in root_link; reliable,
transient local so the latched pose reaches a late joiner)
``/camera/right/...`` the same three, when ``use_right_eye`` is true.

Publishes (reliable, depth 10)
------------------------------
``/hand_pose`` (geometry_msgs/PoseWithCovarianceStamped): hand frame in root_link, stamp = image
stamp, 6x6 covariance (x y z rotX rotY rotZ, row-major) from the noise model; only on success.
``/markers`` (geometry_msgs/PoseArray): every processed frame, the accepted marker poses in the
camera frame (frame_id and stamp of the image); an empty array is an explicit failed detection.
With both eyes, one message per stereo pair, expressed in the left camera frame.
A frame whose stamp equals the previous frame's of the same eye is dropped (same evidence).

Parameters
----------
robot (str): packaged robot name or YAML path (markers, dictionary, side length, root frame).
noise_model (str): ``pose_dependent`` (paper eq. 13, fitted defaults) or ``constant`` (CN).
cn_sigma_pos (float, m), cn_sigma_rot_deg (float, deg): the CN model's standard deviations.
fusion (str): ``best`` | ``weighted`` | ``joint`` when several markers are accepted.
max_reprojection_error_px, ambiguity_ratio, ambiguity_margin_px, ambiguity_min_angle_deg,
min_side_px (float), refine_lm, edge_refinement (bool): see ``detection.DetectorConfig``.
use_right_eye (bool): also process the right eye and fuse the pair (same image stamp).
stereo_timeout (float, s): how long one eye's result waits for the other's before going alone.
use_sim_time (bool, built in): stamps come from the image headers anyway.

No services.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from numpy.typing import NDArray
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from sensor_msgs.msg import CameraInfo, Image

from body_schema import load_robot
from body_schema.noise import ConstantNoise, PoseDependentNoise
from dh_estimator.messages import matrix_to_pose_msg, pose_msg_to_matrix

from .detection import FUSION_MODES, DetectorConfig, FrameResult, HandEstimate, HandPoseEstimator, fuse_estimates
from .image_conversion import ImageConversionError, image_to_gray

__all__ = ['DetectorNode', 'pose_msg_to_matrix', 'matrix_to_pose_msg', 'main']

OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        history=HistoryPolicy.KEEP_LAST)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)


def _stamp_key(stamp: Any) -> tuple[int, int]:
    return int(stamp.sec), int(stamp.nanosec)


class _Eye:
    """Latest calibration and pose of one eye."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.k: NDArray[np.float64] | None = None
        self.dist: NDArray[np.float64] | None = None
        self.size: tuple[int, int] | None = None
        self.root_T_cam: NDArray[np.float64] | None = None
        self.last_stamp: tuple[int, int] | None = None


class DetectorNode(Node):
    """See the module docstring for topics and parameters."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('marker_detector', **kwargs)
        d = DetectorConfig()
        self._declare('robot', 'icub_right_arm', 'packaged robot name or path of a robot YAML')
        self._declare('noise_model', 'pose_dependent',
                      "covariance model: 'pose_dependent' (paper eq. 13) or 'constant' (CN)")
        cn = ConstantNoise()
        self._declare('cn_sigma_pos', float(cn.sigma_pos), 'CN position standard deviation [m]',
                      (1e-6, 1.0))
        self._declare('cn_sigma_rot_deg', float(np.degrees(cn.sigma_rot)),
                      'CN orientation standard deviation [deg]', (1e-4, 90.0))
        self._declare('fusion', d.fusion, f'combining several accepted markers: {FUSION_MODES}')
        self._declare('max_reprojection_error_px', d.max_reprojection_error_px,
                      'reject a marker whose RMS corner reprojection error is larger [px]', (0.0, 100.0))
        self._declare('ambiguity_ratio', d.ambiguity_ratio,
                      'IPPE flip is ambiguous when alt_err < ratio * best_err + margin', (1.0, 100.0))
        self._declare('ambiguity_margin_px', d.ambiguity_margin_px,
                      'additive margin of the ambiguity test [px]', (0.0, 100.0))
        self._declare('ambiguity_min_angle_deg', d.ambiguity_min_angle_deg,
                      'solutions closer than this are not ambiguous [deg]', (0.0, 180.0))
        self._declare('min_side_px', d.min_side_px, 'ignore markers with a shorter side [px]',
                      (0.0, 1000.0))
        self._declare('refine_lm', d.refine_lm, 'Levenberg-Marquardt polish of the IPPE pose')
        self._declare('edge_refinement', d.edge_refinement,
                      'corners from fitted edge lines (removes ArUco corner bias)')
        self._declare('use_right_eye', False, 'also process the right eye and fuse the pair')
        self._declare('stereo_timeout', 0.5,
                      'seconds one eye waits for the other eye of the same stamp', (0.0, 10.0))

        gp = self.get_parameter
        self.model = load_robot(gp('robot').value)
        kind = gp('noise_model').value
        if kind in ('pose_dependent', 'pdn'):
            noise: Any = PoseDependentNoise()
        elif kind in ('constant', 'cn'):
            noise = ConstantNoise(gp('cn_sigma_pos').value, float(np.radians(gp('cn_sigma_rot_deg').value)))
        else:
            raise ValueError(f"noise_model: unknown {kind!r}; expected 'pose_dependent' or 'constant'")
        config = DetectorConfig(
            max_reprojection_error_px=gp('max_reprojection_error_px').value,
            ambiguity_ratio=gp('ambiguity_ratio').value,
            ambiguity_margin_px=gp('ambiguity_margin_px').value,
            ambiguity_min_angle_deg=gp('ambiguity_min_angle_deg').value,
            refine_lm=gp('refine_lm').value, fusion=gp('fusion').value,
            min_side_px=gp('min_side_px').value, edge_refinement=gp('edge_refinement').value)
        self.estimator = HandPoseEstimator(self.model, noise, config)
        self.root_frame = self.model.root_frame
        self.stereo = bool(gp('use_right_eye').value)
        self.stereo_timeout = float(gp('stereo_timeout').value)

        self._warned: set[str] = set()
        self.eyes = {name: _Eye(name) for name in (('left', 'right') if self.stereo else ('left',))}
        # Stereo: stamp -> {eye: (header, FrameResult, arrival time)} until both eyes are in.
        self._pending: dict[tuple[int, int], dict[str, tuple[Any, FrameResult, float]]] = {}
        self.frames_processed = 0
        self.pub_hand = self.create_publisher(PoseWithCovarianceStamped, 'hand_pose', OUTPUT_QOS)
        self.pub_markers = self.create_publisher(PoseArray, 'markers', OUTPUT_QOS)
        for name, eye in self.eyes.items():
            self.create_subscription(Image, f'camera/{name}/image_raw',
                                     lambda m, e=eye: self._on_image(e, m), qos_profile_sensor_data)
            self.create_subscription(CameraInfo, f'camera/{name}/camera_info',
                                     lambda m, e=eye: self._on_info(e, m), qos_profile_sensor_data)
            self.create_subscription(PoseStamped, f'camera/{name}/pose',
                                     lambda m, e=eye: self._on_pose(e, m), LATCHED_QOS)
        if self.stereo:
            self.create_timer(0.05, self._flush_stale)
        self.get_logger().info(
            f'marker_detector: robot {self.model.name}, markers '
            f'{[m.marker_id for m in self.model.markers]}, noise {kind}, fusion {config.fusion}, '
            f'eyes {list(self.eyes)}')

    # ------------------------------------------------------------------ parameters / logging

    def _declare(self, name: str, default: Any, description: str,
                 float_range: tuple[float, float] | None = None) -> None:
        desc = ParameterDescriptor(description=description)
        if float_range is not None:
            desc.floating_point_range = [FloatingPointRange(from_value=float_range[0],
                                                            to_value=float_range[1], step=0.0)]
        self.declare_parameter(name, default, desc)

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    # ------------------------------------------------------------------ inputs

    def _on_info(self, eye: _Eye, msg: CameraInfo) -> None:
        k = np.array(msg.k, dtype=float).reshape(3, 3)
        if not (np.all(np.isfinite(k)) and k[0, 0] > 0 and k[1, 1] > 0):
            self._warn_once(f'badinfo-{eye.name}', f'{eye.name} camera_info: invalid K {k.tolist()}; ignored')
            return
        dist = np.array(msg.d, dtype=float)
        if dist.size and msg.distortion_model not in ('plumb_bob', 'rational_polynomial'):
            self._warn_once(f'distmodel-{eye.name}', f'{eye.name} camera_info: distortion model '
                            f'{msg.distortion_model!r} treated as plumb_bob')
        eye.k, eye.dist = k, (dist if dist.size else np.zeros(5))
        eye.size = (int(msg.width), int(msg.height))

    def _on_pose(self, eye: _Eye, msg: PoseStamped) -> None:
        try:
            eye.root_T_cam = pose_msg_to_matrix(msg.pose)
        except ValueError as exc:
            self.get_logger().warning(f'{eye.name} camera pose ignored: {exc}')
            return
        if msg.header.frame_id and msg.header.frame_id != self.root_frame:
            self._warn_once(f'poseframe-{eye.name}', f'{eye.name} camera pose is in '
                            f'{msg.header.frame_id!r}, expected {self.root_frame!r}; used as is')

    def _on_image(self, eye: _Eye, msg: Image) -> None:
        if eye.k is None:
            self._warn_once(f'noinfo-{eye.name}', f'no camera_info for the {eye.name} eye yet; '
                            f'skipping frames until it arrives')
            return
        if eye.root_T_cam is None:
            self._warn_once(f'nopose-{eye.name}', f'no camera pose for the {eye.name} eye yet; '
                            f'skipping frames until it arrives')
            return
        key = _stamp_key(msg.header.stamp)
        if key == eye.last_stamp:
            # A re-sent frame is the same evidence, not a second observation.
            self.get_logger().debug(f'{eye.name} frame {key} already processed; dropped')
            return
        eye.last_stamp = key
        t0 = time.perf_counter()
        result = FrameResult()
        try:
            gray = image_to_gray(msg)
            if eye.size is not None and eye.size != (gray.shape[1], gray.shape[0]) and eye.size != (0, 0):
                raise ImageConversionError(
                    f'image is {gray.shape[1]} x {gray.shape[0]} but camera_info says '
                    f'{eye.size[0]} x {eye.size[1]}')
            result = self.estimator.process(gray, eye.k, eye.dist, eye.root_T_cam)
        except (ImageConversionError, ValueError) as exc:
            self.get_logger().warning(f'{eye.name} image at {msg.header.stamp.sec}.'
                                      f'{msg.header.stamp.nanosec:09d} not usable: {exc}',
                                      throttle_duration_sec=2.0)
        except Exception as exc:  # noqa: BLE001 (OpenCV surprises must not kill the node)
            self.get_logger().error(f'{eye.name} image processing failed: {type(exc).__name__}: {exc}',
                                    throttle_duration_sec=2.0)
        self.frames_processed += 1
        self.get_logger().debug(f'{eye.name} frame: {len(result.markers)} markers, '
                                f'{"ok" if result.success else "failed"}, '
                                f'{1e3 * (time.perf_counter() - t0):.2f} ms')
        if not self.stereo:
            self._publish(msg.header, [(eye, result)])
            return
        entry = self._pending.setdefault(key, {})
        entry[eye.name] = (msg.header, result, time.monotonic())
        if len(entry) == len(self.eyes):
            del self._pending[key]
            self._publish_pair(entry)

    def _flush_stale(self) -> None:
        now = time.monotonic()
        for key in [k for k, v in self._pending.items()
                    if now - min(t for _, _, t in v.values()) > self.stereo_timeout]:
            self._publish_pair(self._pending.pop(key))

    # ------------------------------------------------------------------ outputs

    def _publish_pair(self, entry: dict[str, tuple[Any, FrameResult, float]]) -> None:
        # /markers is expressed in the left camera frame (the right eye's too), so one message
        # per stereo pair tells the selector whether the attempt succeeded.
        ref = 'left' if 'left' in entry else next(iter(entry))
        header = entry[ref][0]
        self._publish(header, [(self.eyes[name], res) for name, (_, res, _) in entry.items()],
                      ref_eye=self.eyes[ref])

    def _publish(self, header: Any, results: list[tuple[_Eye, FrameResult]],
                 ref_eye: _Eye | None = None) -> None:
        ref_eye = ref_eye or results[0][0]
        markers = PoseArray()
        markers.header.stamp = header.stamp
        markers.header.frame_id = header.frame_id
        hands: list[HandEstimate] = []
        for eye, res in results:
            to_ref = np.eye(4)
            if eye is not ref_eye and eye.root_T_cam is not None and ref_eye.root_T_cam is not None:
                to_ref = np.linalg.inv(ref_eye.root_T_cam) @ eye.root_T_cam
            markers.poses.extend(matrix_to_pose_msg(to_ref @ m.cam_T_marker) for m in res.markers)
            if res.hand is not None:
                hands.append(res.hand)
        self.pub_markers.publish(markers)
        if not hands:
            return
        hand = fuse_estimates(hands) if len(hands) > 1 else hands[0]
        out = PoseWithCovarianceStamped()
        out.header.stamp = header.stamp
        out.header.frame_id = self.root_frame
        out.pose.pose = matrix_to_pose_msg(hand.pose)
        out.pose.covariance = [float(v) for v in np.asarray(hand.covariance, dtype=float).reshape(36)]
        self.pub_hand.publish(out)


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = DetectorNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
