"""The paired replay: a bag's frames re-detected as rgb8 give back its hand poses exactly, as
another encoding they move; a run's attempts are re-judged per encoding on its real robot."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image

from body_schema import load_robot
from body_schema.sampling import uniform_configs
from calibration_bringup.mcap_writer import McapBagWriter
from calibration_interfaces.image_conversion import image_to_gray, rgb_to_image_fields
from calibration_interfaces.messages import matrix_to_pose_msg, table_to_msg
from calibration_interfaces.noise import NoiseSettings
from marker_detector.detection import HandPoseEstimator
from tools.encoding_bench import VARIANTS
from tools.encoding_replay import failures, redetect

MODEL = load_robot('icub_right_arm')
BY_NAME = {v.name: v for v in VARIANTS}


@pytest.fixture(scope='module')
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A run directory with a bag as the recorder writes it (left camera, hand poses as the node
    publishes them) and the selector's progress.jsonl; returns it and its number of hand poses."""
    from icub_sim_bridge.world import SimWorld

    out = tmp_path_factory.mktemp('run')
    k, root_T_cam = MODEL.camera, MODEL.camera_pose('left')
    est = HandPoseEstimator(MODEL, NoiseSettings().build(MODEL))
    configs = uniform_configs(MODEL.calibration_box, 12, 3)
    hands = 0
    with McapBagWriter(out / 'calibration.mcap') as bag, SimWorld(MODEL) as world:
        for topic, kind in (('/camera/left/camera_info', 'sensor_msgs/msg/CameraInfo'),
                            ('/camera/left/pose', 'geometry_msgs/msg/PoseStamped'),
                            ('/camera/left/image_raw', 'sensor_msgs/msg/Image'),
                            ('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped'),
                            ('/body_schema/true', 'std_msgs/msg/Float64MultiArray')):
            bag.add_channel(topic, kind)
        info = CameraInfo(width=k.width, height=k.height, distortion_model='plumb_bob', d=[0.0] * 5,
                          k=k.K.reshape(-1).tolist())
        bag.write('/camera/left/camera_info', serialize_message(info), 1)
        bag.write('/camera/left/pose', serialize_message(PoseStamped(pose=matrix_to_pose_msg(root_T_cam))), 1)
        bag.write('/body_schema/true', serialize_message(table_to_msg(MODEL.dh)), 1)
        for i, q in enumerate(configs):
            world.set_joint_positions(q)
            img = Image(**rgb_to_image_fields(world.render(root_T_cam, k), 'rgb8'))
            img.header.stamp.sec = i + 1
            t = (i + 1) * 10**9
            bag.write('/camera/left/image_raw', serialize_message(img), t)
            hand = est.process(image_to_gray(img), k.K, np.zeros(5), root_T_cam).hand   # as the node
            if hand is not None:
                msg = PoseWithCovarianceStamped()
                msg.header.stamp = img.header.stamp
                msg.pose.pose = matrix_to_pose_msg(hand.pose)
                bag.write('/hand_pose', serialize_message(msg), t + 5_000_000)
                hands += 1
    records = [{'iteration': i + 1, 'outcome': 'accepted', 'reached_deg': np.degrees(q).tolist()}
               for i, q in enumerate(configs)]
    (out / 'progress.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in records))
    return out, hands


def test_rgb8_reproduces_the_hand_poses_and_jpeg_moves_them(run: tuple[Path, int], tmp_path: Path) -> None:
    directory, hands = run
    assert hands >= 3, 'the fixture must show the hand in some frames'
    written, worst = redetect(directory / 'calibration.mcap', tmp_path / 'rgb8.mcap', BY_NAME['rgb8'])
    assert written == hands and worst < 1e-9               # the message's quaternion: 1e-16
    written, worst = redetect(directory / 'calibration.mcap', tmp_path / 'jpeg.mcap',
                              BY_NAME['compressed JPEG q90 (rgb8)'])
    assert written >= hands - 1 and 0.0 < worst < 0.05          # metres or rotation-matrix entries


def test_failures_rejudge_each_attempt(run: tuple[Path, int]) -> None:
    directory, hands = run
    counts = failures(directory, BY_NAME['bayer_rggb8'])
    assert sum(counts.values()) == 12
    seen_by_rgb8 = sum(n for (outcome, rgb8, _), n in counts.items() if rgb8)
    assert seen_by_rgb8 == hands and all(outcome == 'accepted' for outcome, _, _ in counts)
