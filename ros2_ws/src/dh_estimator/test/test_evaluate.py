"""Offline evaluation on a synthetic bag: it reproduces the estimate, scores every iteration,
writes its CSV, and names what a bag lacks.

The bag is written with the project's own MCAP writer (``calibration_bringup.mcap_writer``, the
recorder's) from messages serialized by rclpy: a seeded true robot, an initial guess, and per
iteration a command, joint states resting at the target, an exact hand pose with its covariance
and the selector's progress record; one iteration has no hand pose (a failed attempt).
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_schema import load_robot, sampling
from body_schema.noise import PoseDependentNoise
from calibration_bringup.mcap_writer import McapBagWriter
from calibration_interfaces.messages import covariance_to_msg, matrix_to_pose_msg, pose_msg_to_matrix, table_to_msg
from dh_estimator.estimator import OnlineEstimator
from dh_estimator.evaluate import (BagFormatError, EvaluationSettings, IterationRow, evaluate_bag, main,
                                   write_csv)

MODEL = load_robot('icub_right_arm')
TRUE_DH = sampling.perturb_dh(MODEL.dh, 11, 0.004, np.radians(2.0))
TRUE_ROBOT = MODEL.with_dh(TRUE_DH)
X0 = sampling.perturb_dh(MODEL.dh, 5)
P0 = sampling.initial_covariance(MODEL.n_joints)
NOISE = PoseDependentNoise()
FAILED = 3            # the iteration whose image showed no hand
ITERATIONS = 6


def _stamp(t: float):
    msg = JointState().header.stamp
    msg.sec, msg.nanosec = int(t), int(round((t - int(t)) * 1e9))
    return msg


def _attempts() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(q, hand pose in the root frame, R) per iteration, seeded: the true robot's exact pose, as
    it comes out of a message (the quaternion round trip changes the last bits)."""
    out = []
    for q in sampling.uniform_configs(MODEL.calibration_box, ITERATIONS, 2):
        pose = pose_msg_to_matrix(matrix_to_pose_msg(TRUE_ROBOT.forward_kinematics(q)))
        out.append((q, pose, NOISE.covariance(0.3, 30.0)))
    return out


class Bag:
    """Writes messages with increasing log times."""

    def __init__(self, path: Path) -> None:
        self.w = McapBagWriter(path)
        self.t_ns = 0

    def put(self, topic: str, type_name: str, msg: object, t: float) -> None:
        self.w.add_channel(topic, type_name)
        self.t_ns = max(self.t_ns + 1, int(t * 1e9))
        self.w.write(topic, serialize_message(msg), self.t_ns)


def write_bag(path: Path, *, true: bool = True, initial: bool = True,
              online: list[np.ndarray] | None = None) -> Path:
    """The synthetic run; ``online`` are the tables the 'node' published after each update."""
    bag = Bag(path)
    if true:
        bag.put('/body_schema/true', 'std_msgs/msg/Float64MultiArray', table_to_msg(TRUE_DH), 0.0)
    if initial:
        bag.put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(X0), 0.0)
        bag.put('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', covariance_to_msg(P0), 0.0)
    updates = iter(online or [])
    movement = 0.0
    for k, (q, pose, R) in enumerate(_attempts(), start=1):
        t0 = 2.0 * k
        cmd = JointTrajectory(joint_names=list(MODEL.joint_names),
                              points=[JointTrajectoryPoint(positions=q.tolist())])
        bag.put('/arm/command', 'trajectory_msgs/msg/JointTrajectory', cmd, t0)
        for t in np.arange(t0 + 0.01, t0 + 0.5, 0.02):           # resting at the target
            js = JointState(name=list(MODEL.joint_names), position=q.tolist())
            js.header.stamp = _stamp(float(t))
            bag.put('/joint_states', 'sensor_msgs/msg/JointState', js, float(t))
        if k != FAILED:
            hp = PoseWithCovarianceStamped()
            hp.header.stamp = _stamp(t0 + 0.3)
            hp.pose.pose = matrix_to_pose_msg(pose)
            hp.pose.covariance = R.ravel().tolist()
            bag.put('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped', hp, t0 + 0.5)
            if online is not None:
                bag.put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(next(updates)),
                        t0 + 0.5)
        movement += 10.0
        record = {'iteration': k, 'strategy': 'al', 'outcome': 'failed' if k == FAILED else 'accepted',
                  'detected': k != FAILED, 'movement_deg': movement, 'discarded': int(k >= FAILED),
                  'selection_s': 0.1, 'sim_time': t0 + 0.6}
        bag.put('/calibration/progress', 'std_msgs/msg/String', String(data=json.dumps(record)), t0 + 0.6)
    bag.w.close()
    return path


