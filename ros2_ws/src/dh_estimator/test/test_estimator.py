"""Pure estimator pieces: joint buffer, one update per configuration, checkpoint, export."""
import numpy as np
import pytest
import yaml

import body_schema
from body_schema import ekf, sampling
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


def test_one_update_per_configuration(arm):
    est = _estimator(arm)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    assert est.offer(q, z, R) is Outcome.ACCEPTED
    x = est.ekf.x.copy()
    assert est.offer(q + 1e-5, z, R) is Outcome.DUPLICATE          # same static configuration
    np.testing.assert_array_equal(est.ekf.x, x)
    assert est.counters == {'updates': 1, 'rejected': 0, 'duplicates': 1}
    assert est.offer(q + 0.1, arm.forward_kinematics(q + 0.1), R) is Outcome.ACCEPTED


def test_rejected_outlier_leaves_state(arm):
    est = _estimator(arm, gate_probability=0.99, gate_warmup=0, q_length=1e-6, q_angle=1e-6)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    z[:3, 3] += 1.0
    x, P = est.ekf.x.copy(), est.ekf.P.copy()
    assert est.offer(q, z, np.eye(6) * 1e-8) is Outcome.REJECTED
    np.testing.assert_array_equal(est.ekf.x, x)
    np.testing.assert_array_equal(est.ekf.P, P)                 # predict's Q undone too


def test_gate_waits_for_warmup(arm):
    est = _estimator(arm, gate_probability=0.99, gate_warmup=1)
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    z[:3, 3] += 0.5
    assert est.offer(q, z, np.eye(6) * 1e-6) is Outcome.ACCEPTED      # no gate yet
    q2 = q + 0.2
    z2 = arm.forward_kinematics(q2)
    z2[:3, 3] += 0.5
    assert est.offer(q2, z2, np.eye(6) * 1e-8) is Outcome.REJECTED


def test_nan_leaves_state(arm):
    est = _estimator(arm, q_length=1e-6)
    q = np.zeros(7)
    z = arm.forward_kinematics(q)
    z[1, 1] = np.nan
    P = est.ekf.P.copy()
    with pytest.raises(ekf.InvalidInputError):
        est.offer(q, z, R)
    np.testing.assert_array_equal(est.ekf.P, P)
    assert est.last_config is None


def test_checkpoint_resumes_exactly(arm, tmp_path):
    est = _estimator(arm)
    for q in sampling.uniform_configs(arm.calibration_box, 5, 1):
        est.offer(q, arm.forward_kinematics(q), R)
    path = tmp_path / 'state.npz'
    est.save_checkpoint(path)
    again = _estimator(arm)
    again.load_checkpoint(path)
    np.testing.assert_array_equal(again.ekf.x, est.ekf.x)
    np.testing.assert_array_equal(again.ekf.P, est.ekf.P)
    np.testing.assert_array_equal(again.last_config, est.last_config)
    assert again.counters == est.counters


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
