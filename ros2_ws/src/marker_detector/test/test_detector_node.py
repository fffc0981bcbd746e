"""The detector node in-process: a synthetic camera publishes, a probe listens."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from body_schema import load_robot
from body_schema.kinematics import rotation_angle_deg
from body_schema.noise import PoseDependentNoise, view_geometry
from calibration_interfaces.messages import matrix_to_pose_msg, pose_msg_to_matrix
from calibration_interfaces.node_util import qos_profile
from marker_detector.detector_node import DetectorNode
from marker_detector.image_conversion import array_to_image_fields
from marker_detector.synthetic import look_at_pose, render_markers

SENSOR_QOS = 5


@pytest.fixture(scope='module')
def model():
    return load_robot('icub_right_arm')


Q = np.radians([-50.0, 60.0, 70.0, 45.0, 10.0, -30.0, 5.0])


def _camera_poses(model) -> dict[str, np.ndarray]:
    """Eyes 6.8 cm apart that see the palm marker at ~0.3 m and ~35 deg.

    Built from the hand pose rather than the description's head pose, so the test does not move
    when the head pose or calibration box are re-measured.
    """
    cam_T_marker = look_at_pose(0.3, 35.0, axis=(0.6, 0.8, 0.0), offset=(0.034, 0.0), spin_deg=20)
    left = model.forward_kinematics(Q) @ model.markers[0].hand_T_marker @ np.linalg.inv(cam_T_marker)
    right = left.copy()
    right[:3, 3] += 0.068 * left[:3, 0]
    return {'left': left, 'right': right}


class Camera:
    """Publishes what the simulator would for the left eye."""

    def __init__(self, ros: Any, model, eye: str = 'left') -> None:
        self.node = ros.node(f'fake_camera_{eye}')
        self.model, self.eye = model, eye
        self.root_T_cam = _camera_poses(model)[eye]
        self.image = self.node.create_publisher(Image, f'/camera/{eye}/image_raw', SENSOR_QOS)
        self.info = self.node.create_publisher(CameraInfo, f'/camera/{eye}/camera_info', SENSOR_QOS)
        self.pose = self.node.create_publisher(PoseStamped, f'/camera/{eye}/pose', qos_profile(f'/camera/{eye}/pose'))

    def publish_pose(self) -> None:
        msg = PoseStamped()
        msg.header.frame_id = 'root_link'
        msg.pose = matrix_to_pose_msg(self.root_T_cam)
        self.pose.publish(msg)

    def publish_info(self) -> None:
        cam = self.model.camera
        msg = CameraInfo()
        msg.header.frame_id = f'{self.eye}_eye_optical'
        msg.width, msg.height = cam.width, cam.height
        msg.distortion_model = 'plumb_bob'
        msg.d = [0.0] * 5
        msg.k = cam.K.reshape(-1).tolist()
        msg.p = np.c_[cam.K, np.zeros(3)].reshape(-1).tolist()
        self.info.publish(msg)

    def render(self, q: np.ndarray) -> np.ndarray:
        root_T_cam = self.root_T_cam
        hand = self.model.forward_kinematics(q)
        shown = []
        for m in self.model.markers:
            cam_T_m = np.linalg.inv(root_T_cam) @ hand @ m.hand_T_marker
            if view_geometry(np.eye(4), cam_T_m)[1] < 85:
                shown.append((m.marker_id, cam_T_m))
        cam = self.model.camera
        gray = render_markers(cam.K, (cam.width, cam.height), shown, self.model.marker_side_length,
                              noise_sigma=1.0, seed=1)
        return np.repeat(gray[..., None], 3, axis=2)

    def publish_image(self, rgb: np.ndarray | None = None, sec: int = 1, **override: Any) -> None:
        msg = Image()
        msg.header.stamp.sec = sec
        msg.header.frame_id = f'{self.eye}_eye_optical'
        if rgb is not None:
            for k, v in array_to_image_fields(rgb, 'rgb8').items():
                setattr(msg, k, v)
        for k, v in override.items():
            setattr(msg, k, v)
        self.image.publish(msg)


class Probe:
    def __init__(self, ros: Any) -> None:
        self.node = ros.node('probe')
        self.hands: list[PoseWithCovarianceStamped] = []
        self.markers: list[PoseArray] = []
        self.node.create_subscription(PoseWithCovarianceStamped, '/hand_pose', self.hands.append, 10)
        self.node.create_subscription(PoseArray, '/markers', self.markers.append, 10)


def _detector(ros: Any, **params: Any) -> DetectorNode:
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return ros.add(DetectorNode(context=ros.context, parameter_overrides=overrides))


def _wait_connected(ros: Any, cam: Camera, det: DetectorNode, probe: Probe) -> None:
    ros.spin_until(lambda: cam.image.get_subscription_count() >= 1
                   and cam.info.get_subscription_count() >= 1
                   and det.pub_markers.get_subscription_count() >= 1
                   and det.pub_hand.get_subscription_count() >= 1, 10.0, 'discovery')


def test_detects_hand_and_publishes_contract(ros: Any, model) -> None:
    q = Q
    cam, probe = Camera(ros, model), Probe(ros)
    cam.publish_pose()                      # latched before the detector exists: late joiner
    det = _detector(ros, use_sim_time=True)
    _wait_connected(ros, cam, det, probe)
    ros.spin_until(lambda: det.eyes['left'].root_T_cam is not None, 5.0, 'latched camera pose')
    rgb = cam.render(q)

    def send_and_check() -> bool:
        # A simulator sends camera_info with every frame; best effort may drop early messages.
        cam.publish_info()
        cam.publish_image(rgb, sec=7)
        return len(probe.hands) > 0

    ros.spin_until(send_and_check, 10.0, '/hand_pose')
    ros.spin_for(0.2)
    assert len(probe.hands) == 1, 're-sent frames of one stamp must count once'
    hand = probe.hands[-1]
    assert hand.header.frame_id == 'root_link' and hand.header.stamp.sec == 7
    truth = model.forward_kinematics(q)
    est = pose_msg_to_matrix(hand.pose.pose)
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 0.006
    assert rotation_angle_deg(est[:3, :3], truth[:3, :3]) < 2.0
    cov = np.array(hand.pose.covariance).reshape(6, 6)
    cam_T_m = np.linalg.inv(cam.root_T_cam) @ truth @ model.markers[0].hand_T_marker
    r, phi = view_geometry(np.eye(4), cam_T_m)
    np.testing.assert_allclose(cov, PoseDependentNoise().covariance(r, phi), rtol=0.05)
    ros.spin_until(lambda: any(len(m.poses) == 1 for m in probe.markers), 5.0, '/markers')
    marker = next(m for m in probe.markers if len(m.poses) == 1)
    assert marker.header.frame_id == 'left_eye_optical' and marker.header.stamp.sec == 7
    np.testing.assert_allclose(pose_msg_to_matrix(marker.poses[0])[:3, 3], cam_T_m[:3, 3], atol=0.006)


def test_bad_and_empty_frames_are_failed_outcomes(ros: Any, model) -> None:
    cam, probe = Camera(ros, model), Probe(ros)
    det = _detector(ros, noise_model='constant')
    _wait_connected(ros, cam, det, probe)
    # No camera_info or pose yet: frames are skipped (no outcome), with one warning.
    cam.publish_image(np.zeros((240, 320, 3), np.uint8), sec=1)
    ros.spin_until(lambda: 'noinfo-left' in det._warn_once.keys, 5.0, 'missing camera_info warning')
    assert probe.markers == []
    cam.publish_pose()
    ros.spin_until(lambda: det.eyes['left'].root_T_cam is not None, 5.0, 'camera pose')
    ros.spin_until(lambda: (cam.publish_info(), det.eyes['left'].k is not None)[1], 5.0, 'camera_info')
    bad = [
        dict(rgb=np.zeros((240, 320, 3), np.uint8)),                              # empty scene
        dict(rgb=np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)),
        dict(rgb=np.zeros((240, 320, 3), np.uint8), encoding='rgba16'),           # bad encoding
        dict(rgb=np.zeros((240, 320, 3), np.uint8), data=b'\x00' * 100),          # truncated
        dict(rgb=np.zeros((240, 320, 3), np.uint8), step=10),                     # bad step
        dict(rgb=None),                                                           # empty message
        dict(rgb=np.zeros((120, 160, 3), np.uint8)),                              # size != info
    ]
    for i, kw in enumerate(bad):
        stamp = 100 + i
        ros.spin_until(lambda: (cam.publish_image(sec=stamp, **kw),
                                any(m.header.stamp.sec == stamp for m in probe.markers))[1],
                       5.0, f'failed outcome for bad frame {i}')
    assert all(len(m.poses) == 0 for m in probe.markers)
    assert probe.hands == []
    assert det.context.ok()


def test_constant_noise_and_invalid_parameters(ros: Any, model) -> None:
    det = _detector(ros, noise_model='constant', cn_sigma_pos=0.004, cn_sigma_rot_deg=1.5)
    np.testing.assert_allclose(det.estimator.noise.variances(0.3, 10.0),
                               (0.004 ** 2, np.radians(1.5) ** 2))
    desc = det.describe_parameter('max_reprojection_error_px')
    assert desc.description and desc.floating_point_range
    with pytest.raises(ValueError, match='noise_model'):
        DetectorNode(context=ros.context, parameter_overrides=[Parameter('noise_model', value='gauss')])


def test_stereo_pair_gives_one_fused_outcome(ros: Any, model) -> None:
    q = Q
    left, right, probe = Camera(ros, model, 'left'), Camera(ros, model, 'right'), Probe(ros)
    left.publish_pose()
    right.publish_pose()
    det = _detector(ros, use_right_eye=True, stereo_timeout=0.3)
    _wait_connected(ros, left, det, probe)
    ros.spin_until(lambda: all(e.root_T_cam is not None for e in det.eyes.values()), 5.0, 'poses')
    ros.spin_until(lambda: (left.publish_info(), right.publish_info(),
                            all(e.k is not None for e in det.eyes.values()))[-1], 5.0, 'infos')
    images = {'left': left.render(q), 'right': right.render(q)}
    assert det.estimator.process(images['right'][..., 0], model.camera.K, None,
                                 right.root_T_cam).success, 'the right eye must see it too'

    def send(stamp: int, eyes: tuple[str, ...]) -> bool:
        for cam in (left, right):
            if cam.eye in eyes:
                cam.publish_image(images[cam.eye], sec=stamp)
        return any(m.header.stamp.sec == stamp for m in probe.markers)

    ros.spin_until(lambda: send(20, ('left', 'right')), 10.0, 'stereo outcome')
    ros.spin_for(0.2)
    pair = [m for m in probe.markers if m.header.stamp.sec == 20]
    hands = [h for h in probe.hands if h.header.stamp.sec == 20]
    assert len(pair) == 1 and len(pair[0].poses) == 2 and len(hands) == 1
    cov = np.array(hands[0].pose.covariance).reshape(6, 6)
    left_only = det.estimator.process(images['left'][..., 0], model.camera.K, None,
                                      left.root_T_cam).hand
    assert cov[0, 0] < left_only.pos_var                   # two eyes know more than one
    # Both markers in /markers are in the left camera frame: the same marker twice, nearly equal.
    a, b = (pose_msg_to_matrix(p)[:3, 3] for p in pair[0].poses)
    assert np.linalg.norm(a - b) < 0.01
    truth = model.forward_kinematics(q)
    assert np.linalg.norm(pose_msg_to_matrix(hands[0].pose.pose)[:3, 3] - truth[:3, 3]) < 0.006
    # Only the left eye: after the timeout the frame is decided alone.
    ros.spin_until(lambda: send(21, ('left',)), 10.0, 'left-only outcome after the stereo timeout')
