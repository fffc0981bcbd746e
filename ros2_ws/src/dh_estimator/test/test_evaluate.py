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
from dataclasses import replace
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
from calibration_interfaces.contract import PUBLISH_TIME_SOURCE
from calibration_interfaces.messages import covariance_to_msg, matrix_to_pose_msg, pose_msg_to_matrix, table_to_msg
from dh_estimator.estimator import OnlineEstimator
from dh_estimator.evaluate import (BagFormatError, EvaluationSettings, IterationRow, evaluate_bag, main, summary_text,
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

    def __init__(self, path: Path, chunk_size: int = 1 << 20) -> None:
        self.w = McapBagWriter(path, chunk_size=chunk_size)
        self.t_ns = 0

    def put(self, topic: str, type_name: str, msg: object, t: float) -> None:
        self.w.add_channel(topic, type_name)
        self.t_ns = max(self.t_ns + 1, int(t * 1e9))
        self.w.write(topic, serialize_message(msg), self.t_ns)


def write_bag(path: Path, *, true: bool = True, initial: bool = True,
              online: list[np.ndarray] | None = None, stray_at: float | None = None,
              chunk_size: int = 1 << 20, late_last: bool = False) -> Path:
    """The synthetic run; ``online`` are the tables the 'node' published after each update.

    ``late_last``: the last hand pose is logged after the last progress record (a recorder that
    fell behind on one topic: seen under load, the node had used it before the record).

    ``stray_at``: log time [s] of one extra joint state stamped 1000 s (a publisher with a wrong
    clock that only the recorder heard).
    """
    bag = Bag(path, chunk_size)
    if true:
        bag.put('/body_schema/true', 'std_msgs/msg/Float64MultiArray', table_to_msg(TRUE_DH), 0.0)
    if initial:
        bag.put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(X0), 0.0)
        bag.put('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', covariance_to_msg(P0), 0.0)
    updates = iter(online or [])
    movement = 0.0
    for k, (q, pose, R) in enumerate(_attempts(), start=1):
        t0 = 2.0 * k
        late = None
        cmd = JointTrajectory(joint_names=list(MODEL.joint_names),
                              points=[JointTrajectoryPoint(positions=q.tolist())])
        bag.put('/arm/command', 'trajectory_msgs/msg/JointTrajectory', cmd, t0)
        for t in np.arange(t0 + 0.01, t0 + 0.5, 0.02):           # resting at the target
            js = JointState(name=list(MODEL.joint_names), position=q.tolist())
            js.header.stamp = _stamp(float(t))
            bag.put('/joint_states', 'sensor_msgs/msg/JointState', js, float(t))
            if stray_at is not None and t >= stray_at:
                js = JointState(name=list(MODEL.joint_names), position=(q + 0.3).tolist())
                js.header.stamp = _stamp(1000.0)
                bag.put('/joint_states', 'sensor_msgs/msg/JointState', js, float(t))
                stray_at = None
        if k != FAILED:
            hp = PoseWithCovarianceStamped()
            hp.header.stamp = _stamp(t0 + 0.3)
            hp.pose.pose = matrix_to_pose_msg(pose)
            hp.pose.covariance = R.ravel().tolist()
            late = hp if late_last and k == ITERATIONS else None
            if late is None:
                bag.put('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped', hp, t0 + 0.5)
            if online is not None:
                bag.put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(next(updates)),
                        t0 + 0.5)
        movement += 10.0
        record = {'iteration': k, 'strategy': 'al', 'outcome': 'failed' if k == FAILED else 'accepted',
                  'detected': k != FAILED, 'movement_deg': movement, 'discarded': int(k >= FAILED),
                  'selection_s': 0.1, 'sim_time': t0 + 0.6}
        bag.put('/calibration/progress', 'std_msgs/msg/String', String(data=json.dumps(record)), t0 + 0.6)
        if late is not None:
            bag.put('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped', late, t0 + 0.7)
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
    # To 10 nm: the interpolation's rounding moves the iCub's tuned robust loss (scale 1.8) by ~1e-6 mm.
    assert [r.position_mm for r in rows] == pytest.approx([r.online_position_mm for r in rows], abs=1e-5)
    # Exact poses of the true robot: five updates already lower the error of the initial guess.
    assert rows[-1].position_mm < rows[0].position_mm
    # The information limit shrinks with every update and stays put at the failed iteration.
    limits = [r.expected_position_mm for r in rows]
    assert all(np.isfinite(limits)) and limits[-1] < 0.5 * limits[0]
    assert limits[FAILED] == limits[FAILED - 1]
    assert 'information limit' in summary_text(ev)


