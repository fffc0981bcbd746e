"""One calibration run as a ROS 2 node graph, for full ROS 2 installs (``ros2 launch``).

Usage::

    ros2 launch calibration_bringup calibration.launch.py strategy:=al iterations:=50 seed:=1 \\
        noise:=pose_dependent output:=results/run

Starts the MCAP recorder, simulator, detector, estimator and selector, each with its parameter
file from ``share/calibration_bringup/config`` plus the run's arguments, exactly as
``scripts/run_calibration.sh`` does (the launcher of pip-only installs such as this repository's
.venv, which has no ``launch`` package); when the selector has finished its iterations the whole
launch shuts down (SIGINT: the estimator exports its model, the recorder closes the bag). Then
``calibration_report --bag <output>/calibration.mcap --output <output>`` writes the report.

The node table (:func:`node_specs`) is plain data, importable without ``launch``, so the tests
check it against the installed executables, parameter files and declared parameters.
"""
from __future__ import annotations

import os
from typing import Any

from body_schema.noise import NOISE_MODELS
from calibration_interfaces.contract import COMPRESSED_IMAGE_TOPICS, IMAGE_TOPICS, IMAGE_TRANSPORTS
from calibration_interfaces.image_conversion import ENCODINGS

#: Launch arguments: name -> (default, description).
ARGUMENTS: dict[str, tuple[str, str]] = {
    'robot': ('icub_right_arm', 'robot description: a packaged name (icub_right_arm, ur5e) or a YAML path'),
    'strategy': ('al', 'random | al | ucsal | ccsal'),
    'iterations': ('50', 'measurement attempts (selector iterations)'),
    'seed': ('1', 'seed of the real robot, the initial guess and the selector'),
    'noise': ('pose_dependent', "pose_dependent | constant (the paper's CN baseline)"),
    'estimator': ('map', "map (online MAP, default) | ekf (the paper's filter)"),
    'body_change': ('', 'a change of the real robot mid-run, e.g. "r_wrist_prosup.d+0.010 r_shoulder_yaw.offset+3"'),
    'body_change_at': ('0', 'the selector iteration at whose command the body changes (0: never)'),
    'rtf': ('1.0', 'simulated seconds per wall second; 0 = as fast as possible'),
    'record_images': ('true', 'record the camera images (false: smaller bag)'),
    'transport': ('raw', 'raw | compressed: the detector reads image_raw/compressed (JPEG) and the bag records it'),
    'image_encoding': ('rgb8', 'encoding of the simulated camera, e.g. bayer_rggb8, yuv422 (calibration_interfaces.'
                               'image_conversion.ENCODINGS)'),
    'camera_info_url': ('', "the detector's intrinsics from a camera_info_manager file (file:///.../ost.yaml) "
                            'instead of camera_info'),
    'output': ('results/run', 'directory of the bag, the model export and progress.jsonl'),
    'viz': ('false', 'true: also serve the live 3D view (calibration_viz) at http://127.0.0.1:8080'),
}


