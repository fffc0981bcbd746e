"""The TF the recorder derives: standard TFMessage CDR, a tree from root_link to both hands and cameras."""
from __future__ import annotations

import numpy as np
import pytest
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from scipy.spatial.transform import Rotation

from body_schema.robot import load_robot
from body_schema.urdf import FrameTransform
from calibration_bringup.mcap_writer import schema_text
from calibration_bringup.tf_recording import TF_STATIC_TOPIC, TF_TOPIC, TF_TYPE, TfBook, encode_tf, tf_message

ROBOT = load_robot()


def _decode(data: bytes):
    return generate_dynamic(TF_TYPE, schema_text(TF_TYPE))[TF_TYPE](data)


def _edges(*messages) -> dict[str, tuple[str, np.ndarray]]:
    out = {}
    for m in messages:
        for t in m.transforms:
            tr, r = t.transform.translation, t.transform.rotation
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
            pose[:3, 3] = [tr.x, tr.y, tr.z]
            out[t.child_frame_id] = (t.header.frame_id, pose)
    return out


def _walk(edges: dict, frame: str) -> tuple[str, np.ndarray]:
    pose = np.eye(4)
    while frame in edges:
        parent, t = edges[frame]
        pose, frame = t @ pose, parent
    return frame, pose


def test_schema_is_the_standard_definition() -> None:
    text = schema_text(TF_TYPE)
    assert text.startswith('geometry_msgs/TransformStamped[] transforms\n')
    assert 'MSG: geometry_msgs/TransformStamped' in text and 'MSG: std_msgs/Header' in text


@pytest.mark.parametrize('count', [0, 1, 5])
def test_encoding_is_mcap_ros2s_byte_for_byte(count: int) -> None:
    # Frame names of every length modulo 4 (string padding) and stamps with large seconds.
    rng = np.random.default_rng(count)
    transforms = []
    for k in range(count):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=k).as_matrix()
        pose[:3, 3] = rng.normal(size=3)
        transforms.append(FrameTransform('p' * (k + 1), 'child_' + 'c' * k, pose))
    stamp = 1_795_811_022_052_422_767 + count
    reference = serialize_dynamic(TF_TYPE, schema_text(TF_TYPE))[TF_TYPE](tf_message(transforms, stamp))
    assert encode_tf(transforms, stamp) == bytes(reference)
    decoded = _decode(encode_tf(transforms, stamp))
    assert [t.child_frame_id for t in decoded.transforms] == [t.child for t in transforms]


def test_tree_reaches_both_hands_and_cameras_and_statics_follow_changes() -> None:
    rng = np.random.default_rng(7)
    true_dh = ROBOT.dh + rng.normal(0, 0.005, ROBOT.dh.shape)
    estimate = ROBOT.dh + rng.normal(0, 0.02, ROBOT.dh.shape)
    q = rng.uniform(*ROBOT.calibration_box.T)
    book = TfBook(ROBOT)
    book.set_true(true_dh)
    book.set_estimate(estimate)
    for eye in ('left', 'right'):
        book.set_camera(eye, ROBOT.camera_pose(eye))
    first = book.on_joint_state(list(reversed(ROBOT.joint_names)), list(reversed(q)), 1_500_000_000, 7)
    assert [r.topic for r in first] == [TF_STATIC_TOPIC, TF_TOPIC] and all(r.log_time_ns == 7 for r in first)
    static, moving = (_decode(r.data) for r in first)
    assert moving.transforms[0].header.stamp.sec == 1 and moving.transforms[0].header.stamp.nanosec == 500_000_000
    edges = _edges(static, moving)
    for hand, dh in (('hand', true_dh), ('estimate/hand', estimate)):
        root, pose = _walk(edges, hand)
        assert root == 'root_link'
        np.testing.assert_allclose(pose, ROBOT.with_dh(dh).forward_kinematics(q), atol=1e-9)
    for eye in ('left', 'right'):
        root, pose = _walk(edges, f'{eye}_camera_optical_frame')
        assert root == 'root_link'
        np.testing.assert_allclose(pose, ROBOT.camera_pose(eye), atol=1e-9)
    assert _walk(edges, 'marker_' + ROBOT.markers[0].name)[0] == 'root_link'

    # No static change: /tf only. A new estimate: /tf_static again, with every static transform.
    assert [r.topic for r in book.on_joint_state(ROBOT.joint_names, q, 2, 8)] == [TF_TOPIC]
    book.set_estimate(true_dh)
    again = book.on_joint_state(ROBOT.joint_names, q, 3, 9)
    assert [r.topic for r in again] == [TF_STATIC_TOPIC, TF_TOPIC]
    assert len(_decode(again[0].data).transforms) == len(static.transforms)
    # A joint state without every arm joint gives no /tf.
    assert book.on_joint_state(['r_elbow'], [0.1], 4, 10) == []


@pytest.mark.parametrize('bad', [[np.nan] * 7, [0.0] * 6])
def test_a_malformed_joint_state_gives_no_tf(bad: list[float]) -> None:
    book = TfBook(ROBOT)
    names = list(ROBOT.joint_names[:len(bad)])
    assert [r.topic for r in book.on_joint_state(names, bad, 1, 1)] == [TF_STATIC_TOPIC]