def test_the_last_row_holds_what_was_logged_after_the_last_record(tmp_path: Path) -> None:
    """Nothing follows the last iteration: an observation the recorder logged after its record
    belongs to it (the final table and the last row agreed only when logging kept up)."""
    tables = direct_run()
    ev = evaluate_bag(write_bag(tmp_path / 'run.mcap', online=tables, late_last=True))
    assert ev.rows[-1].offline_updates == ITERATIONS - 1
    assert ev.rows[-1].position_mm == pytest.approx(ev.rows[-1].online_position_mm, abs=1e-6)
    np.testing.assert_allclose(ev.final_dh, tables[-1], rtol=0, atol=1e-11)


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


def test_a_stray_stamp_only_the_recorder_heard_leaves_the_offline_run_equal_to_the_online_one(tmp_path: Path) -> None:
    # On main the stray joint state became the re-run's newest sample: every later one was
    # thrown away, the offline estimate stopped after the first update and disagreed with the
    # online one (exit 0, a silent wrong answer in the report).
    tables = direct_run()
    ev = evaluate_bag(write_bag(tmp_path / 'stray.mcap', online=tables, stray_at=2.2))
    assert ev.counters['updates'] == ITERATIONS - 1
    assert ev.max_online_offline_difference < 1e-11
    assert ev.pairing['future_joint_states'] == 1
    assert 'future joint states 1' in summary_text(ev)


def write_lagging_bag(path: Path, online: list[np.ndarray], lag: float, publish_times: bool) -> Path:
    """The synthetic run as a recorder that fell ``lag`` seconds behind on /joint_states logs it.

    Per iteration: the command, joint states every 20 ms resting at the target, a hand pose every
    50 ms from 0.3 s (only the first is a new configuration; the rest are duplicates), the
    estimate after the first, the progress record. Each message's publish time is when it was
    sent; its log time is that too, but ``lag`` later for the joint states: as the recorder's
    executor, which takes one message per topic per wait, logged them under load (1.5-2 s of sim
    time late at rtf 2, measured). ``publish_times``: the bag says its publish times are the
    publishers' (metadata ``publish_time: source``), as the recorder's do.
    """
    events: list[tuple[float, float, int, str, str, object]] = []   # (log time, publish time, seq, ...)

    def put(topic: str, type_name: str, msg: object, t: float, delay: float = 0.0) -> None:
        events.append((t + delay, t, len(events), topic, type_name, msg))

    put('/body_schema/true', 'std_msgs/msg/Float64MultiArray', table_to_msg(TRUE_DH), 0.0)
    put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(X0), 0.0)
    put('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', covariance_to_msg(P0), 0.0)
    updates = iter(online)
    for k, (q, pose, R) in enumerate(_attempts(), start=1):
        t0 = 2.0 * k
        put('/arm/command', 'trajectory_msgs/msg/JointTrajectory',
            JointTrajectory(joint_names=list(MODEL.joint_names), points=[JointTrajectoryPoint(positions=q.tolist())]),
            t0)
        for t in np.arange(t0 + 0.01, t0 + 1.0, 0.02):
            js = JointState(name=list(MODEL.joint_names), position=q.tolist())
            js.header.stamp = _stamp(float(t))
            put('/joint_states', 'sensor_msgs/msg/JointState', js, float(t), lag)
        if k != FAILED:
            for i, t in enumerate(np.arange(t0 + 0.3, t0 + 0.99, 0.05)):
                hp = PoseWithCovarianceStamped()
                hp.header.stamp = _stamp(float(t))
                hp.pose.pose = matrix_to_pose_msg(pose)
                hp.pose.covariance = R.ravel().tolist()
                put('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped', hp, float(t) + 0.015)
                if i == 0:
                    put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(next(updates)),
                        float(t) + 0.03)
        record = {'iteration': k, 'strategy': 'al', 'outcome': 'failed' if k == FAILED else 'accepted',
                  'detected': k != FAILED, 'movement_deg': 10.0 * k, 'discarded': int(k >= FAILED),
                  'selection_s': 0.1, 'sim_time': t0 + 1.0}
        put('/calibration/progress', 'std_msgs/msg/String', String(data=json.dumps(record)), t0 + 1.0)
    w = McapBagWriter(path)
    if publish_times:
        w.add_metadata('recording', {'log_time': 'sim', 'tf': 'none', 'publish_time': PUBLISH_TIME_SOURCE})
    last = 0
    for log_t, pub_t, _, topic, type_name, msg in sorted(events, key=lambda e: (e[0], e[2])):
        w.add_channel(topic, type_name)
        last = max(last + 1, int(round(log_t * 1e9)))      # the recorder's log times: arrival order
        w.write(topic, serialize_message(msg), last, int(round(pub_t * 1e9)))
    w.close()
    return path


