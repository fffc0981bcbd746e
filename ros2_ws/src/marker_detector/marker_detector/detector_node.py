"""ROS 2 node: ArUco hand-pose detection with a pose-dependent noise model.

A thin layer over :mod:`marker_detector.detection` (geometry), :mod:`marker_detector.stereo`
(pairing the eyes) and :mod:`calibration_interfaces.image_conversion` (what cv_bridge would do).

Subscribes
----------
``/camera/left/image_raw`` (sensor_msgs/Image, any camera encoding of
:mod:`calibration_interfaces.image_conversion`: mono8/16, rgb/bgr(a)8/16, Bayer 8/16, YUV 4:2:2;
sensor-data QoS), or with ``transport: compressed`` ``/camera/left/image_raw/compressed``
(sensor_msgs/CompressedImage, JPEG or PNG as image_transport's compressed plugin publishes it)
``/camera/left/camera_info`` (sensor_msgs/CameraInfo; sensor-data QoS, which matches both
reliable and best-effort publishers). With ``camera_info_url`` the intrinsics come from that
camera_info_manager file (``ost.yaml``) instead; the topic is then only compared with it, and
the first difference is logged once, naming what differs.
``/camera/left/pose`` (geometry_msgs/PoseStamped: optical frame in root_link; reliable,
transient local so the latched pose reaches a late joiner)
``/camera/right/...`` the same three, when ``use_right_eye`` is true.

Publishes (reliable, depth 10)
------------------------------
``/hand_pose`` (geometry_msgs/PoseWithCovarianceStamped): hand frame in root_link, stamp = image
stamp, 6x6 covariance (x y z rotX rotY rotZ, row-major) from the noise model; only on success. With
both eyes, a stamp both see gives one pose refined on both images' corners
(:meth:`~marker_detector.detection.HandPoseEstimator.stereo`; covariance
:func:`body_schema.noise.stereo_covariance`), a stamp one eye sees that eye's.
``/markers`` (geometry_msgs/PoseArray): every judged frame, the accepted marker poses in the
camera frame (frame_id and stamp of the image); an empty array is an explicit failed detection
(a valid frame without the hand). A frame that cannot be judged (bad image, unusable or missing
camera_info, no camera pose yet) publishes nothing here.
``/diagnostics`` (diagnostic_msgs/DiagnosticArray): one status per frame, named
``marker_detector``, hardware_id the eye(s): OK detected, WARN no marker, ERROR bad input with
the reason, and each eye's own verdict (keys: :class:`calibration_interfaces.outcome.FrameKey`).
With both eyes, one message per stereo pair, expressed in the left camera frame.
A frame whose stamp equals the previous frame's of the same eye is dropped (same evidence).
Warnings about bad input are throttled per kind of problem (one per kind every 2 s), not per
call site, so a burst of one kind does not hide another.

Parameters
----------
Declared from :class:`marker_detector.detector_node.DetectorNodeSettings` (robot, stereo,
transport, Bayer demosaicing and white-balance gains, camera_info_url),
:class:`calibration_interfaces.noise.NoiseSettings` and
:class:`~calibration_interfaces.noise.PoseDependentSettings` (``noise_model``: ``pose_dependent``
| ``constant``, and their coefficients: by default the robot description's fitted law) and
:class:`marker_detector.detection.DetectorConfig`
(detection and gating). docs/nodes/detector.md lists them with defaults and ranges;
``calibration_bringup/config/detector.yaml`` sets a run's values.
use_sim_time (bool, built in): stamps come from the image headers anyway.

No services.
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from numpy.typing import NDArray
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from body_schema import load_robot
from calibration_interfaces.camera_info_file import CameraInfoFile, camera_info_differences, read_camera_info
from calibration_interfaces.contract import IMAGE_TRANSPORTS, SENSOR, image_topic
from calibration_interfaces.image_conversion import DEMOSAICING, ImageConversionError, check_gains
from calibration_interfaces.messages import matrix_to_pose_msg, pose_msg_to_matrix
from calibration_interfaces.node_util import WarnOnce, WarnThrottled, declare_settings, qos_profile, spin_node
from calibration_interfaces.noise import NoiseSettings, PoseDependentSettings
from calibration_interfaces.outcome import DETECTOR_DIAGNOSTIC, FrameStatus, encode_frame
from calibration_interfaces.parameters import setting

from .detection import BadInput, DetectorConfig, FrameResult, HandPoseEstimator
from .frame import DISTORTION_MODELS, CameraCalibration, calibration_from_info, judge_frame
from .stereo import EyeResult, StereoPairer, combine, pair_status

__all__ = ['DetectorNode', 'DetectorNodeSettings', 'main']


@dataclass(frozen=True)
class DetectorNodeSettings:
    """The detector node's own parameters (the rest: noise settings and DetectorConfig)."""

    robot: str = setting('icub_right_arm', 'Packaged robot name or path of a robot YAML')
    use_right_eye: bool = setting(False, 'Also process the right eye: a stamp both eyes see gives one hand pose '
                                  'from both images\' marker corners (a robot with eyes; ignored for a fixed camera)')
    stereo_timeout: float = setting(0.5, 'Seconds one eye waits for the other eye of the same stamp', (0.0, 10.0))
    transport: str = setting('raw', 'Image transport: raw (camera/<eye>/image_raw, sensor_msgs/Image) or compressed '
                             '(camera/<eye>/image_raw/compressed, JPEG or PNG)', choices=IMAGE_TRANSPORTS)
    demosaicing: str = setting('vng', 'Demosaicing of Bayer images: vng (corners closest to a colour camera\'s of '
                               'the interpolations, tools/encoding_bench.py), edge_aware, bilinear (cv_bridge\'s, '
                               'the fastest), or mosaic (every photosite read as grey, no interpolation: exact on '
                               'the black-and-white marker for a white-balanced sensor, docs/nodes/detector.md)',
                               choices=DEMOSAICING)
    bayer_gains: tuple[float, ...] = setting((1.0, 1.0, 1.0), 'With demosaicing mosaic: white-balance gains of the '
                                             'red, green and blue sites, for a camera that does not balance its raw '
                                             'data (measured on a white sheet with '
                                             'calibration_interfaces.image_conversion.mosaic_gains); 1 1 1: as sent')
    camera_info_url: str = setting('', 'Left (or only) camera\'s intrinsics from a camera_info_manager YAML file '
                                   '(ost.yaml; file://, package:// or a path) instead of its camera_info topic; '
                                   'empty = the topic')
    right_camera_info_url: str = setting('', 'The same for the right eye (with use_right_eye); empty = its topic')