def node_specs(args: dict[str, str]) -> list[dict[str, Any]]:
    """The graph's nodes for launch-argument values ``args`` (every key of :data:`ARGUMENTS`).

    Returns
    -------
    list of dict
        In start order, each with ``name``, ``package``, ``executable``, ``params_file`` (in the
        config directory of ``config_package``, default ``calibration_bringup``) and ``parameters``
        (overrides, typed).
    """
    out = os.path.abspath(args['output'])
    noise = args['noise']
    if noise not in NOISE_MODELS:
        raise ValueError(f'noise must be one of {list(NOISE_MODELS)}, got {noise!r}')
    seed = int(args['seed'])
    if args['estimator'] not in ('map', 'ekf'):
        raise ValueError(f"estimator must be 'map' or 'ekf', got {args['estimator']!r}")
    if args['viz'].lower() not in ('true', 'false'):
        raise ValueError(f"viz must be 'true' or 'false', got {args['viz']!r}")
    transport = args['transport']
    if transport not in IMAGE_TRANSPORTS:
        raise ValueError(f'transport must be one of {list(IMAGE_TRANSPORTS)}, got {transport!r}')
    if args['image_encoding'] not in ENCODINGS:
        raise ValueError(f"image_encoding must be one of {sorted(ENCODINGS)}, got {args['image_encoding']!r}")
    # The bag records the images of the transport the detector reads.
    other = [t for t in IMAGE_TOPICS if (t in COMPRESSED_IMAGE_TOPICS) == (transport == 'raw')]
    detector = {'transport': transport}
    if args['camera_info_url']:
        detector['camera_info_url'] = args['camera_info_url']
    # The view's parameter file is its own package's (as run_calibration.sh --viz uses it).
    viz = [{'name': 'viz', 'package': 'calibration_viz', 'executable': 'viz_node', 'params_file': 'viz.yaml',
            'config_package': 'calibration_viz', 'parameters': {'transport': transport}}] \
        if args['viz'].lower() == 'true' else []
    specs = [
        # The recorder first, so every latched fact (true table, initial estimate, camera poses) is in the bag.
        {'name': 'recorder', 'package': 'calibration_bringup', 'executable': 'recorder_node',
         'params_file': 'recorder.yaml',
         'parameters': {'output': os.path.join(out, 'calibration.mcap'),
                        'exclude_images': args['record_images'].lower() != 'true', 'exclude': other}},
        {'name': 'sim', 'package': 'icub_sim_bridge', 'executable': 'sim_node', 'params_file': 'sim.yaml',
         'parameters': {'perturb_seed': seed, 'real_time_factor': float(args['rtf']),
                        'body_change': args['body_change'], 'body_change_at_command': int(args['body_change_at']),
                        'image_encoding': args['image_encoding'],
                        'compressed_format': 'jpeg' if transport == 'compressed' else 'none'}},
        {'name': 'detector', 'package': 'marker_detector', 'executable': 'detector_node',
         'params_file': 'detector.yaml', 'parameters': detector},
        {'name': 'estimator', 'package': 'dh_estimator', 'executable': 'estimator_node',
         'params_file': 'estimator.yaml',
         'parameters': {'initial_seed': seed, 'noise_model': noise, 'estimator': args['estimator'],
                        'export_dir': os.path.join(out, 'model')}},
        {'name': 'selector', 'package': 'active_selector', 'executable': 'selector_node',
         'params_file': 'selector.yaml',
         'parameters': {'strategy': args['strategy'], 'iterations': int(args['iterations']), 'seed': seed,
                        'noise_model': noise, 'progress_file': os.path.join(out, 'progress.jsonl')}},
        *viz,
    ]
    # Every node reads the same description (as run_calibration.sh --robot passes it to each).
    for spec in specs:
        spec['parameters'] = {'robot': args['robot'], **spec['parameters']}
    return specs


def generate_launch_description() -> Any:
    """The launch description: arguments, the Fast DDS profile, the nodes, shutdown after the selector."""
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import (DeclareLaunchArgument, EmitEvent, OpaqueFunction, RegisterEventHandler,
                                SetEnvironmentVariable)
    from launch.event_handlers import OnProcessExit
    from launch.events import Shutdown
    from launch.substitutions import EnvironmentVariable
    from launch_ros.actions import Node

    def config_dir(package: str) -> str:
        return os.path.join(get_package_share_directory(package), 'config')

    config = config_dir('calibration_bringup')

    def nodes(context: Any) -> list[Any]:
        values = {k: context.launch_configurations[k] for k in ARGUMENTS}
        actions, selector = [], None
        for spec in node_specs(values):
            node = Node(package=spec['package'], executable=spec['executable'], output='screen',
                        parameters=[os.path.join(config_dir(spec.get('config_package', 'calibration_bringup')),
                                                 spec['params_file']), spec['parameters']])
            actions.append(node)
            if spec['name'] == 'selector':
                selector = node
        # The selector exits after its last iteration: that ends the run.
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=selector, on_exit=[EmitEvent(event=Shutdown(reason='calibration finished'))])))
        return actions

    # Shared-memory segments sized for camera frames, unless the caller chose a profile.
    profile = os.path.join(config, 'fastdds_shm.xml')
    env = [SetEnvironmentVariable(v, EnvironmentVariable(v, default_value=profile))
           for v in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')]
    return LaunchDescription([
        *(DeclareLaunchArgument(k, default_value=d, description=text) for k, (d, text) in ARGUMENTS.items()),
        *env,
        OpaqueFunction(function=nodes),
    ])