def test_a_recorder_behind_on_joint_states_leaves_the_re_run_equal_to_the_online_one(tmp_path: Path) -> None:
    """The re-run replays the order the messages were published in, not the recorder's.

    On main the re-run replayed log order: each hand pose waited for joint states logged 1.5 s
    later, behind more than ``max_pending`` newer images, and was dropped (a launched run: 2 of
    its 5 online updates re-run, 'pending dropped 236', 25 mm offline against 3.5 mm online).
    """
    tables = direct_run()
    lagging = evaluate_bag(write_lagging_bag(tmp_path / 'lag.mcap', tables, lag=1.5, publish_times=True))
    assert lagging.counters['updates'] == ITERATIONS - 1
    assert lagging.pairing['pending_dropped'] == 0
    assert lagging.max_online_offline_difference < 1e-11
    assert [r.offline_updates for r in lagging.rows[1:]] == [1, 2, 2, 3, 4, 5]
    # The same bag without the recorder's word on its publish times is replayed as logged: the
    # order that lost the updates (what a bag of another recorder gets).
    legacy = evaluate_bag(write_lagging_bag(tmp_path / 'legacy.mcap', tables, lag=1.5, publish_times=False))
    assert legacy.pairing['pending_dropped'] > 0 and legacy.counters['updates'] < ITERATIONS - 1
    # A recorder that kept up: both orders agree.
    prompt = evaluate_bag(write_lagging_bag(tmp_path / 'prompt.mcap', tables, lag=0.0, publish_times=False))
    assert prompt.counters['updates'] == ITERATIONS - 1 and prompt.max_online_offline_difference < 1e-11


def _chunks(path: Path):
    from mcap.reader import make_reader

    with path.open('rb') as f:
        return make_reader(f).get_summary().chunk_indexes