def direct_run() -> list[np.ndarray]:
    """The filter fed the detected attempts directly: the table after each update."""
    est = OnlineEstimator(MODEL, X0, P0, EvaluationSettings().estimator)
    tables = []
    for k, (q, pose, R) in enumerate(_attempts(), start=1):
        if k != FAILED:
            assert est.offer(q, pose, R).value == 'accepted'
            tables.append(est.dh.copy())
    return tables


def test_the_offline_run_reproduces_the_filter_and_the_online_estimate(tmp_path: Path) -> None:
    tables = direct_run()
    ev = evaluate_bag(write_bag(tmp_path / 'run.mcap', online=tables))
    # Equal up to rounding: the joint states are interpolated at the image stamp.
    np.testing.assert_allclose(ev.final_dh, tables[-1], rtol=0, atol=1e-11)
    assert ev.max_online_offline_difference < 1e-11
    np.testing.assert_array_equal(ev.true_dh, TRUE_DH)
    assert ev.counters['updates'] == ITERATIONS - 1 and ev.strategy == 'al'

    rows = ev.rows
    assert [r.iteration for r in rows] == list(range(ITERATIONS + 1))
    assert rows[0].outcome == 'initial' and rows[0].offline_updates == 0
    assert [r.offline_updates for r in rows[1:]] == [1, 2, 2, 3, 4, 5]     # nothing at the failed one
    assert rows[FAILED].outcome == 'failed' and not rows[FAILED].detected
    assert rows[FAILED].position_mm == rows[FAILED - 1].position_mm
    assert [r.position_mm for r in rows] == pytest.approx([r.online_position_mm for r in rows], abs=1e-6)
    # Exact poses of the true robot: five updates already lower the error of the initial guess.
    assert rows[-1].position_mm < rows[0].position_mm


def test_initial_guess_choices_and_the_csv(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / 'run.mcap')
    recorded = evaluate_bag(bag)
    nominal = evaluate_bag(bag, EvaluationSettings(initial='nominal'))
    perturbed = evaluate_bag(bag, EvaluationSettings(initial='perturbed', initial_seed=5))
    # The node's seeded guess is the recorded one (seed 5): the same run, to the bit.
    np.testing.assert_array_equal(perturbed.final_dh, recorded.final_dh)
    assert nominal.rows[0].position_mm != recorded.rows[0].position_mm

    path = write_csv(recorded.rows, tmp_path / 'out' / 'metrics.csv')
    with path.open(newline='') as f:
        lines = list(csv.DictReader(f))
    assert list(lines[0]) == list(IterationRow.__dataclass_fields__)
    assert len(lines) == ITERATIONS + 1
    assert float(lines[-1]['position_mm']) == pytest.approx(recorded.rows[-1].position_mm)
    assert lines[FAILED]['outcome'] == 'failed' and lines[FAILED]['detected'] == 'False'


def test_what_a_bag_lacks_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match='nothing.mcap'):
        evaluate_bag(tmp_path / 'nothing.mcap')
    with pytest.raises(BagFormatError, match='/body_schema/true'):
        evaluate_bag(write_bag(tmp_path / 'no_truth.mcap', true=False))
    # No recorded initial estimate: iterations cannot be scored from the recording alone ...
    no_initial = write_bag(tmp_path / 'no_initial.mcap', initial=False)
    with pytest.raises(BagFormatError, match='initial'):
        evaluate_bag(no_initial)
    # ... but the node's seeded guess can stand in for it.
    assert evaluate_bag(no_initial, EvaluationSettings(initial='perturbed', initial_seed=5)).counters['updates'] == 5
    with pytest.raises(ValueError, match='guessed'):
        EvaluationSettings(initial='guessed')


def test_the_command_line_writes_the_csv_or_says_what_is_wrong(tmp_path: Path, capsys) -> None:
    bag = write_bag(tmp_path / 'run.mcap')
    assert main([str(bag), '--output', str(tmp_path / 'eval'), '--no-plots']) == 0
    assert (tmp_path / 'eval' / 'metrics.csv').is_file()
    assert 'position error' in capsys.readouterr().out
    assert main([str(tmp_path / 'missing.mcap'), '--no-plots']) == 2
    assert 'missing.mcap' in capsys.readouterr().err
