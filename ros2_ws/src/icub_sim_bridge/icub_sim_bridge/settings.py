"""Parameters of the simulator node, one field each (pure; no rclpy).

Empty or zero values of the robot-dependent fields mean "the robot description's"; the node
declares every field as a read-only parameter
(:func:`calibration_interfaces.node_util.declare_settings`).
"""
from __future__ import annotations

from dataclasses import dataclass

from calibration_interfaces.image_conversion import COMPRESSED_FORMATS, ENCODINGS
from calibration_interfaces.parameters import setting

__all__ = ['SimSettings']


@dataclass(frozen=True)
class SimSettings:
    """Parameters of ``sim_node`` (node name ``icub_sim``)."""

    robot: str = setting('icub_right_arm', 'Robot description: packaged name or YAML path')
    true_dh_file: str = setting('', "DH file with the simulated robot's real table (an exported "
                                'calibrated_dh.yaml or a robot description); empty = nominal')
    perturb_seed: int = setting(-1, 'If >= 0, the real robot is the (file or nominal) table perturbed '
                                'uniformly with this seed', (-1, 2**31 - 1))
    perturb_width_length: float = setting(0.004, 'Full width of the a, d perturbation [m]', (0.0, 0.1))
    perturb_width_angle_deg: float = setting(2.0, 'Full width of the alpha, offset perturbation [deg]', (0.0, 60.0))
    camera_perturbation: str = setting('', 'If perturb_seed >= 0: the real cameras are off the description\'s '
                                       'poses by "<m> <deg>" (a random direction and axis, seeded); the published '
                                       'poses stay the description\'s; empty = none')
    marker_perturbation: str = setting('', 'If perturb_seed >= 0: the real marker board is off the description\'s '
                                       'placement on the flange by "<m> <deg>" (seeded); empty = none')
    body_change: str = setting('', 'A change of the real robot applied mid-run, e.g. "r_wrist_prosup.d+0.010 '
                               'r_shoulder_yaw.offset+3" (m, deg); empty = none (icub_sim_bridge.body_change)')
    body_change_at_command: int = setting(0, 'Apply body_change when this /arm/command arrives (1 = the first), '
                                          'before moving; 0 = only through the ~/apply_body_change service',
                                          (0, 1000000))
    physics_step: float = setting(0.005, 'Fixed physics time step [s]; at most 1/joint_state_rate', (1e-4, 0.02))
    real_time_factor: float = setting(1.0, 'Sim seconds per wall second; 0 runs as fast as possible', (0.0, 100.0))
    joint_state_rate: float = setting(50.0, '/joint_states and /clock rate [Hz, sim time]', (50.0, 1000.0))
    image_rate: float = setting(10.0, 'Camera rate [Hz, sim time]; 0 disables the images', (0.0, 60.0))
    # Up to 10 turns a second: the arm is kinematic, so any speed is exact, and a fast arm saves
    # the experiment sim ticks (calibration_bringup.experiment.GraphSettings).
    max_joint_speed_deg: float = setting(30.0, 'Speed limit of every joint [deg/s]', (1.0, 3600.0))
    contact_check: bool = setting(True, 'Check the real arm for contacts with the obstacles and itself at every joint '
                                        'state while it moves (icub_sim_bridge.contacts) and report them on '
                                        '/diagnostics (about 0.5-1 ms a check)')
    initial_positions_deg: tuple[float, ...] = setting((), 'Arm joints at start [deg]; empty = centre of the '
                                                       'calibration box (or random_start)', array_type='double')
    random_start: bool = setting(False, 'With empty initial_positions_deg: start at a configuration drawn '
                                 'uniformly in the calibration box from perturb_seed (as the paper: one random '
                                 'start per experiment, shared by the methods)')
    head_pose_deg: tuple[float, ...] = setting((), "Head joints (neck pitch, roll, yaw, eye tilt, eye pan) [deg], "
                                               "held still; empty = the description's", array_type='double')
    cameras: tuple[str, ...] = setting((), "Cameras to simulate (the description's eyes or fixed cameras, by "
                                       "name); empty = every camera of the description")
    image_width: int = setting(0, "Image width [px], at least 16; intrinsics scale with it; 0 = the description's camera",
                               (0, 4096))
    image_height: int = setting(0, "Image height [px], at least 16; 0 = the description's camera", (0, 4096))
    supersample: int = setting(1, 'Anti-aliasing factor (render n times larger, average down)', (1, 4))
    pixel_noise_std: float = setting(0.0, 'Additive Gaussian pixel noise [grey levels]', (0.0, 100.0))
    blur_sigma: float = setting(0.0, 'Gaussian blur sigma [px]', (0.0, 10.0))
    noise_seed: int = setting(0, 'Seed of the pixel noise', (0, 2**31 - 1))
    image_encoding: str = setting('rgb8', 'Encoding of image_raw, as a camera of that kind delivers the render '
                                  '(Bayer: the mosaic of its filter pattern; YUV 4:2:2: even widths only)',
                                  choices=tuple(ENCODINGS))
    compressed_format: str = setting('none', "Also publish image_raw/compressed (image_transport's compressed "
                                     'topic, made from image_raw) in this codec, while someone subscribes; none = not',
                                     choices=('none', *COMPRESSED_FORMATS))
    jpeg_quality: int = setting(90, 'JPEG quality of image_raw/compressed (image_transport: 95)', (1, 100))
    png_level: int = setting(3, 'PNG compression level of image_raw/compressed (image_transport: 3)', (0, 9))
    marker_dictionary: str = setting('', "cv2.aruco dictionary of the hand markers; empty = the description's")
    marker_ids: tuple[int, ...] = setting((), "Marker ids, in the description's order; empty = the description's",
                                          array_type='integer')
    marker_side_length: float = setting(0.0, "Black-square side [m]; 0 = the description's", (0.0, 0.05))