@pytest.mark.parametrize('where', ['in a chunk', 'in a message index'])
def test_a_truncated_bag_is_evaluated_up_to_its_last_complete_chunk_and_says_so(tmp_path: Path, where: str,
                                                                                capsys) -> None:
    # As a SIGKILLed recorder leaves it. On main a cut in a message index (the record after each
    # chunk) made evaluate and calibration_report fail with a raw struct.error traceback.
    full = write_bag(tmp_path / 'full.mcap', chunk_size=4096)
    chunks = _chunks(full)
    c = chunks[2 * len(chunks) // 3]
    cut = c.chunk_start_offset + (c.chunk_length // 2 if where == 'in a chunk' else c.chunk_length + 5)
    bag = tmp_path / 'cut.mcap'
    bag.write_bytes(full.read_bytes()[:cut])
    ev = evaluate_bag(bag)
    assert not ev.bag.complete and 0 < ev.bag.message_count
    assert 1 <= len(ev.rows) - 1 < ITERATIONS                    # some iterations recovered, not all
    lost = 'the last chunk' if where == 'in a chunk' else 'MESSAGE_INDEX cut'
    assert ev.bag.loss.startswith(f'bag truncated (cut.mcap was not finished): recovered {ev.bag.message_count} '
                                  'messages up to t=') and lost in ev.bag.loss
    assert main([str(bag), '--output', str(tmp_path / 'eval'), '--no-plots']) == 0
    assert 'bag truncated' in capsys.readouterr().out

    from calibration_bringup.report import main as report_main

    assert report_main(['--bag', str(bag), '--output', str(tmp_path / 'report')]) == 0
    assert f'**{ev.bag.loss}.**' in (tmp_path / 'report' / 'report.md').read_text()
    # The same figures, machine-readable for studies over many runs.
    import json

    rec = json.loads((tmp_path / 'report' / 'summary.json').read_text())
    assert rec['iterations'] == ev.rows[-1].iteration and sum(rec['outcomes'].values()) == rec['iterations']
    assert rec['final']['position_mm'] == pytest.approx(ev.rows[-1].position_mm)
    assert rec['initial']['orientation_deg'] == pytest.approx(ev.rows[0].orientation_deg)
    assert rec['identifiable'] == ev.identifiable and rec['nees_band'][0] < rec['nees_band'][1]
    assert rec['nees_identifiable'] == pytest.approx(ev.nees_identifiable)


@pytest.mark.parametrize('content, says', [(b'', 'is empty'), (b'PK\x03\x04 a zip file', 'is not an MCAP file')])
def test_an_empty_or_foreign_file_is_one_line_and_a_failure(tmp_path: Path, capsys, content: bytes,
                                                           says: str) -> None:
    # On main both were read as a bag without messages: 'no /body_schema/true message'.
    bag = tmp_path / 'x.mcap'
    bag.write_bytes(content)
    assert main([str(bag), '--no-plots']) == 2
    err = capsys.readouterr().err
    assert err == f'evaluate: {bag} {says}' + (" (it starts with b'PK\\x03\\x04 a z')" if content else '') + '\n'

    from calibration_bringup.report import main as report_main

    assert report_main(['--bag', str(bag), '--output', str(tmp_path / 'report')]) == 1
    assert capsys.readouterr().err.startswith(f'calibration_report: {bag} {says}')


# --------------------------------------------------------------------------------------------
# A UR5e whose real camera and marker are off the description's, estimated with the table

def _ur5e_bag(path: Path, with_truth: bool) -> tuple[Path, dict[str, np.ndarray]]:
    """18 exact attempts through a camera 2 cm / 2 deg and a marker 5 mm / 5 deg off."""
    from body_schema.extrinsics import corrections, random_delta
    from calibration_interfaces.messages import extrinsics_to_msg
    ur = load_robot('ur5e')
    rng = np.random.default_rng(3)
    true_dh = sampling.perturb_dh(ur.dh, rng, 0.004, np.radians(2.0))
    c, m = random_delta(rng, 0.02, np.radians(2.0)), random_delta(rng, 0.005, np.radians(5.0))
    big_e, big_f = corrections(ur.camera_pose('left'), ur.markers[0].hand_T_marker, c, m)
    x0 = sampling.perturb_dh(ur.dh, rng, 0.01, np.radians(3.0))
    bag = Bag(path)
    bag.put('/body_schema/true', 'std_msgs/msg/Float64MultiArray', table_to_msg(true_dh), 0.0)
    if with_truth:
        bag.put('/body_schema/true_extrinsics', 'std_msgs/msg/Float64MultiArray', extrinsics_to_msg(c, m), 0.0)
    bag.put('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', table_to_msg(x0), 0.0)
    # The node publishes the covariance of the table and both corrections (36 x 36).
    p0 = np.diag(np.concatenate([np.diag(sampling.initial_covariance(6, 0.01, np.radians(3.0))),
                                 [0.02 ** 2] * 3 + [np.radians(2.0) ** 2] * 3 + [0.005 ** 2] * 3
                                 + [np.radians(5.0) ** 2] * 3]))
    bag.put('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', covariance_to_msg(p0), 0.0)
    for k, q in enumerate(sampling.uniform_configs(ur.calibration_box, 18, 4), start=1):
        t0 = 2.0 * k
        cmd = JointTrajectory(joint_names=list(ur.joint_names), points=[JointTrajectoryPoint(positions=q.tolist())])
        bag.put('/arm/command', 'trajectory_msgs/msg/JointTrajectory', cmd, t0)
        for t in np.arange(t0 + 0.01, t0 + 0.5, 0.02):
            js = JointState(name=list(ur.joint_names), position=q.tolist())
            js.header.stamp = _stamp(float(t))
            bag.put('/joint_states', 'sensor_msgs/msg/JointState', js, float(t))
        hp = PoseWithCovarianceStamped()
        hp.header.stamp = _stamp(t0 + 0.3)
        hp.pose.pose = matrix_to_pose_msg(big_e @ ur.with_dh(true_dh).forward_kinematics(q) @ big_f)
        hp.pose.covariance = np.diag([1e-8] * 3 + [1e-7] * 3).ravel().tolist()     # 0.1 mm, 0.02 deg
        bag.put('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped', hp, t0 + 0.5)
        record = {'iteration': k, 'strategy': 'random', 'outcome': 'accepted', 'detected': True,
                  'movement_deg': 10.0 * k, 'discarded': 0, 'selection_s': 0.0, 'sim_time': t0 + 0.6}
        bag.put('/calibration/progress', 'std_msgs/msg/String', String(data=json.dumps(record)), t0 + 0.6)
    bag.w.close()
    return path, {'c': c, 'm': m}


@pytest.mark.parametrize('with_truth', [True, False])
def test_camera_and_marker_are_scored_against_the_truth_in_the_tables_gauge(tmp_path: Path, with_truth: bool) -> None:
    path, _ = _ur5e_bag(tmp_path / 'ur.mcap', with_truth)
    settings = EvaluationSettings.from_parameters({'robot': 'ur5e', 'camera_prior': '0.02 2',
                                                   'marker_prior': '0.005 5', 'noise_model': 'pose_dependent'})
    ev = evaluate_bag(path, settings)
    assert ev.parameters == 36 and ev.identifiable == 28
    # Exact observations: the table is right in the description's gauge, whatever the camera did.
    assert ev.rows[-1].position_mm < 0.5 and ev.rows[-1].orientation_deg < 0.05
    err, sigma = ev.extrinsics['camera']
    text = summary_text(ev)
    assert 'camera pose error' in text and "held at the description's value" in text
    if with_truth:
        assert np.all(np.abs(err) < 3.0 * np.asarray(sigma)) and max(abs(e) for e in err[:3]) < 1.0
        assert np.isfinite(ev.nees_identifiable)
    else:
        assert np.all(np.isnan(err)) and np.isnan(ev.nees_identifiable)


def test_the_truth_is_scored_on_the_branch_of_the_table_the_estimate_took() -> None:
    # An estimate on the UR5e's twin table (elbow a > 0, its offset and the next turned by pi)
    # moves the hand exactly as the truth: its error is zero, not pi.
    from dh_estimator.estimator import EstimatorSettings
    from dh_estimator.evaluate import true_state

    ur = load_robot('ur5e')
    twin = ur.dh.copy()
    twin[2, 0], twin[2, 3], twin[3, 3] = -twin[2, 0], twin[2, 3] + np.pi, twin[3, 3] + np.pi
    P0 = sampling.initial_covariance(ur.n_joints)  # noqa: N806
    plain = OnlineEstimator(ur, twin, P0)
    assert np.abs(true_state(plain, ur.dh, None)[0] - twin.ravel()).max() < 1e-12
    with_camera = OnlineEstimator(ur, twin, P0, EstimatorSettings(camera_prior='0.02 2', marker_prior='0.005 5'))
    x, errors = true_state(with_camera, ur.dh, (np.zeros(6), np.zeros(6)))
    assert np.abs(x - with_camera.x).max() < 1e-9                       # the estimate is the truth
    assert max(abs(v) for b in errors.values() for v in b[0]) < 1e-6


def test_another_noise_law_replaces_the_recorded_covariances(tmp_path: Path, capsys, monkeypatch) -> None:
    """``noise_law``: every observation takes the law's covariance at its hand pose, seen from the
    description's camera (the recorded 0.1 mm / 0.02 deg is replaced by a law 10x wider)."""
    from body_schema.noise import PoseDependentNoise
    from dh_estimator import evaluate as evaluate_module
    path, _ = _ur5e_bag(tmp_path / 'ur.mcap', True)
    values = {'robot': 'ur5e', 'camera_prior': '0.02 2', 'marker_prior': '0.005 5'}
    recorded = evaluate_bag(path, EvaluationSettings.from_parameters(values))
    law = {'a_pos': 0.0, 'b_pos': 0.0, 'floor_pos': 1e-6, 'a_rot': 0.0, 'b_rot': 0.0, 'floor_rot': 1e-5,
           'depth_ratio': 3.0}
    used = []
    real = PoseDependentNoise.hand_covariance

    def spy(self, camera, pose, markers):
        used.append(real(self, camera, pose, markers))
        return used[-1]

    monkeypatch.setattr(PoseDependentNoise, 'hand_covariance', spy)
    wide = evaluate_bag(path, replace(EvaluationSettings.from_parameters(values), noise_law=tuple(law.items())))
    monkeypatch.undo()
    assert len(used) == 18
    for cov in used:
        assert np.sort(np.linalg.eigvalsh(cov[:3, :3])) == pytest.approx([1e-6, 1e-6, 9e-6])
    # Ten times the recorded standard deviations and more: the information limit far wider.
    assert wide.rows[-1].expected_position_mm > 10.0 * recorded.rows[-1].expected_position_mm
    # The innovations past the warm-up (10 updates) are checked against the change test's bound.
    assert recorded.innovations.count == wide.innovations.count == 8
    assert recorded.innovations.bound == pytest.approx(27.86, abs=0.01)
    assert 'innovations after the warm-up: median NIS' in summary_text(wide)
    # The command line reads the block tools.fit_noise prints, and names a file without one.
    good, bad = tmp_path / 'law.yaml', tmp_path / 'bad.yaml'
    good.write_text('noise_model: {' + ', '.join(f'{k}: {v}' for k, v in law.items()) + ', covariance: sandwich}\n')
    bad.write_text('joints: []\n')
    assert evaluate_module.read_noise_law(good) == tuple((k, float(v)) for k, v in law.items())
    # Its estimator keys apply as if it were the description's, unless a parameter set them.
    scaled = tmp_path / 'scaled.yaml'
    scaled.write_text('noise_model: {' + ', '.join(f'{k}: {v}' for k, v in law.items()) + ', loss_scale: 1.5}\n')
    base = EvaluationSettings.from_parameters(values)
    apply, read = evaluate_module.with_noise_law, evaluate_module.read_noise_block
    assert apply(base, read(scaled)).estimator.loss_scale == 1.5
    assert apply(base, read(good)).estimator.covariance == 'sandwich'
    pinned = replace(base, estimator=replace(base.estimator, loss_scale=2.0, covariance='gauss_newton'))
    assert apply(pinned, read(scaled)).estimator.loss_scale == 2.0
    assert apply(pinned, read(good)).estimator.covariance == 'gauss_newton'
    assert evaluate_module.main([str(path), '--robot', 'ur5e', '--noise-law', str(bad), '--no-plots']) == 2
    assert f"{bad}: no 'noise_model:' mapping" in capsys.readouterr().err
    with pytest.raises(ValueError, match="re-applying a law needs a fixed camera; 'icub_right_arm' has none"):
        evaluate_bag(path, EvaluationSettings(noise_law=tuple(law.items())))
