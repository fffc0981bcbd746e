"""The detector node in-process: a synthetic camera publishes, a probe listens."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from body_schema import load_robot
from body_schema.kinematics import rotation_angle_deg
from body_schema.noise import PoseDependentNoise, view_geometry
from calibration_interfaces.camera_info_file import CameraInfoFile, CameraInfoFileError, write_camera_info
from calibration_interfaces.image_conversion import array_to_image_fields, compress, encode_rgb, rgb_to_image_fields
from calibration_interfaces.messages import matrix_to_pose_msg, pose_msg_to_matrix
from calibration_interfaces.node_util import qos_profile
from calibration_interfaces.outcome import DETECTOR_DIAGNOSTIC, FrameReport, FrameStatus, decode_frame
from marker_detector.detector_node import DetectorNode
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

    def publish_image(self, rgb: np.ndarray | None = None, sec: int = 1, nanosec: int = 0, **override: Any) -> None:
        msg = Image()
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
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
    # The description's own law (the iCub's noise_model block), not the built-in one.
    np.testing.assert_allclose(cov, PoseDependentNoise.for_robot(model).covariance(r, phi), rtol=0.05)
    ros.spin_until(lambda: any(len(m.poses) == 1 for m in probe.markers), 5.0, '/markers')
    marker = next(m for m in probe.markers if len(m.poses) == 1)
    assert marker.header.frame_id == 'left_eye_optical' and marker.header.stamp.sec == 7
    np.testing.assert_allclose(pose_msg_to_matrix(marker.poses[0])[:3, 3], cam_T_m[:3, 3], atol=0.006)


def _assert_near_truth(model, hand: PoseWithCovarianceStamped, q: np.ndarray) -> None:
    truth = model.forward_kinematics(q)
    est = pose_msg_to_matrix(hand.pose.pose)
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 0.006
    assert rotation_angle_deg(est[:3, :3], truth[:3, :3]) < 2.0


@pytest.mark.parametrize('encoding, codec', [('bayer_rggb8', ''), ('yuv422', ''), ('rgb8', 'jpeg')])
def test_camera_encodings_and_the_compressed_transport(ros: Any, model, encoding: str, codec: str) -> None:
    """A Bayer or YUV camera, or image_transport's compressed topic (transport: compressed),
    gives the hand pose an rgb8 camera gives."""
    cam, probe = Camera(ros, model), Probe(ros)
    cam.publish_pose()
    det = _detector(ros, transport='compressed' if codec else 'raw')
    pub = cam.node.create_publisher(CompressedImage, '/camera/left/image_raw/compressed', SENSOR_QOS) \
        if codec else cam.image
    ros.spin_until(lambda: pub.get_subscription_count() >= 1 and det.pub_hand.get_subscription_count() >= 1
                   and det.eyes['left'].root_T_cam is not None, 10.0, 'discovery')
    assert cam.image.get_subscription_count() == (0 if codec else 1)     # one transport only
    rgb = cam.render(Q)

    def send() -> bool:
        cam.publish_info()
        msg = CompressedImage() if codec else Image()
        msg.header.stamp.sec = 3
        fields = (compress(encode_rgb(rgb, encoding), encoding, codec, jpeg_quality=90) if codec
                  else rgb_to_image_fields(rgb, encoding))
        for k, v in fields.items():
            setattr(msg, k, v)
        pub.publish(msg)
        return len(probe.hands) > 0

    ros.spin_until(send, 10.0, f'/hand_pose from {encoding} {codec or "raw"}')
    _assert_near_truth(model, probe.hands[-1], Q)


def test_intrinsics_from_a_calibration_file(ros: Any, model, tmp_path, monkeypatch) -> None:
    """camera_info_url: the file's intrinsics are used from the start, without any camera_info
    topic; a driver's camera_info that disagrees is named once (what differs) and ignored."""
    k = model.camera
    path = write_camera_info(tmp_path / 'ost.yaml', CameraInfoFile(k.width, k.height, k.K, camera_name='left'))
    cam, probe = Camera(ros, model), Probe(ros)
    cam.publish_pose()
    det = _detector(ros, camera_info_url=f'file://{path}')
    logged = _Logged()
    monkeypatch.setattr(det, 'get_logger', lambda: logged)
    np.testing.assert_array_equal(det.eyes['left'].k, k.K)
    ros.spin_until(lambda: cam.image.get_subscription_count() >= 1 and det.pub_hand.get_subscription_count() >= 1
                   and det.eyes['left'].root_T_cam is not None, 10.0, 'discovery')
    rgb = cam.render(Q)
    ros.spin_until(lambda: (cam.publish_image(rgb, sec=5), len(probe.hands) > 0)[1], 10.0, 'hand without camera_info')
    _assert_near_truth(model, probe.hands[-1], Q)

    def publish_wrong() -> None:
        msg = CameraInfo(width=640, height=480, distortion_model='plumb_bob', d=[0.0] * 5,
                         k=(k.K * [[2.0], [2.0], [1.0]]).reshape(-1).tolist())
        cam.info.publish(msg)

    ros.spin_until(lambda: (publish_wrong(), len(logged.warnings) > 0)[1], 5.0, 'a warning about camera_info')
    for _ in range(5):
        publish_wrong()
        ros.spin_for(0.02)
    assert len(logged.warnings) == 1, logged.warnings
    assert 'size: 320 x 240 in the file vs 640 x 480' in logged.warnings[0] and 'fx 257.34' in logged.warnings[0]
    assert str(path) in logged.warnings[0]
    np.testing.assert_array_equal(det.eyes['left'].k, k.K)             # the file still decides
    ros.spin_until(lambda: (cam.publish_image(rgb, sec=6), any(h.header.stamp.sec == 6 for h in probe.hands))[1],
                   10.0, 'hand after the wrong camera_info')
    with pytest.raises(CameraInfoFileError, match='nothing.yaml'):
        DetectorNode(context=ros.context, parameter_overrides=[
            Parameter('camera_info_url', value=f'file://{tmp_path}/nothing.yaml')])


