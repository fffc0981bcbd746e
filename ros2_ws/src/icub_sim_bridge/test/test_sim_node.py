"""The sim node in-process with a probe node: topics, motion, image layout, bad commands."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from body_schema.robot import load_robot
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from calibration_interfaces.image_conversion import compress, compressed_to_array, image_to_array
from icub_sim_bridge import sim_node
from icub_sim_bridge.sim_node import SimNode

ROBOT = load_robot()
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def make_sim(ros, **params):
    defaults = dict(real_time_factor=0.0, image_rate=10.0, perturb_seed=5)
    defaults.update(params)
    overrides = [Parameter(k, value=v) for k, v in defaults.items()]
    return ros.add(SimNode(context=ros.context, parameter_overrides=overrides))


class Probe:
    """Collects the last message of every contract topic."""

    def __init__(self, ros) -> None:
        self.node = ros.node('probe')
        self.last: dict[str, object] = {}
        self.count: dict[str, int] = {}
        self.joint_states: list[JointState] = []
        topics = [('/clock', Clock, 10), ('/joint_states', JointState, 50),
                  ('/body_schema/true', Float64MultiArray, LATCHED)]
        for eye in ('left', 'right'):
            topics += [(f'/camera/{eye}/image_raw', Image, qos_profile_sensor_data),
                       (f'/camera/{eye}/camera_info', CameraInfo, LATCHED),
                       (f'/camera/{eye}/pose', PoseStamped, LATCHED)]
        for name, typ, qos in topics:
            self.node.create_subscription(typ, name, self._cb(name), qos)
        self.cmd = self.node.create_publisher(JointTrajectory, '/arm/command', 10)

    def _cb(self, name):
        def cb(msg):
            self.last[name] = msg
            self.count[name] = self.count.get(name, 0) + 1
            if name == '/joint_states':
                self.joint_states.append(msg)
        return cb

    def command(self, names, points, times=None) -> None:
        msg = JointTrajectory()
        msg.joint_names = list(names)
        for k, p in enumerate(points):
            pt = JointTrajectoryPoint(positions=[float(v) for v in p])
            if times is not None:
                pt.time_from_start = Duration(sec=int(times[k]), nanosec=int((times[k] % 1) * 1e9))
            msg.points.append(pt)
        self.cmd.publish(msg)

    def q(self) -> np.ndarray:
        return np.array(self.last['/joint_states'].position)

    def sim_time(self) -> float:
        c = self.last['/clock'].clock
        return c.sec + c.nanosec * 1e-9


def test_every_contract_topic_appears_with_the_right_content(ros) -> None:
    sim = make_sim(ros)
    probe = Probe(ros)
    want = {'/clock', '/joint_states', '/body_schema/true'} | {
        f'/camera/{e}/{t}' for e in ('left', 'right') for t in ('image_raw', 'camera_info', 'pose')}
    ros.spin_until(lambda: want <= set(probe.last) and probe.count.get('/camera/left/image_raw', 0) >= 2,
                   20.0, f'all contract topics; got {sorted(probe.last)}')
    types = dict(sim.get_topic_names_and_types())
    assert types['/arm/command'] == ['trajectory_msgs/msg/JointTrajectory']
    assert types['/camera/left/image_raw'] == ['sensor_msgs/msg/Image']

    js = probe.last['/joint_states']
    assert list(js.name) == list(ROBOT.joint_names)
    true = probe.last['/body_schema/true']
    assert [d.label for d in true.layout.dim] == ['joints', 'params']
    assert [d.size for d in true.layout.dim] == [7, 4]
    table = np.array(true.data).reshape(7, 4)
    np.testing.assert_allclose(table, sim.true_dh)
    assert 0 < np.abs(table - ROBOT.dh).max() < np.radians(1.01)   # the small seeded perturbation

    info = probe.last['/camera/left/camera_info']
    assert info.distortion_model == 'plumb_bob' and list(info.d) == [0.0] * 5
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), ROBOT.camera.K)
    np.testing.assert_allclose(np.reshape(info.p, (3, 4))[:, :3], ROBOT.camera.K)
    np.testing.assert_allclose(np.reshape(info.r, (3, 3)), np.eye(3))

    pose = probe.last['/camera/left/pose']
    assert pose.header.frame_id == 'root_link'
    p = pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], ROBOT.camera_pose('left')[:3, 3], atol=1e-12)


def test_rgb8_layout_and_joint_state_rate(ros) -> None:
    make_sim(ros, image_width=640, image_height=480, cameras=['left'])
    probe = Probe(ros)
    ros.spin_until(lambda: '/camera/left/image_raw' in probe.last and len(probe.joint_states) > 60,
                   20.0, 'an image and 60 joint states')
    img = probe.last['/camera/left/image_raw']
    assert (img.encoding, img.width, img.height, img.step) == ('rgb8', 640, 480, 640 * 3)
    assert len(img.data) == img.step * img.height and img.is_bigendian == 0
    pixels = np.frombuffer(bytes(img.data), np.uint8).reshape(480, 640, 3)
    assert pixels.std() > 10          # a scene, not a blank frame
    info = probe.last['/camera/left/camera_info']
    assert (info.width, info.height) == (640, 480) and info.header.stamp == img.header.stamp
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in probe.joint_states])
    assert np.all(np.diff(stamps) > 0)
    assert np.median(np.diff(stamps)) <= 20_000_000          # >= 50 Hz in sim time


def test_a_bayer_camera_with_the_compressed_transport(ros, monkeypatch) -> None:
    """image_encoding: the render as a Bayer mosaic; compressed_format: image_raw/compressed as
    image_transport makes it from image_raw, encoded only while someone subscribes."""
    encoded = []
    monkeypatch.setattr(sim_node, 'compress', lambda *a, **k: (encoded.append(1), compress(*a, **k))[1])
    make_sim(ros, cameras=['left'], image_encoding='bayer_rggb8', compressed_format='png')
    probe = Probe(ros)
    raw: dict[tuple[int, int], Image] = {}
    probe.node.create_subscription(Image, '/camera/left/image_raw',
                                   lambda m: raw.__setitem__((m.header.stamp.sec, m.header.stamp.nanosec), m),
                                   qos_profile_sensor_data)
    ros.spin_until(lambda: len(raw) >= 3, 20.0, 'raw images')
    assert encoded == []                          # nobody subscribed to the compressed topic
    packed: list[CompressedImage] = []
    probe.node.create_subscription(CompressedImage, '/camera/left/image_raw/compressed', packed.append,
                                   qos_profile_sensor_data)
    ros.spin_until(lambda: any((p.header.stamp.sec, p.header.stamp.nanosec) in raw for p in packed), 20.0,
                   'a compressed image and its raw one')
    pair = next(p for p in packed if (p.header.stamp.sec, p.header.stamp.nanosec) in raw)
    img = raw[(pair.header.stamp.sec, pair.header.stamp.nanosec)]
    assert (img.encoding, img.step, img.width) == ('bayer_rggb8', 320, 320)
    mosaic = image_to_array(img)
    assert mosaic.shape == (240, 320) and mosaic.std() > 10
    assert pair.format == 'bayer_rggb8; png compressed ' and pair.header.frame_id == img.header.frame_id
    np.testing.assert_array_equal(compressed_to_array(pair), mosaic)           # PNG: the same mosaic
    np.testing.assert_array_equal(compressed_to_array(pair, 'rgb8'), image_to_array(img, 'rgb8'))
    with pytest.raises(ValueError, match='even'):
        SimNode(context=ros.context, parameter_overrides=[Parameter('image_encoding', value='yuyv'),
                                                          Parameter('image_width', value=321)])


def test_command_moves_arm_to_target_in_sim_time_at_bounded_speed(ros) -> None:
    sim = make_sim(ros, max_joint_speed_deg=60.0, image_rate=5.0)
    probe = Probe(ros)
    ros.spin_until(lambda: '/joint_states' in probe.last, 10.0, 'joint states')
    start = probe.q()
    target = start + np.radians([-10.0, 15.0, -20.0, 25.0, 10.0, -10.0, 5.0])
    t0 = probe.sim_time()
    probe.command(ROBOT.joint_names, [target])
    ros.spin_until(lambda: np.abs(probe.q() - target).max() < 1e-9, 20.0, 'the arm at its target')
    elapsed = probe.sim_time() - t0
    assert elapsed >= 25.0 / 60.0 - 0.02          # no joint faster than 60 deg/s
    assert elapsed < 25.0 / 60.0 + 0.5
    qs = np.array([m.position for m in probe.joint_states])
    dts = np.diff([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in probe.joint_states])
    speeds = np.abs(np.diff(qs, axis=0)) / dts[:, None]
    assert speeds.max() <= np.radians(60.0) * 1.001
    # Holds there.
    n = len(probe.joint_states)
    ros.spin_until(lambda: len(probe.joint_states) > n + 20, 10.0, 'more joint states')
    np.testing.assert_array_equal(probe.q(), target)
    np.testing.assert_allclose(sim.world.joint_positions(), target, atol=1e-12)


@pytest.mark.parametrize('names, points, what', [
    (['r_shoulder_pitch', 'r_knee'], [[-0.5, 0.1]], 'unknown joint names'),
    (['r_elbow'], [[float('nan')]], 'non-finite'),
    (['r_elbow'], [], 'empty trajectory'),
    (['r_elbow'], [[np.radians(150.0)]], 'outside the limits'),
])
def test_bad_commands_are_rejected_and_sim_keeps_running(ros, names, points, what) -> None:
    sim = make_sim(ros, image_rate=0.0)
    logged: list[str] = []
    original = sim.get_logger().warning
    sim.get_logger().warning = lambda msg, **kw: (logged.append(msg), original(msg, **kw))
    probe = Probe(ros)
    ros.spin_until(lambda: '/joint_states' in probe.last, 10.0, 'joint states')
    before = probe.q()
    t_before = probe.sim_time()
    probe.command(names, points)
    ros.spin_until(lambda: logged, 10.0, 'the rejection warning')
    assert what in logged[0] and 'rejected /arm/command' in logged[0]
    ros.spin_until(lambda: probe.sim_time() > t_before + 0.5, 10.0, 'sim time to go on')
    np.testing.assert_array_equal(probe.q(), before)
    # And a good command afterwards still works.
    target = before.copy()
    target[3] += 0.1
    probe.command(ROBOT.joint_names, [target])
    ros.spin_until(lambda: np.abs(probe.q() - target).max() < 1e-9, 10.0, 'the arm at a later target')


def test_real_time_factor_one_follows_the_wall_clock(ros) -> None:
    import time

    make_sim(ros, real_time_factor=1.0, image_rate=0.0)
    probe = Probe(ros)
    ros.spin_until(lambda: '/clock' in probe.last, 10.0, 'clock')
    s0, w0 = probe.sim_time(), time.monotonic()
    # Three wall seconds: the last /clock received can be a spin late at either end, which on a
    # loaded machine was 13% of a one-second window (rate 1.13).
    ros.spin_until(lambda: time.monotonic() - w0 > 3.0, 8.0, 'three wall seconds')
    rate = (probe.sim_time() - s0) / (time.monotonic() - w0)
    assert 0.8 < rate < 1.1


def test_projected_corners_match_detected_ones_over_the_wire(ros) -> None:
    """Everything from the messages: image, CameraInfo K, camera pose, true DH, joint state."""
    import cv2
    from scipy.spatial.transform import Rotation

    from body_schema.noise import view_geometry
    from body_schema.markers import aruco_dictionary, marker_corners, refine_corners_edges
    from icub_sim_bridge.camera import project_points

    make_sim(ros, supersample=2, cameras=['left'], max_joint_speed_deg=360.0)
    probe = Probe(ros)
    ros.spin_until(lambda: {'/camera/left/image_raw', '/camera/left/pose', '/body_schema/true',
                            '/camera/left/camera_info'} <= set(probe.last), 20.0, 'image, pose, K, DH')
    det = cv2.aruco.ArucoDetector(aruco_dictionary(ROBOT.marker_dictionary))
    p = probe.last['/camera/left/pose'].pose
    cam = np.eye(4)
    cam[:3, :3] = Rotation.from_quat([p.orientation.x, p.orientation.y, p.orientation.z,
                                      p.orientation.w]).as_matrix()
    cam[:3, 3] = [p.position.x, p.position.y, p.position.z]
    true = ROBOT.with_dh(np.reshape(probe.last['/body_schema/true'].data, (7, 4)))
    errors = []
    # Box configurations where a marker should face the eye within 35 deg (picked by FK).
    qs = np.random.default_rng(11).uniform(ROBOT.calibration_box[:, 0], ROBOT.calibration_box[:, 1], (400, 7))
    hands = true.forward_kinematics(qs)
    facing = np.zeros(len(qs), bool)
    for m in ROBOT.markers:
        _r, phi = view_geometry(cam, hands @ m.hand_T_marker)
        uv = project_points((hands @ m.hand_T_marker)[:, :3, 3], cam, ROBOT.camera.K)
        facing |= (phi < 35.0) & np.all((uv > 30) & (uv < [290, 210]), axis=1)
    for q in qs[facing][:4]:
        probe.command(ROBOT.joint_names, [q])
        ros.spin_until(lambda: np.abs(probe.q() - q).max() < 1e-9, 20.0, 'the arm at a test pose')
        stamp_after = probe.last['/joint_states'].header.stamp
        ros.spin_until(lambda: _t(probe.last['/camera/left/image_raw'].header.stamp) > _t(stamp_after),
                       10.0, 'an image taken after settling')
        img = probe.last['/camera/left/image_raw']
        K = np.reshape(probe.last['/camera/left/camera_info'].k, (3, 3))
        gray = cv2.cvtColor(np.frombuffer(bytes(img.data), np.uint8).reshape(img.height, img.width, 3),
                            cv2.COLOR_RGB2GRAY)
        corners, ids, _ = det.detectMarkers(gray)
        hand = true.forward_kinematics(q)
        for c, i in zip(corners if ids is not None else [], ids.ravel() if ids is not None else []):
            m = next(m for m in ROBOT.markers if m.marker_id == int(i))
            mk = hand @ m.hand_T_marker
            _r, phi = view_geometry(cam, mk)
            if phi < 45.0:
                obj = marker_corners(ROBOT.marker_side_length)
                uv = project_points(obj @ mk[:3, :3].T + mk[:3, 3], cam, K)
                refined = refine_corners_edges(gray, c.reshape(4, 2))
                assert refined is not None, f'no edge fit for marker {int(i)}'
                errors.append(np.abs(refined - uv).max())
    assert len(errors) >= 3, 'too few frontal detections'
    assert max(errors) < 0.5, errors


def _t(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def test_starts_from_the_estimators_exported_dh_file(ros, tmp_path) -> None:
    from calibration_interfaces.dh_file import write_dh_file

    rng = np.random.default_rng(11)
    calibrated = ROBOT.dh + rng.uniform(-0.002, 0.002, ROBOT.dh.shape)
    # What OnlineEstimator.export writes (a DH file with one-sigma and counters).
    path = write_dh_file(tmp_path / 'calibrated_dh.yaml', calibrated, ROBOT.joint_names, ROBOT.name,
                         np.full(ROBOT.dh.shape, 1e-3), extra={'updates': {'updates': 3}})
    sim = make_sim(ros, true_dh_file=str(path), perturb_seed=-1, image_rate=0.0)
    np.testing.assert_allclose(sim.true_dh, calibrated, atol=1e-12)


def test_a_missing_dh_file_is_named(ros, tmp_path) -> None:
    from calibration_interfaces.dh_file import DhFileError

    with pytest.raises(DhFileError, match='nope.yaml'):
        make_sim(ros, true_dh_file=str(tmp_path / 'nope.yaml'))


def test_the_body_changes_at_the_scheduled_command_and_the_truth_follows(ros) -> None:
    """body_change applied when the 2nd command arrives: /body_schema/true re-published with the
    increments, the rendered arm rebuilt, the arm still where it was; once only."""
    from std_srvs.srv import Trigger

    spec = 'r_wrist_prosup.d+0.010 r_shoulder_yaw.offset+3'
    sim = make_sim(ros, body_change=spec, body_change_at_command=2, cameras=['left'])
    probe = Probe(ros)
    ros.spin_until(lambda: '/body_schema/true' in probe.last and '/joint_states' in probe.last, 10.0, 'truth')
    before = np.array(probe.last['/body_schema/true'].data).reshape(7, 4)
    q0 = probe.q()
    probe.command(ROBOT.joint_names, [q0])                       # 1st command: nothing changes
    ros.spin_until(lambda: sim.commands == 1, 10.0, 'the first command')
    assert probe.count['/body_schema/true'] == 1 and not sim.body_changed
    target = q0 + np.radians(2.0)
    probe.command(ROBOT.joint_names, [target])                   # 2nd: the body changes, then it moves
    ros.spin_until(lambda: probe.count['/body_schema/true'] == 2, 10.0, 'the changed truth')
    after = np.array(probe.last['/body_schema/true'].data).reshape(7, 4)
    expected = before.copy()
    expected[4, 1] += 0.010
    expected[2, 3] += np.radians(3.0)
    np.testing.assert_allclose(after, expected, atol=1e-12)
    np.testing.assert_allclose(sim.world.dh, expected, atol=1e-12)
    ros.spin_until(lambda: np.abs(probe.q() - target).max() < 1e-9, 20.0, 'the arm at its target')
    # The rebuilt world's hand is where the changed table puts it (at the world's own joints: the
    # sim syncs them to the trajectory when it renders, not at every joint state).
    q_world = sim.world.joint_positions()
    np.testing.assert_allclose(sim.world.hand_pose(), ROBOT.with_dh(expected).forward_kinematics(q_world), atol=1e-6)
    # The service refuses a second application.
    client = probe.node.create_client(Trigger, '/icub_sim/apply_body_change')
    ros.spin_until(lambda: client.service_is_ready(), 10.0, 'the service')
    future = client.call_async(Trigger.Request())
    ros.spin_until(future.done, 10.0, 'the service reply')
    assert not future.result().success and 'already' in future.result().message


def test_a_bad_body_change_fails_at_start(ros) -> None:
    with pytest.raises(ValueError, match='r_knee'):
        make_sim(ros, body_change='r_knee.d+0.01')


def test_a_perturbed_camera_and_marker_are_rendered_but_the_description_is_published(ros) -> None:
    """camera_perturbation / marker_perturbation: the images come from the real poses, the graph
    is told the description's, and /body_schema/true_extrinsics says by how much they differ."""
    from body_schema.extrinsics import perturb_pose
    from calibration_interfaces.messages import msg_to_extrinsics, pose_msg_to_matrix

    ur = load_robot('ur5e')
    sim = make_sim(ros, robot='ur5e', image_rate=0.0, perturb_seed=3, camera_perturbation='0.02 2',
                   marker_perturbation='0.005 5')
    probe = ros.node('probe_extrinsics')
    got = {}
    for name, typ in (('/camera/left/pose', PoseStamped), ('/body_schema/true_extrinsics', Float64MultiArray)):
        probe.create_subscription(typ, name, lambda msg, name=name: got.__setitem__(name, msg), LATCHED)
    ros.spin_until(lambda: len(got) == 2, 10.0, f'the camera pose and the true extrinsics; got {sorted(got)}')
    np.testing.assert_allclose(pose_msg_to_matrix(got['/camera/left/pose'].pose), ur.camera_pose('left'), atol=1e-12)
    cam, marker = msg_to_extrinsics(got['/body_schema/true_extrinsics'])
    assert np.linalg.norm(cam[:3]) == pytest.approx(0.02) and np.degrees(np.linalg.norm(cam[3:])) == pytest.approx(2.0)
    assert np.linalg.norm(marker[:3]) == pytest.approx(0.005)
    assert np.degrees(np.linalg.norm(marker[3:])) == pytest.approx(5.0)
    np.testing.assert_allclose(sim.real_cameras['left'], perturb_pose(ur.camera_pose('left'), cam), atol=1e-12)
    # The world draws the marker where the real board is.
    np.testing.assert_allclose(sim.world.markers[0].placement.hand_T_marker,
                               perturb_pose(ur.markers[0].hand_T_marker, marker), atol=1e-12)
    # The DH draw is the same as without them (a stream of its own).
    plain = make_sim(ros, robot='ur5e', image_rate=0.0, perturb_seed=3)
    np.testing.assert_array_equal(plain.true_dh, sim.true_dh)


