"""ROS 2 node: the PyBullet arm of a robot description with an ArUco-marked hand and its cameras.

Steps a :class:`~icub_sim_bridge.world.SimWorld` at a fixed physics step, follows joint
trajectories at a bounded joint speed, and publishes the simulated sensors in sim time.

Topics published
----------------
/clock : rosgraph_msgs/Clock
    Sim time, at ``joint_state_rate`` (the node itself runs on it: ``use_sim_time`` is forced on).
/joint_states : sensor_msgs/JointState
    The arm joints [rad, rad/s] at ``joint_state_rate`` (sim time).
/camera/<name>/image_raw : sensor_msgs/Image
    One set of camera topics per simulated camera (``cameras``: the iCub's eyes ``left``,
    ``right``; a fixed camera of the description under its name).
    ``image_encoding`` (rgb8; or any camera encoding, e.g. a Bayer mosaic) at ``image_rate``
    (sim time), sensor-data QoS.
/camera/<name>/image_raw/compressed : sensor_msgs/CompressedImage
    With ``compressed_format`` jpeg or png: the same frames as image_transport's compressed
    publisher makes them from image_raw (format ``"<encoding>; jpeg compressed bgr8"``),
    sensor-data QoS; encoded only while someone subscribes.
/camera/<name>/camera_info : sensor_msgs/CameraInfo
    K, D (plumb_bob, zeros), R = I, P; with every image, reliable + transient local.
/camera/<name>/pose : geometry_msgs/PoseStamped
    Optical frame in ``root_link``; transient local (the head holds still). Always the
    description's pose: with ``camera_perturbation`` the images are rendered from a real pose
    off it (what a tape-measured camera pose is to a real one).
/body_schema/true : std_msgs/Float64MultiArray
    The simulated robot's real DH table, L x 4 (a, d, alpha, offset); transient local;
    published again when the body changes.
/body_schema/true_extrinsics : std_msgs/Float64MultiArray
    2 x 6: the real camera's and marker board's offsets from the description's poses (position
    [m], rotation vector [rad], :func:`body_schema.extrinsics.perturb_pose`); transient local.
/robot_description : std_msgs/String
    URDF of the real arm (links as :func:`body_schema.urdf.chain_transforms` names the TF
    frames, the simulator's geometry); transient local; published again when the body changes.
/diagnostics : diagnostic_msgs/DiagnosticArray
    With ``contact_check``: the real arm checked for contacts with the description's obstacles
    (drawn in the images too) and with itself at every joint state while it moves
    (:class:`icub_sim_bridge.contacts.ContactMonitor`), one status named
    :data:`calibration_interfaces.outcome.CONTACT_DIAGNOSTIC` (checks, contacts, pairs, least
    clearance to a static body) once a second of sim time and at once on a new contact; level OK,
    ERROR after a contact (also logged).

Topics subscribed
-----------------
/arm/command : trajectory_msgs/JointTrajectory
    Waypoints over a subset of the arm joints; reliable. Rejected with a warning (and the arm
    holds where it is) for unknown or repeated names, NaN/inf, no points, a wrong number of
    positions, or targets outside the joint limits.

Services
--------
~/apply_body_change : std_srvs/Trigger
    Applies ``body_change`` now (once): the real robot changes, ``/body_schema/true`` follows.

Parameters
----------
Declared (read-only) from :class:`icub_sim_bridge.settings.SimSettings`: robot, the real robot
(``true_dh_file``: any DH file of :mod:`calibration_interfaces.dh_file`, e.g. the estimator's
exported ``calibrated_dh.yaml``; ``perturb_seed``), a change of that robot mid-run
(``body_change``, ``body_change_at_command``), timing, cameras, image degradation, image
encoding and compression, and markers. docs/nodes/sim.md lists them with defaults and ranges;
``config/sim.yaml`` sets a run's values.
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import dataclasses
import re
import time
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from body_schema.arm_visuals import description_urdf
from body_schema.extrinsics import corrections, parse_std, perturb_pose, random_delta
from body_schema.robot import load_robot
from body_schema.sampling import perturb_dh, uniform_configs
from calibration_interfaces.contract import RELIABLE, image_topic, optical_frame
from calibration_interfaces.dh_file import read_dh_file
from calibration_interfaces.image_conversion import ENCODINGS, array_to_image_fields, compress, encode_rgb
from calibration_interfaces.messages import extrinsics_to_msg, matrix_to_pose_msg, table_to_msg
from calibration_interfaces.node_util import WarnThrottled, declare_settings, qos_profile, spin_node
from calibration_interfaces.outcome import CONTACT_DIAGNOSTIC, ContactStatus, encode_contacts

from .body_change import parse_body_change
from .camera import degrade
from .contacts import ContactMonitor
from .motion import CommandError, TrajectoryFollower, validate_command
from .settings import SimSettings
from .world import SimWorld

#: Joint-state periods simulated per timer tick when running as fast as possible.
RTF0_TICKS = 1
#: Smallest image side [px] the simulator renders.
MIN_IMAGE_PX = 16


def _stamp(ns: int) -> TimeMsg:
    return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class SimNode(Node):
    """The simulator node; ``kwargs`` go to :class:`rclpy.node.Node` (context, overrides)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('icub_sim', **kwargs)
        self._warn = WarnThrottled(self)
        self.set_parameters([Parameter('use_sim_time', Parameter.Type.BOOL, True)])
        s = self.settings = declare_settings(self, SimSettings, read_only=True)
        self.robot = r = load_robot(s.robot)
        if r.camera is None or not r.camera_names:
            raise ValueError(f'robot {r.name!r} needs a camera section and eyes or fixed_cameras for the simulator')
        cameras = tuple(s.cameras) or r.camera_names
        bad = [e for e in cameras if e not in r.camera_names]
        if bad:
            raise ValueError(f'cameras: unknown cameras {bad}; expected any of {sorted(r.camera_names)}')
        if ENCODINGS[s.image_encoding].kind in ('uyvy', 'yuyv') and (s.image_width or r.camera.width) % 2:
            raise ValueError(f'image_encoding {s.image_encoding} pairs pixels (4:2:2): it needs an even image width, '
                             f'got {s.image_width or r.camera.width}')

        # The "real robot": nominal, a DH file, and/or a small seeded perturbation.
        true_dh = read_dh_file(s.true_dh_file, r.n_joints).dh if s.true_dh_file else r.dh.copy()
        if s.perturb_seed >= 0:
            true_dh = perturb_dh(true_dh, s.perturb_seed, s.perturb_width_length,
                                 np.radians(s.perturb_width_angle_deg))
        self.true_dh = true_dh
        # A scheduled (or requested) change of that robot; parsed now so a bad spec fails at start.
        self.body_change = parse_body_change(s.body_change, r.joint_names) if s.body_change else None
        # Real camera poses and marker board off the description's (which the graph is told).
        cam_error = parse_std(s.camera_perturbation, 'camera_perturbation')
        marker_error = parse_std(s.marker_perturbation, 'marker_perturbation')
        rng = np.random.default_rng([max(s.perturb_seed, 0), 16])     # a stream of its own: the DH draw is unchanged
        cam_delta = random_delta(rng, *cam_error) if cam_error and s.perturb_seed >= 0 else np.zeros(6)
        marker_delta = random_delta(rng, *marker_error) if marker_error and s.perturb_seed >= 0 else np.zeros(6)
        if np.any(marker_delta):
            board = corrections(np.eye(4), r.markers[0].hand_T_marker, np.zeros(6), marker_delta)[1]
            real_robot = dataclasses.replace(r, markers=tuple(
                dataclasses.replace(m, hand_T_marker=board @ m.hand_T_marker) for m in r.markers))
        else:
            real_robot = r
        self.true_extrinsics = (cam_delta, marker_delta)
        self.body_changed = False
        self.commands = 0
        head = None   # fixed cameras only: no head
        if r.eyes is not None:
            head = np.radians(np.asarray(s.head_pose_deg, dtype=float)) if s.head_pose_deg else r.eyes.head_pose
            if head.shape != (len(r.eyes.head_joints),):
                raise ValueError(f'head_pose_deg needs {len(r.eyes.head_joints)} angles, got {list(s.head_pose_deg)}')
        self._head = head
        self.real_robot = real_robot
        self.contacts = ContactMonitor(real_robot, true_dh, head_pose=head) if s.contact_check else None
        self._q_checked: np.ndarray | None = None
        self._contacts_reported = -1
        self._next_contact_report = 0
        self.world = SimWorld(real_robot, true_dh, marker_dictionary=s.marker_dictionary or None,
                              marker_ids=list(s.marker_ids) or None,
                              marker_side_length=s.marker_side_length or None,
                              head_pose=head, physics_step=s.physics_step)
        for name, px in (('image_width', s.image_width), ('image_height', s.image_height)):
            if 0 < px < MIN_IMAGE_PX:
                raise ValueError(f'{name} {px} px is below {MIN_IMAGE_PX} px (0: the description\'s camera)')
        self.intrinsics = r.camera.scaled(s.image_width or r.camera.width, s.image_height or r.camera.height)
        self.cameras = {eye: r.camera_pose(eye, head) for eye in cameras}      # published
        self.real_cameras = {eye: perturb_pose(pose, cam_delta) for eye, pose in self.cameras.items()}
        if s.initial_positions_deg:
            q0 = np.radians(np.asarray(s.initial_positions_deg, dtype=float))
        elif s.random_start:    # a stream of its own: the DH and extrinsics draws are unchanged
            q0 = uniform_configs(r.calibration_box, 1, np.random.default_rng([max(s.perturb_seed, 0), 17]))[0]
        else:
            q0 = r.calibration_box.mean(axis=1)
        q0 = validate_command(self.robot.joint_names, [q0], [], self.robot.joint_names,
                              self.robot.limits, q0).targets[0]
        self.follower = TrajectoryFollower(q0, np.radians(s.max_joint_speed_deg))
        self.world.set_joint_positions(q0)

        if s.physics_step > 1.0 / s.joint_state_rate + 1e-12:
            raise ValueError(f'physics_step {s.physics_step} s is longer than the joint-state '
                             f'period 1/{s.joint_state_rate} s')
        self.rtf = s.real_time_factor
        self._step_ns = int(round(s.physics_step * 1e9))
        self._js_ns = int(round(1e9 / s.joint_state_rate))
        self._img_ns = int(round(1e9 / s.image_rate)) if s.image_rate > 0 else 0
        self._supersample = s.supersample
        self._noise_std, self._blur = s.pixel_noise_std, s.blur_sigma
        self._rng = np.random.default_rng(s.noise_seed)
        self.sim_ns = 0
        self._next_js = 0
        self._next_img = 0
        self._q_last_js = q0.copy()

        # Publishers and subscriber.
        self.pub_clock = self.create_publisher(ClockMsg, '/clock', qos_profile('/clock'))
        self.pub_js = self.create_publisher(JointState, '/joint_states', qos_profile('/joint_states'))
        self.pub_true = self.create_publisher(Float64MultiArray, '/body_schema/true', qos_profile('/body_schema/true'))
        self.pub_true_extrinsics = self.create_publisher(Float64MultiArray, '/body_schema/true_extrinsics',
                                                         qos_profile('/body_schema/true_extrinsics'))
        self.pub_description = self.create_publisher(String, '/robot_description', qos_profile('/robot_description'))
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', qos_profile('/diagnostics'))
        self.pub_img, self.pub_info, self.pub_pose, self.pub_compressed = {}, {}, {}, {}
        for eye in self.cameras:
            for pubs, cls, suffix in ((self.pub_img, Image, 'image_raw'), (self.pub_info, CameraInfo, 'camera_info'),
                                      (self.pub_pose, PoseStamped, 'pose')):
                pubs[eye] = self.create_publisher(cls, f'/camera/{eye}/{suffix}', qos_profile(f'/camera/{eye}/{suffix}'))
            if s.compressed_format != 'none':
                name = image_topic(eye, 'compressed')
                self.pub_compressed[eye] = self.create_publisher(CompressedImage, name, qos_profile(name))
        # A volatile subscription also takes the selector's latched command.
        self.create_subscription(JointTrajectory, '/arm/command', self._on_command, qos_profile(RELIABLE))
        self.create_service(Trigger, '~/apply_body_change', self._on_apply_body_change)
        self._publish_latched()

        # The loop runs on the wall clock (sim time only advances because of it).
        self._wall0, self._sim0 = time.monotonic(), 0
        chunk = self._js_ns / 1e9
        period = 0.0 if self.rtf == 0 else max(chunk / self.rtf, 0.001)
        self._timer = self.create_timer(period, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'simulating {self.robot.name} ({"perturbed" if not np.allclose(true_dh, self.robot.dh) else "nominal"} '
            f'DH), cameras {list(self.cameras)} {self.intrinsics.width}x{self.intrinsics.height} {s.image_encoding}'
            f'{"" if s.compressed_format == "none" else f" (+ {s.compressed_format} compressed)"} at '
            f'{s.image_rate} Hz, physics step {s.physics_step} s, real-time factor {self.rtf}')
        if np.any(cam_delta) or np.any(marker_delta):
            self.get_logger().info(
                f'real camera off the published pose by {1e3 * cam_delta[:3].round(5)} mm, '
                f'{np.degrees(cam_delta[3:]).round(4)} deg (rotation vector); marker board off by '
                f'{1e3 * marker_delta[:3].round(6)} mm, {np.degrees(marker_delta[3:]).round(4)} deg')

    # ------------------------------------------------------------------------------------------
    # Messages

    def _publish_real_arm(self) -> None:
        self.pub_true.publish(table_to_msg(self.true_dh))
        self.pub_description.publish(String(data=description_urdf(self.robot, self.true_dh)))

    def _publish_latched(self) -> None:
        self._publish_real_arm()
        self.pub_true_extrinsics.publish(extrinsics_to_msg(*self.true_extrinsics))
        for eye, pose in self.cameras.items():
            ps = PoseStamped(pose=matrix_to_pose_msg(pose))
            ps.header.frame_id = self.robot.root_frame
            self.pub_pose[eye].publish(ps)

    def _camera_info(self, eye: str, stamp: TimeMsg) -> CameraInfo:
        k = self.intrinsics
        info = CameraInfo()
        info.header.stamp, info.header.frame_id = stamp, optical_frame(eye)
        info.width, info.height = k.width, k.height
        info.distortion_model = 'plumb_bob'
        info.d = [0.0] * 5
        info.k = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        return info

    def _publish_images(self, stamp: TimeMsg) -> None:
        self.world.set_joint_positions(self.follower.q)
        for eye, pose in self.real_cameras.items():    # rendered from the real poses
            rgb = self.world.render(pose, self.intrinsics, supersample=self._supersample)
            rgb = degrade(rgb, self._noise_std, self._blur, self._rng)
            s = self.settings
            frame = rgb if s.image_encoding == 'rgb8' else encode_rgb(rgb, s.image_encoding)
            img = Image()
            img.header.stamp, img.header.frame_id = stamp, optical_frame(eye)
            # data as bytes: ~0.1 ms; a numpy array would take ~50 ms
            for k, v in array_to_image_fields(frame, s.image_encoding).items():
                setattr(img, k, v)
            self.pub_img[eye].publish(img)
            pub = self.pub_compressed.get(eye)
            if pub is not None and pub.get_subscription_count():     # image_transport encodes only for someone
                comp = CompressedImage()
                comp.header = img.header
                fields = compress(frame, s.image_encoding, s.compressed_format, jpeg_quality=s.jpeg_quality,
                                  png_level=s.png_level)
                comp.format, comp.data = fields['format'], fields['data']
                pub.publish(comp)
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
        self._check_contacts(q, stamp)

    def _check_contacts(self, q: np.ndarray, stamp: TimeMsg) -> None:
        """Check the arm where it moved to; report at once on a new contact, else once a sim second."""
        if self.contacts is None:
            return
        if self._q_checked is None or not np.array_equal(q, self._q_checked):
            self._q_checked = q.copy()
            pairs = self.contacts.check(q)
            if pairs:
                self._warn('contact', f'contact at {np.round(np.degrees(q), 1).tolist()} deg: '
                           + ', '.join(f'{a} - {b}' for a, b in pairs))
        r = self.contacts.report
        if r.contacts != self._contacts_reported or self.sim_ns >= self._next_contact_report:
            self._contacts_reported = r.contacts
            self._next_contact_report = self.sim_ns + 1_000_000_000
            values = encode_contacts(r.checks, r.contacts, r.pairs, r.min_clearance, r.min_clearance_pair,
                                     self.sim_ns / 1e9)
            status = ContactStatus(r.checks, r.contacts, dict(r.pairs), r.min_clearance, r.min_clearance_pair, 0.0)
            msg = DiagnosticArray()
            msg.header.stamp = stamp
            msg.status = [DiagnosticStatus(
                level=bytes([status.level]), name=CONTACT_DIAGNOSTIC, hardware_id=self.robot.name,
                message=(f'no contact in {r.checks} checked configurations' if not r.contacts else
                         f'{r.contacts} of {r.checks} checked configurations in contact: '
                         + ', '.join(f'{a} - {b}' for a, b in sorted(r.pairs))),
                values=[KeyValue(key=k, value=v) for k, v in values.items()])]
            self.pub_diagnostics.publish(msg)

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

    def apply_body_change(self) -> str:
        """Change the real robot by ``body_change`` (once) and publish its new table.

        Raises
        ------
        RuntimeError
            If there is no change to apply, or it was applied already.
        """
        if self.body_change is None:
            raise RuntimeError('no body_change parameter set')
        if self.body_changed:
            raise RuntimeError('the body change was applied already')
        self.true_dh = self.true_dh + self.body_change
        self.world.set_dh(self.true_dh)
        if self.contacts is not None:      # the changed body is the one checked from now on (counts kept)
            report = self.contacts.report
            self.contacts.close()
            self.contacts = ContactMonitor(self.real_robot, self.true_dh, head_pose=self._head)
            self.contacts.report = report
        self.body_changed = True
        self._publish_real_arm()
        text = f'the real robot changed ({self.settings.body_change}) at sim time {self.sim_ns / 1e9:.3f} s'
        self.get_logger().warning(text)
        return text

    def _on_apply_body_change(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.message, response.success = self.apply_body_change(), True
        except RuntimeError as exc:
            response.message, response.success = str(exc), False
        return response

    def _on_command(self, msg: JointTrajectory) -> None:
        self.commands += 1
        if self.commands == self.settings.body_change_at_command and self.body_change is not None:
            self.apply_body_change()
        try:
            wp = validate_command(msg.joint_names, [list(p.positions) for p in msg.points],
                                  [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points],
                                  self.robot.joint_names, self.robot.limits, self.follower.q)
        except CommandError as exc:
            self.follower.stop()
            # Throttled per reason (numbers aside): a burst of bad commands is not a screenful.
            self._warn(re.sub(r'[-+.\d]+', '#', str(exc)),
                       f'rejected /arm/command: {exc}; the arm holds at its present position')
            return
        duration = self.follower.start(wp)
        self.get_logger().info(f'moving to {np.round(np.degrees(wp.targets[-1]), 1).tolist()} deg '
                               f'through {len(wp.targets)} point(s), {duration:.2f} s')

    def destroy_node(self) -> None:
        self.world.close()
        if self.contacts is not None:
            self.contacts.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    spin_node(SimNode, args)


if __name__ == '__main__':
    main()