class _Logged:
    """Records what the node logs (a stand-in for its rclpy logger)."""

    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warning(self, text: str, **_: Any) -> None:
        self.warnings.append(text)

    error = warning

    def info(self, text: str, **_: Any) -> None:
        pass

    debug = info


def test_bad_input_is_not_a_failed_detection(ros: Any, model, monkeypatch) -> None:
    """An empty or random scene is an explicit failed detection (empty /markers, WARN); a bad
    image, a missing or unusable camera_info, a missing camera pose publish no /markers and an
    ERROR diagnostic naming the problem, and every distinct problem is logged (on main they all
    came out as an empty /markers and a global throttle hid half of them)."""
    cam, probe = Camera(ros, model), Probe(ros)
    diags: list[DiagnosticArray] = []
    probe.node.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 100)
    det = _detector(ros, noise_model='constant')
    logged = _Logged()
    monkeypatch.setattr(det, 'get_logger', lambda: logged)
    _wait_connected(ros, cam, det, probe)
    ros.spin_until(lambda: det.pub_diagnostics.get_subscription_count() >= 1, 10.0, 'diagnostics discovery')

    def verdicts() -> dict[tuple[int, int], FrameReport]:
        out = {}
        for d in diags:
            for s in d.status:
                if s.name == DETECTOR_DIAGNOSTIC:
                    r = decode_frame({v.key: v.value for v in s.values})
                    assert s.level == bytes([r.status.level])
                    out[(d.header.stamp.sec, d.header.stamp.nanosec)] = r
        return out

    tries = iter(range(1, 10**6))

    def send(stamp: int, **kw: Any) -> FrameReport:
        # Best effort may drop a frame: re-send, each try with its own stamp (a re-sent stamp
        # would be judged anew once its inputs are fixed).
        ros.spin_until(lambda: (cam.publish_image(sec=stamp, nanosec=next(tries), **kw),
                                any(k[0] == stamp for k in verdicts()))[1], 5.0, f'verdict on frame {stamp}')
        return next(r for k, r in verdicts().items() if k[0] == stamp)

    zeros = np.zeros((240, 320, 3), np.uint8)
    # No camera pose, then no camera_info yet: bad input, not "not visible".
    assert send(1, rgb=zeros).kind == 'pose.missing'
    cam.publish_pose()
    ros.spin_until(lambda: det.eyes['left'].root_T_cam is not None, 5.0, 'camera pose')
    assert send(2, rgb=zeros).kind == 'camera_info.missing'
    ros.spin_until(lambda: (cam.publish_info(), det.eyes['left'].k is not None)[1], 5.0, 'camera_info')
    good = [dict(rgb=zeros), dict(rgb=np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8))]
    for i, kw in enumerate(good):
        r = send(10 + i, **kw)
        assert r.status is FrameStatus.NO_MARKER and r.eyes == {'left': FrameStatus.NO_MARKER}
    bad = [
        (dict(rgb=zeros, encoding='32FC1'), 'image.encoding'),       # a depth image
        (dict(rgb=zeros, data=b'\x00' * 100), 'image.data'),        # truncated
        (dict(rgb=zeros, step=10), 'image.step'),
        (dict(rgb=None), 'image.encoding'),                          # empty message
        (dict(rgb=np.zeros((120, 160, 3), np.uint8)), 'image.size'),  # size != camera_info
    ]
    for i, (kw, kind) in enumerate(bad):
        r = send(100 + i, **kw)
        assert (r.status, r.kind) == (FrameStatus.BAD_INPUT, kind)
    # A camera_info with NaN distortion, then one with a zero K: refused, frames are bad input.
    for i, (field, value, kind) in enumerate((('d', [float('nan')] + [0.0] * 4, 'camera_info.D'),
                                              ('k', [0.0] * 9, 'camera_info.K'))):
        original = cam.publish_info

        def publish_bad(field=field, value=value) -> None:
            msg = CameraInfo(width=320, height=240, distortion_model='plumb_bob', d=[0.0] * 5,
                             k=model.camera.K.reshape(-1).tolist())
            setattr(msg, field, value)
            cam.info.publish(msg)
        ros.spin_until(lambda: (publish_bad(), det.eyes['left'].k is None)[1], 5.0, f'bad {kind} taken')
        r = send(200 + i, rgb=zeros)
        assert (r.status, r.kind) == (FrameStatus.BAD_INPUT, kind)
        ros.spin_until(lambda: (original(), det.eyes['left'].k is not None)[1], 5.0, 'good camera_info again')
    ros.spin_for(0.2)
    bad_stamps = {k for k, r in verdicts().items() if r.status is FrameStatus.BAD_INPUT}
    assert {k[0] for k in bad_stamps} >= {1, 2} | {100 + i for i in range(len(bad))} | {200, 201}
    published = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in probe.markers}
    assert not published & bad_stamps, f'bad frames reached /markers: {sorted(published & bad_stamps)}'
    assert {k[0] for k in published} >= {10, 11}
    assert all(len(m.poses) == 0 for m in probe.markers) and probe.hands == []
    # Every distinct problem was logged, whatever the order and however fast they came.
    for kind in ('pose.missing', 'camera_info.missing', 'camera_info.D', 'camera_info.K',
                 *(k for _, k in bad)):
        assert any(f'{kind}:' in w for w in logged.warnings), (kind, logged.warnings)
    assert det.context.ok()


