"""ROS 2 node: the PyBullet iCub right arm with an ArUco-marked hand and two eye cameras.

Steps a :class:`~icub_sim_bridge.world.SimWorld` at a fixed physics step, follows joint
trajectories at a bounded joint speed, and publishes the simulated sensors in sim time.

Topics published
----------------
/clock : rosgraph_msgs/Clock
    Sim time, at ``joint_state_rate`` (the node itself runs on it: ``use_sim_time`` is forced on).
/joint_states : sensor_msgs/JointState
    The 7 arm joints [rad, rad/s] at ``joint_state_rate`` (sim time).
/camera/{left,right}/image_raw : sensor_msgs/Image
    rgb8 at ``image_rate`` (sim time), sensor-data QoS.
/camera/{left,right}/camera_info : sensor_msgs/CameraInfo
    K, D (plumb_bob, zeros), R = I, P; with every image, reliable + transient local.
/camera/{left,right}/pose : geometry_msgs/PoseStamped
    Optical frame in ``root_link``; transient local (the head holds still).
/body_schema/true : std_msgs/Float64MultiArray
    The simulated robot's real DH table, 7 x 4 (a, d, alpha, offset); transient local.

Topics subscribed
-----------------
/arm/command : trajectory_msgs/JointTrajectory
    Waypoints over a subset of the arm joints; reliable. Rejected with a warning (and the arm
    holds where it is) for unknown or repeated names, NaN/inf, no points, a wrong number of
    positions, or targets outside the joint limits.

Parameters
----------
robot (str), true_dh_file (str), perturb_seed (int), perturb_width_length (float, m),
perturb_width_angle_deg (float), physics_step (float, s), real_time_factor (float),
joint_state_rate (float, Hz), image_rate (float, Hz), max_joint_speed_deg (float, deg/s),
initial_positions_deg (float[7]), head_pose_deg (float[5]), cameras (str[]), image_width (int),
image_height (int), supersample (int), pixel_noise_std (float), blur_sigma (float),
noise_seed (int), marker_dictionary (str), marker_ids (int[]), marker_side_length (float, m).
See :meth:`SimNode._declare` for descriptions and ranges.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
import yaml
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from body_schema.robot import ArmModel, load_robot
from body_schema.sampling import perturb_dh
from dh_estimator.messages import matrix_to_pose_msg, table_to_msg

from .camera import degrade
from .motion import CommandError, TrajectoryFollower, validate_command
from .world import SimWorld

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: Joint-state periods simulated per timer tick when running as fast as possible.
RTF0_TICKS = 1
RELIABLE = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


def load_dh_file(path: str, robot: ArmModel) -> np.ndarray:
    """A "real robot" DH table from YAML, shape (L, 4) [m, rad].

    Accepts a full robot description (its joints' ``dh`` are used) or a mapping
    ``{angle_unit: deg|rad, dh: [[a, d, alpha, offset], ...]}`` (``angle_unit`` defaults to rad).

    Raises
    ------
    ValueError
        If the file is missing, malformed or the table has the wrong shape.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f'true_dh_file {path!r} does not exist')
    data = yaml.safe_load(p.read_text())
    if isinstance(data, dict) and 'joints' in data:
        return load_robot(p).dh
    if not isinstance(data, dict) or 'dh' not in data:
        raise ValueError(f'true_dh_file {path!r}: expected a robot description or a mapping with "dh"')
    unit = data.get('angle_unit', 'rad')
    if unit not in ('deg', 'rad'):
        raise ValueError(f'true_dh_file {path!r}: angle_unit must be deg or rad, got {unit!r}')
    dh = np.array(data['dh'], dtype=float)
    if dh.shape != robot.dh.shape or not np.all(np.isfinite(dh)):
        raise ValueError(f'true_dh_file {path!r}: dh must be a finite {robot.dh.shape} table, got {dh.shape}')
    if unit == 'deg':
        dh[:, 2:] = np.radians(dh[:, 2:])
    return dh


