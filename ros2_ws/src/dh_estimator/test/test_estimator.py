"""Pure estimator pieces: joint buffer, one update per configuration, checkpoint, export."""
import numpy as np
import pytest
import yaml

import body_schema
from body_schema import ekf, sampling
from body_schema.urdf import link_pose
from calibration_interfaces.outcome import Outcome
from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
from dh_estimator.joint_buffer import JointStateBuffer, StampOutOfRange


@pytest.fixture(scope='module')
def arm():
    return body_schema.load_robot()


def _estimator(arm, **kw):
    return OnlineEstimator(arm, sampling.perturb_dh(arm.dh, 3), sampling.initial_covariance(7),
                           EstimatorSettings(**kw))


R = np.diag([1e-5] * 3 + [1e-3] * 3)


def test_buffer_interpolates_and_detects_rest():
    b = JointStateBuffer(2)
    for t in np.arange(0.0, 1.01, 0.02):
        b.add(t, [min(t, 0.5), 0.0])          # moves until 0.5 s, then holds
    np.testing.assert_allclose(b.at(0.25), [0.25, 0.0])
    np.testing.assert_allclose(b.at(0.251), [0.251, 0.0])
    assert b.is_static(0.9, 0.2, 1e-6)
    assert not b.is_static(0.55, 0.2, 1e-6)
    with pytest.raises(StampOutOfRange, match='1.500'):
        b.at(1.5)
    with pytest.raises(ValueError, match='finite'):
        b.add(2.0, [np.nan, 0.0])


@pytest.mark.parametrize('kind', ['map', 'ekf'])
def test_one_update_per_configuration(arm, kind):
    est = _estimator(arm, estimator=kind)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    assert est.offer(q, z, R) is Outcome.ACCEPTED
    x = est.x.copy()
    assert est.offer(q + 1e-5, z, R) is Outcome.DUPLICATE          # same static configuration
    np.testing.assert_array_equal(est.x, x)
    assert est.counters == {'updates': 1, 'rejected': 0, 'duplicates': 1, 'outliers': 0, 'changes': 0,
                            'twin_moves': 0, 'restarts': 0, 'resolved': 0, 'outlier_verdicts': 0,
                            'withdrawn_changes': 0}
    assert est.offer(q + 0.1, arm.forward_kinematics(q + 0.1), R) is Outcome.ACCEPTED


def test_map_flags_a_gross_outlier_but_keeps_going(arm):
    est = _estimator(arm)
    qs = sampling.uniform_configs(arm.calibration_box, 12, 4)
    for q in qs[:10]:
        assert est.offer(q, arm.forward_kinematics(q), R) is Outcome.ACCEPTED
    z = arm.forward_kinematics(qs[10])
    z[:3, 3] += 0.3                                                  # 30 cm off: a wrong detection
    assert est.offer(qs[10], z, R) is Outcome.OUTLIER
    assert est.counters['outliers'] == 1
    assert 'outlier' in est.describe_last()
    assert est.offer(qs[11], arm.forward_kinematics(qs[11]), R) is Outcome.ACCEPTED


def test_rejected_outlier_leaves_state(arm):
    est = _estimator(arm, estimator='ekf', gate_probability=0.99, gate_warmup=0, q_length=1e-6, q_angle=1e-6)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    z[:3, 3] += 1.0
    x, P = est.ekf.x.copy(), est.ekf.P.copy()
    assert est.offer(q, z, np.eye(6) * 1e-8) is Outcome.REJECTED
    np.testing.assert_array_equal(est.ekf.x, x)
    np.testing.assert_array_equal(est.ekf.P, P)                 # predict's Q undone too


def test_gate_waits_for_warmup(arm):
    est = _estimator(arm, estimator='ekf', gate_probability=0.99, gate_warmup=1)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    z[:3, 3] += 0.5
    assert est.offer(q, z, np.eye(6) * 1e-6) is Outcome.ACCEPTED      # no gate yet
    q2 = q + 0.2
    z2 = arm.forward_kinematics(q2)
    z2[:3, 3] += 0.5
    assert est.offer(q2, z2, np.eye(6) * 1e-8) is Outcome.REJECTED


def _bad_inputs(arm):
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    nan_pose = z.copy()
    nan_pose[1, 1] = np.nan
    beyond = q.copy()
    beyond[3] = arm.limits[3, 1] + 0.2
    indefinite = R.copy()
    indefinite[0, 0] = -1e-5
    return {
        'nan pose': (q, nan_pose, R, 'NaN'),
        'misshaped pose': (q, z[:3], R, '4x4'),
        'misshaped joints': (q[:5], z, R, 'shape'),
        'singular R': (q, z, np.zeros((6, 6)), 'R'),
        'indefinite R': (q, z, indefinite, 'R'),
        'joints outside the limits': (beyond, arm.forward_kinematics(beyond), R, 'outside its limits'),
    }


