"""A recorded bag in the Rerun viewer (calibration_viz.bag_view): what the layout is made of.

The bag is written the recorder's way (McapBagWriter, TfBook, the sim's and the estimator's URDFs),
so this also checks that Rerun's own MCAP importer reads what we record: the frame tree, the real
arm's meshes from /robot_description. Seeded and synthetic; no ROS graph, no browser.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from body_schema.arm_visuals import description_urdf
from body_schema.robot import load_robot
from calibration_bringup.mcap_writer import McapBagWriter
from calibration_bringup.tf_recording import TF_STATIC_TOPIC, TF_TOPIC, TF_TYPE, TfBook
from calibration_interfaces.contract import ESTIMATE_FRAME_PREFIX
from calibration_viz import bag_view

ROBOT = load_robot()
N_POSES = 5
ESTIMATE = ROBOT.dh + np.random.default_rng(3).normal(0, 0.01, ROBOT.dh.shape)


def _ghost(i: int) -> str:
    """The estimator's URDF after update ``i`` (it republishes it with every estimate)."""
    return description_urdf(ROBOT, ESTIMATE + 0.001 * i, prefix=ESTIMATE_FRAME_PREFIX)


def _hand_pose(i: int, sigma: float) -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = ROBOT.root_frame
    msg.header.stamp.sec = i
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = 0.1 * i, -0.2, 0.05
    msg.pose.pose.orientation.w = 1.0
    cov = np.diag([sigma ** 2, (2 * sigma) ** 2, (3 * sigma) ** 2, 1e-4, 1e-4, 1e-4])
    msg.pose.covariance = cov.ravel().tolist()
    return msg


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    rng = np.random.default_rng(4)
    out = tmp_path_factory.mktemp('bag_view') / 'calibration.mcap'
    book = TfBook(ROBOT)
    book.set_true(ROBOT.dh)
    book.set_estimate(ESTIMATE)
    for eye in ('left', 'right'):
        book.set_camera(eye, ROBOT.camera_pose(eye))
    with McapBagWriter(out) as w:
        for topic, type_name in (('/robot_description', 'std_msgs/msg/String'),
                                 ('/body_schema/robot_description', 'std_msgs/msg/String'),
                                 ('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped'),
                                 (TF_TOPIC, TF_TYPE), (TF_STATIC_TOPIC, TF_TYPE)):
            w.add_channel(topic, type_name)
        w.write('/robot_description', serialize_message(String(data=description_urdf(ROBOT))), 0)
        for i in range(N_POSES):
            t = (i + 1) * 10**9
            q = rng.uniform(*ROBOT.calibration_box.T)
            for rec in book.on_joint_state(ROBOT.joint_names, q.tolist(), t, t):
                w.write(rec.topic, rec.data, rec.log_time_ns)
            w.write('/hand_pose', serialize_message(_hand_pose(i, 0.001 * (i + 1))), t)
            w.write('/body_schema/robot_description', serialize_message(String(data=_ghost(i))), t)
    with open(out.parent / 'metrics.csv', 'w', newline='') as f:
        writer = csv.writer(f)
        writer.writerow(['iteration', 'sim_time', 'position_mm', 'orientation_deg'])
        for i in range(N_POSES):
            writer.writerow([i, float(i + 1), 10.0 / (i + 1), 1.0 / (i + 1)])
    return out


def test_observations_carry_their_3_sigma_ellipsoids(bag: Path) -> None:
    obs = bag_view.hand_observations(bag)
    assert obs.centers.shape == (N_POSES, 3) and obs.frame == ROBOT.root_frame
    np.testing.assert_allclose(obs.centers[:, 0], 0.1 * np.arange(N_POSES))
    # Axis-aligned covariance: the semi-axes are 3 sigma of x, y, z, in some order.
    for i, half in enumerate(obs.half_sizes):
        np.testing.assert_allclose(np.sort(half), 3 * 0.001 * (i + 1) * np.array([1.0, 2.0, 3.0]), rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(obs.quaternions, axis=1), 1.0)


def test_the_estimate_is_its_last_urdf(bag: Path) -> None:
    assert bag_view.estimate_urdf(bag) == _ghost(N_POSES - 1) != _ghost(0)


def test_error_curve_names_a_foreign_csv(tmp_path: Path) -> None:
    path = tmp_path / 'other.csv'
    path.write_text('a,b\n1,2\n')
    with pytest.raises(ValueError, match='position_mm'):
        bag_view.error_curve(path)


def test_saved_view_holds_both_arms_the_frames_observations_errors_and_layout(bag: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    rrd = tmp_path / 'view.rrd'
    assert bag_view.main([str(bag), '--save', str(rrd)]) == 0
    reader = RrdReader(rrd)
    entities = _entities(rrd)
    real = [e for e in entities if e.startswith(f'/{ROBOT.name}/visual_geometries/')]
    ghost = [e for e in entities if e.startswith(f'/{bag_view.ESTIMATE_ENTITY}/') and 'visual_geometries/estimate' in e]
    assert real, f'no meshes of the real arm from /robot_description among {sorted(entities)}'
    assert ghost, f'no meshes of the estimated arm among {sorted(entities)}'
    assert {'/tf', '/tf_static', f'/{bag_view.OBSERVATION_ENTITY}', f'/{bag_view.ERROR_ENTITY}/position_mm',
            f'/{bag_view.ERROR_ENTITY}/orientation_deg'} <= entities
    assert len(reader.blueprints()) == 1


def _entities(rrd: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {chunk.entity_path for chunk in RrdReader(rrd).stream()}


def test_a_bag_cut_by_a_crash_is_shown_up_to_what_survived(bag: Path, tmp_path: Path, capsys) -> None:
    cut = tmp_path / 'cut.mcap'
    data = bag.read_bytes()
    cut.write_bytes(data[:len(data) * 9 // 10])          # no summary, no footer: as after a SIGKILL
    assert bag_view.main([str(cut), '--save', str(tmp_path / 'cut.rrd')]) == 0
    assert 'bag truncated' in capsys.readouterr().err
    assert {'/tf', f'/{ROBOT.name}'} <= _entities(tmp_path / 'cut.rrd')


def test_a_missing_or_foreign_file_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    assert bag_view.main([str(tmp_path / 'nope.mcap'), '--save', str(tmp_path / 'x.rrd')]) == 2
    assert 'no bag at' in capsys.readouterr().err
    (tmp_path / 'notes.txt').write_text('not a bag')
    assert bag_view.main([str(tmp_path / 'notes.txt'), '--save', str(tmp_path / 'x.rrd')]) == 2
    assert 'not an MCAP file' in capsys.readouterr().err