def _stamp_key(stamp: Any) -> tuple[int, int]:
    return int(stamp.sec), int(stamp.nanosec)


class _Eye:
    """Latest calibration and pose of one eye."""

    def __init__(self, name: str, file: CameraInfoFile | None = None) -> None:
        self.name = name
        # The latest camera_info decides (a camera sends one with every frame): usable, or why not;
        # a calibration file decides instead when there is one (the topic is only compared).
        self.file = file
        self.calibration: CameraCalibration | BadInput = BadInput(
            'camera_info.missing', f'no camera_info for the {name} eye yet')
        if file is not None:
            self.calibration = calibration_from_info(file.k.reshape(-1), file.d, file.width, file.height)
        self.file_differs = False
        self.root_T_cam: NDArray[np.float64] | None = None
        self.last_stamp: tuple[int, int] | None = None

    @property
    def k(self) -> NDArray[np.float64] | None:
        """The usable camera matrix (3, 3), None while the calibration is missing or bad."""
        return self.calibration.k if isinstance(self.calibration, CameraCalibration) else None


class DetectorNode(Node):
    """See the module docstring for topics and parameters."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('marker_detector', **kwargs)
        s = declare_settings(self, DetectorNodeSettings)
        self.noise = declare_settings(self, NoiseSettings)
        pdn = declare_settings(self, PoseDependentSettings)
        config = declare_settings(self, DetectorConfig)
        self.model = load_robot(s.robot)
        self.estimator = HandPoseEstimator(self.model, self.noise.build(self.model, pdn), config)
        self.root_frame = self.model.root_frame
        # A fixed camera has no right eye: the parameter files' stereo default is the iCub's.
        self.stereo = s.use_right_eye and self.model.eyes is not None
        if s.use_right_eye and not self.stereo:
            self.get_logger().info(f'use_right_eye ignored: robot {self.model.name} has a fixed camera, no eyes')
        self.demosaicing = s.demosaicing
        try:
            self.bayer_gains = check_gains(s.bayer_gains)
        except ImageConversionError as exc:
            raise ValueError(f'bayer_gains must be three positive numbers (red, green, blue), '
                             f'got {list(s.bayer_gains)}') from exc
        self._warn_once = WarnOnce(self)
        self._warn = WarnThrottled(self)
        self.frames_processed = 0
        self.frame_counts = {s: 0 for s in FrameStatus}     # published verdicts, for tests and logs
        urls = {'left': s.camera_info_url, 'right': s.right_camera_info_url}
        self.eyes = {name: _Eye(name, read_camera_info(urls[name]) if urls[name] else None)
                     for name in (('left', 'right') if self.stereo else ('left',))}
        image_type = Image if s.transport == 'raw' else CompressedImage
        self.pairer = StereoPairer(tuple(self.eyes), s.stereo_timeout)
        self.pub_hand = self.create_publisher(PoseWithCovarianceStamped, 'hand_pose', qos_profile('/hand_pose'))
        self.pub_markers = self.create_publisher(PoseArray, 'markers', qos_profile('/markers'))
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', qos_profile('/diagnostics'))
        for name, eye in self.eyes.items():
            # A relative name (no leading /), so a namespace or a remap points it at a real camera.
            self.create_subscription(image_type, image_topic(name, s.transport).lstrip('/'),
                                     lambda m, e=eye: self._on_image(e, m), qos_profile(SENSOR))
            # Best effort matches both reliable and best-effort camera_info publishers.
            self.create_subscription(CameraInfo, f'camera/{name}/camera_info',
                                     lambda m, e=eye: self._on_info(e, m), qos_profile(SENSOR))
            self.create_subscription(PoseStamped, f'camera/{name}/pose',
                                     lambda m, e=eye: self._on_pose(e, m), qos_profile(f'/camera/{name}/pose'))
        if self.stereo:
            self.create_timer(0.05, self._flush_stale)
        self.get_logger().info(
            f'marker_detector: robot {self.model.name}, markers '
            f'{[m.marker_id for m in self.model.markers]}, noise {self.noise.noise_model}, fusion {config.fusion}, '
            f'eyes {list(self.eyes)}, transport {s.transport}')
        for eye in self.eyes.values():
            if eye.file is not None:
                self._check_model(eye, eye.file.distortion_model, bool(eye.file.d.size))
                self.get_logger().info(
                    f'{eye.name} eye: intrinsics from {eye.file.source} ({eye.file.camera_name or "unnamed"}, '
                    f'{eye.file.width} x {eye.file.height}, fx {eye.file.k[0, 0]:g}); its camera_info topic is '
                    f'only compared with them')

    # ------------------------------------------------------------------ inputs

    def _check_model(self, eye: _Eye, model: str, has_distortion: bool) -> None:
        if has_distortion and model not in DISTORTION_MODELS:
            self._warn_once(f'distmodel-{eye.name}', f'{eye.name} camera_info: distortion model '
                            f'{model!r} treated as plumb_bob')

    def _on_info(self, eye: _Eye, msg: CameraInfo) -> None:
        if eye.file is not None:
            # The file decides; say once if the driver's camera_info tells another story.
            if not eye.file_differs:
                diff = camera_info_differences(eye.file, msg.width, msg.height, msg.k, msg.d, msg.distortion_model)
                if diff:
                    eye.file_differs = True
                    self.get_logger().warning(
                        f'{eye.name} camera_info topic disagrees with {eye.file.source} ({"; ".join(diff)}); '
                        f'the file is used')
            return
        try:
            eye.calibration = calibration_from_info(msg.k, msg.d, msg.width, msg.height)
        except BadInput as exc:
            eye.calibration = exc
            self._warn(f'{eye.name}.{exc.kind}', f'{eye.name} camera_info rejected: {exc}; its frames are '
                       f'bad input until a valid one arrives')
            return
        self._check_model(eye, msg.distortion_model, bool(len(msg.d)))

    def _on_pose(self, eye: _Eye, msg: PoseStamped) -> None:
        try:
            root_T_cam = pose_msg_to_matrix(msg.pose)
        except ValueError as exc:
            self._warn(f'{eye.name}.pose', f'{eye.name} camera pose ignored (the previous one stays): {exc}')
            return
        eye.root_T_cam = root_T_cam
        if msg.header.frame_id and msg.header.frame_id != self.root_frame:
            self._warn_once(f'poseframe-{eye.name}', f'{eye.name} camera pose is in '
                            f'{msg.header.frame_id!r}, expected {self.root_frame!r}; used as is')

    def _on_image(self, eye: _Eye, msg: Image | CompressedImage) -> None:
        key = _stamp_key(msg.header.stamp)
        if key == eye.last_stamp:
            # A re-sent frame is the same evidence, not a second observation.
            self.get_logger().debug(f'{eye.name} frame {key} already processed; dropped')
            return
        t0 = time.perf_counter()
        if eye.root_T_cam is None:
            result = FrameResult(bad_input=BadInput('pose.missing', f'no camera pose for the {eye.name} eye yet'))
        else:
            try:
                result = judge_frame(self.estimator, msg, eye.calibration, eye.root_T_cam, self.demosaicing,
                                     self.bayer_gains)
            except Exception as exc:  # noqa: BLE001 (OpenCV surprises must not kill the node)
                # Not evidence about the hand either way: a frame nobody could judge.
                result = FrameResult(bad_input=BadInput(f'internal.{type(exc).__name__}',
                                                        f'image processing failed: {exc}'))
        if result.bad_input is None:
            eye.last_stamp = key       # judged: a re-send of this stamp is no new evidence
        else:
            self._warn(f'{eye.name}.{result.bad_input.kind}', f'{eye.name} image at {msg.header.stamp.sec}.'
                       f'{msg.header.stamp.nanosec:09d} not usable: {result.bad_input}')
        self.frames_processed += 1
        self.get_logger().debug(f'{eye.name} frame: {len(result.markers)} markers, {result.status.value}, '
                                f'{1e3 * (time.perf_counter() - t0):.2f} ms')
        item = EyeResult(eye.name, msg.header, result, eye.root_T_cam, time.monotonic())
        entry = self.pairer.add(key, item)
        if entry is not None:
            self._publish(entry)

    def _flush_stale(self) -> None:
        for entry in self.pairer.stale(time.monotonic()):
            self._publish(entry)

    # ------------------------------------------------------------------ outputs

    def _publish(self, entry: dict[str, EyeResult]) -> None:
        # /markers is expressed in the left camera frame (the right eye's too), so one message
        # per stereo pair tells the selector whether the attempt succeeded.
        header, marker_poses, hand = combine(entry, estimator=self.estimator)
        status = pair_status(entry)
        self._diagnose(header, status, entry)
        if status is FrameStatus.BAD_INPUT:
            return            # not a detection attempt: /markers stays silent
        markers = PoseArray()
        markers.header.stamp = header.stamp
        markers.header.frame_id = header.frame_id
        markers.poses = [matrix_to_pose_msg(m) for m in marker_poses]
        self.pub_markers.publish(markers)
        if hand is None:
            return
        out = PoseWithCovarianceStamped()
        out.header.stamp = header.stamp
        out.header.frame_id = self.root_frame
        out.pose.pose = matrix_to_pose_msg(hand.pose)
        out.pose.covariance = [float(v) for v in np.asarray(hand.covariance, dtype=float).reshape(36)]
        self.pub_hand.publish(out)

    def _diagnose(self, header: Any, status: FrameStatus, entry: dict[str, EyeResult]) -> None:
        self.frame_counts[status] += 1
        bad = [item.result.bad_input for item in entry.values() if item.result.bad_input is not None]
        message = {FrameStatus.DETECTED: 'hand detected', FrameStatus.NO_MARKER: 'no marker accepted',
                   FrameStatus.BAD_INPUT: '; '.join(f'{i.eye}: {i.result.bad_input}' for i in entry.values()
                                                    if i.result.bad_input is not None)}[status]
        # Each eye's own verdict too: the selector learns where each eye sees the hand.
        values = encode_frame(status, header.stamp.sec + header.stamp.nanosec * 1e-9,
                              ' '.join(b.kind for b in bad) if status is FrameStatus.BAD_INPUT else '',
                              {name: item.result.status for name, item in entry.items()})
        diag = DiagnosticArray()
        diag.header.stamp = header.stamp
        diag.header.frame_id = header.frame_id
        diag.status = [DiagnosticStatus(level=bytes([status.level]), name=DETECTOR_DIAGNOSTIC, message=message,
                                        hardware_id='+'.join(entry), values=[KeyValue(key=k, value=v)
                                                                             for k, v in values.items()])]
        self.pub_diagnostics.publish(diag)


def main(args: list[str] | None = None) -> None:
    spin_node(DetectorNode, args)


if __name__ == '__main__':
    main()