@pytest.mark.parametrize('case', ['nan pose', 'misshaped pose', 'misshaped joints', 'singular R',
                                  'indefinite R', 'joints outside the limits'])
def test_bad_input_is_a_clear_error_and_changes_nothing(arm, case):
    est = _estimator(arm, q_length=1e-6)
    q0 = sampling.uniform_configs(arm.calibration_box, 1, 9)[0]
    est.offer(q0, arm.forward_kinematics(q0), R)
    x, P, counters = est.x.copy(), est.P.copy(), est.counters
    q, z, cov, words = _bad_inputs(arm)[case]
    with pytest.raises(ekf.InvalidInputError, match=words):
        est.offer(q, z, cov)
    np.testing.assert_array_equal(est.x, x)
    np.testing.assert_array_equal(est.P, P)
    assert est.counters == counters
    np.testing.assert_array_equal(est.last_config, q0)
    assert est.map.n_observations == 1


def test_nan_leaves_ekf_state(arm):
    est = _estimator(arm, estimator='ekf', q_length=1e-6)
    q = np.zeros(7)
    z = arm.forward_kinematics(q)
    z[1, 1] = np.nan
    P = est.ekf.P.copy()
    with pytest.raises(ekf.InvalidInputError):
        est.offer(q, z, R)
    np.testing.assert_array_equal(est.ekf.P, P)
    assert est.last_config is None


@pytest.mark.parametrize('kind', ['map', 'ekf'])
def test_checkpoint_resumes_exactly(arm, tmp_path, kind):
    est = _estimator(arm, estimator=kind)
    qs = sampling.uniform_configs(arm.calibration_box, 7, 1)
    for q in qs[:5]:
        est.offer(q, arm.forward_kinematics(q), R)
    path = tmp_path / 'state.npz'
    est.save_checkpoint(path)
    again = _estimator(arm, estimator=kind)
    again.load_checkpoint(path)
    np.testing.assert_array_equal(again.x, est.x)
    np.testing.assert_array_equal(again.P, est.P)
    np.testing.assert_array_equal(again.last_config, est.last_config)
    assert again.counters == est.counters
    for q in qs[5:]:                 # and it goes on exactly as the uninterrupted one
        assert again.offer(q, arm.forward_kinematics(q), R) is est.offer(q, arm.forward_kinematics(q), R)
    np.testing.assert_array_equal(again.x, est.x)


def test_checkpoint_of_another_estimator_is_refused(arm, tmp_path):
    _estimator(arm, estimator='ekf').save_checkpoint(tmp_path / 'ekf.npz')
    with pytest.raises(ValueError, match="'ekf' estimator"):
        _estimator(arm).load_checkpoint(tmp_path / 'ekf.npz')


def test_export_yaml_and_urdf(arm, tmp_path):
    est = _estimator(arm)
    y, u = est.export(tmp_path)
    doc = yaml.safe_load(y.read_text())
    assert [j['name'] for j in doc['joints']] == list(arm.joint_names)
    np.testing.assert_allclose(doc['joints'][2]['dh'][:2], est.dh[2, :2])
    assert doc['joints'][2]['dh'][3] == pytest.approx(np.degrees(est.dh[2, 3]))
    assert doc['joints'][0]['sigma'][0] == pytest.approx(np.sqrt(est.P[0, 0]))
    text = u.read_text()
    assert text.startswith('<?xml') and 'r_wrist_yaw' in text


# --------------------------------------------------------------------------------------------
# Camera pose and marker offset estimated with the table (UR5e, a fixed camera)

def _ur_estimator(**kw):
    ur = body_schema.load_robot('ur5e')
    return ur, OnlineEstimator(ur, sampling.perturb_dh(ur.dh, 3), sampling.initial_covariance(6),
                               EstimatorSettings(**kw))


def test_without_priors_the_estimator_is_the_table_alone():
    ur, est = _ur_estimator()
    assert est.extrinsics is None and est.x.shape == (24,) and est.extrinsic_poses() is None
    np.testing.assert_array_equal(est.P, est.P_dh)


def test_camera_and_marker_priors_add_their_states_and_hold_what_they_absorb():
    ur, est = _ur_estimator(camera_prior='0.02 2', marker_prior='0.005 5')
    assert est.x.shape == (36,) and est.P_dh.shape == (24, 24)
    np.testing.assert_allclose(np.sqrt(np.diag(est.P))[24:], [0.02] * 3 + [np.radians(2)] * 3
                               + [0.005] * 3 + [np.radians(5)] * 3)
    # pan d and offset, the whole wrist-3 row: at the description's values (they define the frames).
    for i in (1, 3, 20, 21, 22, 23):
        assert est.x[i] == ur.dh.ravel()[i]
    assert est.identifiability.rank == 28
    cam, marker = est.extrinsic_poses()
    np.testing.assert_allclose(cam, ur.camera_pose('left'))