def test_constant_noise_and_invalid_parameters(ros: Any, model) -> None:
    det = _detector(ros, noise_model='constant', cn_sigma_pos=0.004, cn_sigma_rot_deg=1.5)
    np.testing.assert_allclose(det.estimator.noise.variances(0.3, 10.0),
                               (0.004 ** 2, np.radians(1.5) ** 2))
    desc = det.describe_parameter('max_reprojection_error_px')
    assert desc.description and desc.floating_point_range
    with pytest.raises(ValueError, match='noise_model'):
        DetectorNode(context=ros.context, parameter_overrides=[Parameter('noise_model', value='gauss')])
    with pytest.raises(ValueError, match=r'bayer_gains must be three positive numbers .*got \[1.0, -1.0, 1.0\]'):
        DetectorNode(context=ros.context, parameter_overrides=[Parameter('bayer_gains', value=[1.0, -1.0, 1.0])])
    assert _detector(ros, demosaicing='mosaic', bayer_gains=[2.2, 1.0, 1.4]).bayer_gains == (2.2, 1.0, 1.4)
    # A fixed camera has no right eye (its frames would each wait stereo_timeout for one): ignored.
    fixed = _detector(ros, robot='ur5e', use_right_eye=True)
    assert not fixed.stereo and list(fixed.eyes) == ['left']


def test_stereo_pair_gives_one_fused_outcome(ros: Any, model) -> None:
    q = Q
    left, right, probe = Camera(ros, model, 'left'), Camera(ros, model, 'right'), Probe(ros)
    diags: list[DiagnosticArray] = []
    probe.node.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 100)
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

    def eyes(stamp: int) -> dict[str, FrameStatus]:
        return next(dict(decode_frame({v.key: v.value for v in st.values}).eyes) for d in diags
                    for st in d.status if st.name == DETECTOR_DIAGNOSTIC and d.header.stamp.sec == stamp)

    # The verdict names each eye's own (the selector learns where each eye sees the hand).
    ros.spin_until(lambda: {d.header.stamp.sec for d in diags} >= {20, 21}, 5.0, 'both verdicts')
    assert eyes(20) == {'left': FrameStatus.DETECTED, 'right': FrameStatus.DETECTED}
    assert eyes(21) == {'left': FrameStatus.DETECTED}