def test_a_random_start_is_drawn_in_the_box_per_robot_seed(ros) -> None:
    def start(**params):
        return make_sim(ros, image_rate=0.0, random_start=True, **params).follower.q

    box = ROBOT.calibration_box
    a, a_again, b = start(perturb_seed=5), start(perturb_seed=5), start(perturb_seed=6)
    assert np.all((a >= box[:, 0]) & (a <= box[:, 1])) and np.all((b >= box[:, 0]) & (b <= box[:, 1]))
    np.testing.assert_array_equal(a, a_again)                 # shared by every method of a repetition
    assert np.max(np.abs(a - b)) > 1e-3
    assert np.max(np.abs(a - box.mean(axis=1))) > 1e-3        # not the default centre
    # The drawn start does not move the robot's own draw, and explicit positions still win.
    assert np.array_equal(make_sim(ros, image_rate=0.0, random_start=True).true_dh,
                          make_sim(ros, image_rate=0.0).true_dh)
    given = np.radians([-50.0, 60.0, 70.0, 40.0, 10.0, -30.0, 0.0])
    np.testing.assert_allclose(start(perturb_seed=5, initial_positions_deg=list(np.degrees(given))), given)


def test_contacts_with_the_table_are_reported_on_diagnostics_and_a_clear_motion_reports_none(ros) -> None:
    """The UR5e drawn on its table: a motion that stays clear reports zero contacts (level OK) and
    the least clearance; a command that drives the wrist into the table reports it (level ERROR,
    the pair named), as a user watching /diagnostics would see it."""
    from diagnostic_msgs.msg import DiagnosticArray

    from calibration_interfaces.outcome import CONTACT_DIAGNOSTIC, decode_contacts

    ur = load_robot('ur5e')
    make_sim(ros, robot='ur5e', image_rate=0.0, max_joint_speed_deg=180.0)
    probe = Probe(ros)
    reports = []
    probe.node.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda m: reports.extend(s for s in m.status if s.name == CONTACT_DIAGNOSTIC), 100)
    ros.spin_until(lambda: '/joint_states' in probe.last, 20.0, 'joint states')
    up = np.radians([0.0, -100.0, 60.0, -180.0, -90.0, 0.0])
    probe.command(ur.joint_names, [up])
    ros.spin_until(lambda: np.allclose(probe.q(), up, atol=1e-6) and reports
                   and decode_contacts({v.key: v.value for v in reports[-1].values}).checks > 5, 30.0, 'a clear move')
    clear = decode_contacts({v.key: v.value for v in reports[-1].values})
    assert clear.contacts == 0 and reports[-1].level == bytes([0]) and 0.05 < clear.min_clearance < 0.6
    down = np.radians([0.0, -40.0, 130.0, -180.0, -90.0, 0.0])          # the wrist below the table top
    probe.command(ur.joint_names, [down])
    ros.spin_until(lambda: decode_contacts({v.key: v.value for v in reports[-1].values}).contacts > 0, 30.0,
                   'a contact report')
    hit = decode_contacts({v.key: v.value for v in reports[-1].values})
    assert reports[-1].level == bytes([2]) and any('table' in pair for pair in hit.pairs)
    assert hit.min_clearance < 0.0 and 'contact' in reports[-1].message