def _stamp(ns: int) -> TimeMsg:
    return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _desc(text: str, lo: float | None = None, hi: float | None = None, step: float = 0.0,
          integer: bool = False, read_only: bool = True) -> ParameterDescriptor:
    d = ParameterDescriptor(description=text, read_only=read_only)
    if lo is not None:
        if integer:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=int(step))]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=step)]
    return d


class SimNode(Node):
    """The simulator node; ``kwargs`` go to :class:`rclpy.node.Node` (context, overrides)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('icub_sim', **kwargs)
        self.set_parameters([Parameter('use_sim_time', Parameter.Type.BOOL, True)])
        self._declare()
        prm = {n: self.get_parameter(n).value for n in self._names}

        # The "real robot": nominal, a second table, or a small seeded perturbation.
        self.robot = self._robot
        true_dh = self.robot.dh.copy()
        if prm['true_dh_file']:
            true_dh = load_dh_file(prm['true_dh_file'], self.robot)
        if prm['perturb_seed'] >= 0:
            true_dh = perturb_dh(true_dh, prm['perturb_seed'], prm['perturb_width_length'],
                                 np.radians(prm['perturb_width_angle_deg']))
        self.true_dh = true_dh
        head = np.radians(np.asarray(prm['head_pose_deg'], dtype=float))
        if head.shape != (5,):
            raise ValueError(f'head_pose_deg needs 5 angles, got {prm["head_pose_deg"]}')
        self.world = SimWorld(self.robot, true_dh, marker_dictionary=prm['marker_dictionary'] or None,
                              marker_ids=list(prm['marker_ids']) or None,
                              marker_side_length=prm['marker_side_length'] or None,
                              head_pose=head, physics_step=prm['physics_step'])
        self.intrinsics = self.robot.camera.scaled(prm['image_width'], prm['image_height'])
        self.cameras = {eye: self.robot.camera_pose(eye, head) for eye in prm['cameras']}
        q0 = np.radians(np.asarray(prm['initial_positions_deg'], dtype=float))
        q0 = validate_command(self.robot.joint_names, [q0], [], self.robot.joint_names,
                              self.robot.limits, q0).targets[0]
        self.follower = TrajectoryFollower(q0, np.radians(prm['max_joint_speed_deg']))
        self.world.set_joint_positions(q0)

        if prm['physics_step'] > 1.0 / prm['joint_state_rate'] + 1e-12:
            raise ValueError(f'physics_step {prm["physics_step"]} s is longer than the joint-state '
                             f'period 1/{prm["joint_state_rate"]} s')
        self.rtf = float(prm['real_time_factor'])
        self._step_ns = int(round(prm['physics_step'] * 1e9))
        self._js_ns = int(round(1e9 / prm['joint_state_rate']))
        self._img_ns = int(round(1e9 / prm['image_rate'])) if prm['image_rate'] > 0 else 0
        self._supersample = int(prm['supersample'])
        self._noise_std, self._blur = float(prm['pixel_noise_std']), float(prm['blur_sigma'])
        self._rng = np.random.default_rng(prm['noise_seed'])
        self.sim_ns = 0
        self._next_js = 0
        self._next_img = 0
        self._q_last_js = q0.copy()

        # Publishers and subscriber.
        self.pub_clock = self.create_publisher(ClockMsg, '/clock', 10)
        self.pub_js = self.create_publisher(JointState, '/joint_states', 10)
        self.pub_true = self.create_publisher(Float64MultiArray, '/body_schema/true', LATCHED)
        self.pub_img, self.pub_info, self.pub_pose = {}, {}, {}
        for eye in self.cameras:
            self.pub_img[eye] = self.create_publisher(Image, f'/camera/{eye}/image_raw', qos_profile_sensor_data)
            self.pub_info[eye] = self.create_publisher(CameraInfo, f'/camera/{eye}/camera_info', LATCHED)
            self.pub_pose[eye] = self.create_publisher(PoseStamped, f'/camera/{eye}/pose', LATCHED)
        self.create_subscription(JointTrajectory, '/arm/command', self._on_command, RELIABLE)
        self._publish_latched()

        # The loop runs on the wall clock (sim time only advances because of it).
        self._wall0, self._sim0 = time.monotonic(), 0
        chunk = self._js_ns / 1e9
        period = 0.0 if self.rtf == 0 else max(chunk / self.rtf, 0.001)
        self._timer = self.create_timer(period, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'simulating {self.robot.name} ({"perturbed" if not np.allclose(true_dh, self.robot.dh) else "nominal"} '
            f'DH), cameras {list(self.cameras)} {self.intrinsics.width}x{self.intrinsics.height} at '
            f'{prm["image_rate"]} Hz, physics step {prm["physics_step"]} s, real-time factor {self.rtf}')

    # ------------------------------------------------------------------------------------------
    # Parameters

    def _declare(self) -> None:
        self._names: list[str] = []

        def dec(name: str, default: Any, desc: ParameterDescriptor) -> None:
            self.declare_parameter(name, default, desc)
            self._names.append(name)

        dec('robot', 'icub_right_arm', _desc('Robot description: packaged name or YAML path.'))
        self._robot = load_robot(self.get_parameter('robot').value)
        r = self._robot
        if r.camera is None or r.eyes is None:
            raise ValueError(f'robot {r.name!r} needs camera and eyes sections for the simulator')
        dec('true_dh_file', '', _desc('YAML with the simulated robot\'s real DH table (a robot '
                                      'description or {angle_unit, dh}); empty = nominal.'))
        dec('perturb_seed', -1, _desc('If >= 0, the real robot is the (file or nominal) table '
                                      'perturbed uniformly with this seed.', -1, 2**31 - 1, 1, True))
        dec('perturb_width_length', 0.004, _desc('Full width of the a, d perturbation [m].', 0.0, 0.1))
        dec('perturb_width_angle_deg', 2.0, _desc('Full width of the alpha, offset perturbation [deg].', 0.0, 60.0))
        dec('physics_step', 0.005, _desc('Fixed physics time step [s]; at most 1/joint_state_rate.', 1e-4, 0.02))
        dec('real_time_factor', 1.0, _desc('Sim seconds per wall second; 0 runs as fast as possible.', 0.0, 100.0))
        dec('joint_state_rate', 50.0, _desc('/joint_states and /clock rate [Hz, sim time].', 50.0, 1000.0))
        dec('image_rate', 10.0, _desc('Camera rate [Hz, sim time]; 0 disables the images.', 0.0, 60.0))
        dec('max_joint_speed_deg', 30.0, _desc('Speed limit of every joint [deg/s].', 1.0, 360.0))
        dec('initial_positions_deg', [float(v) for v in np.degrees(r.calibration_box.mean(axis=1))],
            _desc('Arm joints at start [deg] (default: centre of the calibration box).'))
        dec('head_pose_deg', [float(v) for v in np.degrees(r.eyes.head_pose)],
            _desc('Head joints (neck pitch, roll, yaw, eye tilt, eye pan) [deg]; held still.'))
        dec('cameras', ['left', 'right'], _desc('Eyes to simulate: any of left, right.'))
        dec('image_width', r.camera.width, _desc('Image width [px]; intrinsics scale with it.', 16, 4096, 1, True))
        dec('image_height', r.camera.height, _desc('Image height [px].', 16, 4096, 1, True))
        dec('supersample', 1, _desc('Anti-aliasing factor (render n times larger, average down).', 1, 4, 1, True))
        dec('pixel_noise_std', 0.0, _desc('Additive Gaussian pixel noise [grey levels].', 0.0, 100.0))
        dec('blur_sigma', 0.0, _desc('Gaussian blur sigma [px].', 0.0, 10.0))
        dec('noise_seed', 0, _desc('Seed of the pixel noise.', 0, 2**31 - 1, 1, True))
        dec('marker_dictionary', r.marker_dictionary, _desc('cv2.aruco dictionary of the hand markers.'))
        dec('marker_ids', [m.marker_id for m in r.markers], _desc('Marker ids, in the description\'s order.'))
        dec('marker_side_length', r.marker_side_length, _desc('Black-square side [m].', 0.005, 0.05))
        bad = [e for e in self.get_parameter('cameras').value if e not in r.eyes.links]
        if bad:
            raise ValueError(f'cameras: unknown eyes {bad}; expected any of {sorted(r.eyes.links)}')

    # ------------------------------------------------------------------------------------------
    # Messages

    def _publish_latched(self) -> None:
        self.pub_true.publish(table_to_msg(self.true_dh))
        for eye, pose in self.cameras.items():
            ps = PoseStamped(pose=matrix_to_pose_msg(pose))
            ps.header.frame_id = self.robot.root_frame
            self.pub_pose[eye].publish(ps)

    def _camera_info(self, eye: str, stamp: TimeMsg) -> CameraInfo:
        k = self.intrinsics
        info = CameraInfo()
        info.header.stamp, info.header.frame_id = stamp, f'{eye}_camera_optical_frame'
        info.width, info.height = k.width, k.height
        info.distortion_model = 'plumb_bob'
        info.d = [0.0] * 5
        info.k = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        return info

    def _publish_images(self, stamp: TimeMsg) -> None:
        self.world.set_joint_positions(self.follower.q)
        for eye, pose in self.cameras.items():
            rgb = self.world.render(pose, self.intrinsics, supersample=self._supersample)
            rgb = degrade(rgb, self._noise_std, self._blur, self._rng)
            img = Image()
            img.header.stamp, img.header.frame_id = stamp, f'{eye}_camera_optical_frame'
            img.height, img.width = rgb.shape[:2]
            img.encoding, img.is_bigendian, img.step = 'rgb8', 0, rgb.shape[1] * 3
            img.data = rgb.tobytes()    # bytes: ~0.1 ms; a numpy array would take ~50 ms
            self.pub_img[eye].publish(img)
            self.pub_info[eye].publish(self._camera_info(eye, stamp))

    def _publish_joints(self, stamp: TimeMsg) -> None:
        q = self.follower.q
        js = JointState()
        js.header.stamp = stamp
        js.name = list(self.robot.joint_names)
        js.position = q.tolist()
        js.velocity = ((q - self._q_last_js) / (self._js_ns / 1e9)).tolist()
        self._q_last_js = q
        self.pub_js.publish(js)
        self.pub_clock.publish(ClockMsg(clock=stamp))

    # ------------------------------------------------------------------------------------------
    # Loop and commands

    def advance(self, duration_ns: int) -> None:
        """Step the simulation ``duration_ns`` of sim time, publishing whatever falls due."""
        end = self.sim_ns + duration_ns
        dt = self._step_ns / 1e9
        while self.sim_ns < end:
            self.follower.advance(dt)
            self.world.step()
            self.sim_ns += self._step_ns
            if self.sim_ns >= self._next_js:
                self._publish_joints(_stamp(self.sim_ns))
                self._next_js += self._js_ns
            if self._img_ns and self.sim_ns >= self._next_img:
                self._publish_images(_stamp(self.sim_ns))
                self._next_img += self._img_ns

    def _tick(self) -> None:
        if self.rtf == 0:
            # One joint-state period per tick: a subscriber sharing this executor takes one message
            # per wait, so publishing several per tick would overflow its queue.
            self.advance(RTF0_TICKS * self._js_ns)
            return
        target = self._sim0 + int((time.monotonic() - self._wall0) * self.rtf * 1e9)
        behind = target - self.sim_ns
        if behind > 250_000_000:
            # Too slow for this factor: drop the backlog rather than spiral.
            self._wall0, self._sim0 = time.monotonic(), self.sim_ns
            behind = self._js_ns
        if behind >= self._step_ns:
            self.advance(behind - behind % self._step_ns)

    def _on_command(self, msg: JointTrajectory) -> None:
        try:
            wp = validate_command(msg.joint_names, [list(p.positions) for p in msg.points],
                                  [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points],
                                  self.robot.joint_names, self.robot.limits, self.follower.q)
        except CommandError as exc:
            self.follower.stop()
            self.get_logger().warning(f'rejected /arm/command: {exc}; the arm holds at its present position')
            return
        duration = self.follower.start(wp)
        self.get_logger().info(f'moving to {np.round(np.degrees(wp.targets[-1]), 1).tolist()} deg '
                               f'through {len(wp.targets)} point(s), {duration:.2f} s')

    def destroy_node(self) -> None:
        self.world.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = SimNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