@pytest.mark.parametrize('parallel_std, expected', [(-1.0, None), (0.0, 1e-6), (0.003, 0.003)])
def test_parallel_axis_combinations_are_held_by_the_guess_uncertainty_and_the_absorbed_ones_pinned(
        tmp_path, parallel_std, expected):
    ur, est = _ur_estimator(camera_prior='0.02 2', marker_prior='0.005 5', parallel_std=parallel_std)
    exact, parallel = est.identifiability.held_groups()
    std = est.map.fixed_std
    np.testing.assert_allclose(std[:6], 1e-6)                          # what camera and marker absorb
    p24 = parallel[:24]                                                # DH components only
    spread = np.sqrt(np.diag(p24.T @ sampling.initial_covariance(6) @ p24))
    np.testing.assert_allclose(std[6:], spread if expected is None else expected)
    if expected is None:
        assert np.all(std[6:] > 0.005)                                 # the paper-wide guess: centimetres
    held = yaml.safe_load(est.export(tmp_path)[0].read_text())['identifiability']['held']
    assert 'the 2 only parallel axes hide with standard deviation' in held


def test_export_writes_the_camera_pose_with_sigma_and_a_static_transform(tmp_path):
    ur, est = _ur_estimator(camera_prior='0.02 2', marker_prior='0.005 5')
    est.map.x[24:30] = [0.01, -0.02, 0.005, 0.0, 0.0, np.radians(1.0)]
    y, _ = est.export(tmp_path)
    doc = yaml.safe_load(y.read_text())
    np.testing.assert_allclose(doc['camera']['correction_mm_deg'], [10, -20, 5, 0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(doc['camera']['sigma_mm_deg'], [20, 20, 20, 2, 2, 2])
    np.testing.assert_allclose(doc['camera']['xyz'], ur.camera_pose('left')[:3, 3] + [0.01, -0.02, 0.005])
    assert doc['marker']['sigma_mm_deg'] == pytest.approx([5.0] * 6)
    assert any('camera' in u['direction'] for u in doc['identifiability']['unidentifiable'])
    tf = yaml.safe_load((tmp_path / 'calibrated_camera_static_transform.yaml').read_text())
    assert tf['frame_id'] == 'base' and tf['child_frame_id'] == 'left_camera_optical_frame'
    assert [tf['x'], tf['y'], tf['z']] == pytest.approx(doc['camera']['xyz'])


def test_calibrated_urdf_carries_the_estimated_camera_and_marker_frames(tmp_path):
    ur, est = _ur_estimator(camera_prior='0.02 2', marker_prior='0.005 5')
    est.map.x[24:36] = [0.01, -0.02, 0.005, 0.0, 0.0, np.radians(1.0), 0.002, 0.0, -0.003, np.radians(2.0), 0, 0]
    _, u = est.export(tmp_path)
    text = u.read_text()
    cam, marker = est.extrinsic_poses()
    assert not np.allclose(cam, ur.camera_pose('left'), atol=1e-3)     # the estimate, not the description
    np.testing.assert_allclose(link_pose(text, 'left_camera_optical_frame'), cam, atol=1e-9)
    q = sampling.uniform_configs(ur.calibration_box, 1, 3)[0]
    flange = est.calibrated_model().forward_kinematics(q)
    np.testing.assert_allclose(link_pose(text, 'marker_flange', dict(zip(ur.joint_names, q))), flange @ marker,
                               atol=1e-9)


def test_calibrated_urdf_without_extrinsics_has_the_description_frames(arm, tmp_path):
    ur, est = _ur_estimator()
    _, u = est.export(tmp_path)
    np.testing.assert_allclose(link_pose(u.read_text(), 'left_camera_optical_frame'), ur.camera_pose('left'),
                               atol=1e-9)
    # The iCub's eyes ride its head: not in the arm's URDF; its hand markers are.
    icub = _estimator(arm)
    _, u = icub.export(tmp_path)
    text = u.read_text()
    assert 'camera_optical_frame' not in text and len(arm.markers) > 1
    q = sampling.uniform_configs(arm.calibration_box, 1, 4)[0]
    hand = icub.calibrated_model().forward_kinematics(q)
    for m in arm.markers:
        np.testing.assert_allclose(link_pose(text, f'marker_{m.name}', dict(zip(arm.joint_names, q))),
                                   hand @ m.hand_T_marker, atol=1e-9)


@pytest.mark.parametrize('kw, words', [({'camera_prior': '0.02'}, "camera_prior.*'0.02'"),
                                       ({'marker_prior': '0.005 5', 'estimator': 'ekf'}, 'need estimator map')])
def test_extrinsic_priors_name_the_bad_value(kw, words):
    with pytest.raises(ValueError, match=words):
        EstimatorSettings(**kw)


# --------------------------------------------------------------------------------------------
# Descriptions from a URDF and in Craig's modified convention (Panda)

def test_export_of_a_modified_description_writes_the_estimate_back_as_a_modified_table(tmp_path):
    from body_schema.modified_dh import modified_forward_kinematics
    from calibration_interfaces.dh_file import parse_dh, read_dh_file

    panda = body_schema.load_robot('panda_mdh')
    est = OnlineEstimator(panda, sampling.perturb_dh(panda.dh, 3), sampling.initial_covariance(7), EstimatorSettings())
    y, _ = est.export(tmp_path)
    doc = yaml.safe_load(y.read_text())
    section = doc['modified_dh']
    rows = np.array([j['dh'] for j in section['joints']])
    rows[:, 2:] = np.radians(rows[:, 2:])
    flange = np.array(section['flange'])
    flange[2:] = np.radians(flange[2:])
    q = np.random.default_rng(0).uniform(panda.limits[:, 0], panda.limits[:, 1], (20, 7))
    # the written modified table moves the flange as the estimate does
    np.testing.assert_allclose([panda.base @ modified_forward_kinematics(rows, qq, flange) for qq in q],
                               panda.with_dh(est.dh).flange_pose(q), atol=1e-9)
    # and it reads back as the estimate's standard table; the main table is the standard one
    np.testing.assert_allclose(parse_dh(section).dh, est.dh, atol=1e-12)
    np.testing.assert_allclose(read_dh_file(y, 7).dh, est.dh, atol=1e-9)
    assert section['joints'][1]['sigma'][0] == pytest.approx(np.sqrt(est.P[0, 0]))     # a_0 of standard row 0


def test_export_of_a_urdf_description_writes_its_urdf_corrected(tmp_path):
    from body_schema.urdf_model import urdf_chain
    from calibration_interfaces.dh_file import read_dh_file

    panda = body_schema.load_robot('panda')
    est = OnlineEstimator(panda, sampling.perturb_dh(panda.dh, 3), sampling.initial_covariance(7), EstimatorSettings())
    est.export(tmp_path)
    chain = urdf_chain(tmp_path / 'calibrated_panda.urdf', 'panda_link0', 'panda_link8')
    q = np.random.default_rng(0).uniform(panda.limits[:, 0], panda.limits[:, 1], (20, 7))
    np.testing.assert_allclose([chain.tip_pose(qq) for qq in q], panda.with_dh(est.dh).flange_pose(q), atol=1e-9)
    # a URDF description is a DH file too (the simulator's true_dh_file, the estimator's initial guess)
    np.testing.assert_allclose(read_dh_file(body_schema.robot.robot_path('panda'), 7).dh, panda.dh)
    assert 'modified_dh' not in yaml.safe_load((tmp_path / 'calibrated_dh.yaml').read_text())



def test_innovations_follow_chi_square_when_the_noise_law_is_right_and_not_when_it_is_too_sure(arm):
    from body_schema.noise import innovation_check, sample_pose

    rng = np.random.default_rng(5)
    qs = sampling.uniform_configs(arm.calibration_box, 80, 6)
    zs = [sample_pose(arm.forward_kinematics(q), R, rng) for q in qs]
    checks = {}
    for name, stated in (('right', R), ('too sure', R / 25)):
        # The estimator's own defaults, not the loss and covariance the iCub's description tunes.
        est = _estimator(arm, loss_scale=3.0, covariance='sandwich')
        for q, z in zip(qs, zs):
            est.offer(q, z, stated)
        assert len(est.innovations) == est.counters['updates'] == len(qs)
        checks[name] = innovation_check(est.innovations, skip=20)
    right, sure = checks['right'], checks['too sure']
    assert right.count == 60 and 3.5 < right.median < 7.5 and right.beyond <= 1      # chi-square, 6 dof
    assert sure.median > 25 * 3.5 and sure.beyond > 30


def test_the_ekf_records_the_innovation_of_every_update_gated_or_not(arm):
    est = _estimator(arm, estimator='ekf', gate_probability=0.99, gate_warmup=0)
    q = np.mean(arm.calibration_box, axis=1)
    est.offer(q, arm.forward_kinematics(q), R)
    z = arm.forward_kinematics(q + 0.1)
    z[:3, 3] += 1.0
    assert est.offer(q + 0.1, z, R) is Outcome.REJECTED
    assert len(est.innovations) == 2 and est.innovations[1] == pytest.approx(est.mahalanobis ** 2)
    assert est.innovations[1] > 1e3
