"""The DH-parameter EKF: convergence, noise robustness, Joseph form, gating and bad input."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import body_schema
from body_schema import ekf, metrics, sampling


@pytest.fixture(scope='module')
def arm():
    return body_schema.load_robot()


@pytest.fixture(scope='module')
def evaluator(arm):
    return metrics.PoseErrorEvaluator(arm.base, arm.dh, arm.calibration_box, n=300)


def _run(arm, seed, n_obs, sigma_p, sigma_o, r_p, r_o, q_var, iterations):
    rng = np.random.default_rng(seed)
    x0 = sampling.perturb_dh(arm.dh, rng)
    f = ekf.ExtendedKalmanFilter(x0.ravel(), sampling.initial_covariance(7), Q=q_var * np.eye(28))
    model = ekf.HandPoseModel(arm.base, 7)
    R = np.diag([r_p ** 2] * 3 + [r_o ** 2] * 3)
    for q in sampling.uniform_configs(arm.calibration_box, n_obs, rng):
        z = arm.forward_kinematics(q)
        if sigma_p:
            z[:3, 3] += rng.normal(0, sigma_p, 3)
            z[:3, :3] = Rotation.from_rotvec(rng.normal(0, sigma_o, 3)).as_matrix() @ z[:3, :3]
        f.predict()
        assert model.update(f, q, z, R, iterations=iterations)
    return x0, f


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_noiseless_observations_reach_sub_millimetre(arm, evaluator, seed):
    x0, f = _run(arm, seed, 50, 0.0, 0.0, 1e-4, np.radians(0.05), 1e-7, iterations=5)
    assert evaluator(x0).position_mm > 50          # the paper's spread: a real starting error
    assert evaluator(f.x).position_mm < 1.0
    assert f.n_updates == 50


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_noisy_observations_shrink_error_fivefold(arm, evaluator, seed):
    sp, so = 0.005, np.radians(2.0)
    x0, f = _run(arm, seed, 50, sp, so, sp, so, 0.0, iterations=1)   # the paper's plain EKF
    e0, e = evaluator(x0), evaluator(f.x)
    assert e.position_m < e0.position_m / 5
    assert e.orientation_deg < e0.orientation_deg / 5


def test_nis_is_consistent_near_truth(arm):
    """Started at the truth with honest R, the mean NIS is close to dim z = 6."""
    rng = np.random.default_rng(5)
    sp, so = 0.004, np.radians(1.5)
    f = ekf.ExtendedKalmanFilter(arm.dh.ravel(), sampling.initial_covariance(7, 0.004, np.radians(0.5)))
    model = ekf.HandPoseModel(arm.base, 7)
    R = np.diag([sp ** 2] * 3 + [so ** 2] * 3)
    nis = []
    for q in sampling.uniform_configs(arm.calibration_box, 200, rng):
        z = arm.forward_kinematics(q)
        z[:3, 3] += rng.normal(0, sp, 3)
        z[:3, :3] = Rotation.from_rotvec(rng.normal(0, so, 3)).as_matrix() @ z[:3, :3]
        model.update(f, q, z, R)
        nis.append(f.nis)
    assert 4.8 < np.mean(nis) < 7.2
    assert ekf.nees(arm.dh.ravel(), f.x, f.P) < 28 + 4 * np.sqrt(2 * 28)


def test_joseph_update_keeps_p_symmetric_positive_definite(arm):
    f = ekf.ExtendedKalmanFilter(arm.dh.ravel(), sampling.initial_covariance(7))
    model = ekf.HandPoseModel(arm.base, 7)
    tr0 = np.trace(f.P)
    for q in sampling.uniform_configs(arm.calibration_box, 30, 1):
        model.update(f, q, arm.forward_kinematics(q), 1e-12 * np.eye(6))   # near-singular R
        assert np.array_equal(f.P, f.P.T)
        assert np.linalg.eigvalsh(f.P)[0] > 0
    assert np.trace(f.P) < tr0


def test_predict_adds_q(arm):
    f = ekf.ExtendedKalmanFilter(arm.dh.ravel(), np.eye(28), Q=0.5 * np.eye(28))
    f.predict()
    np.testing.assert_allclose(np.diag(f.P), 1.5)
    np.testing.assert_array_equal(f.x, arm.dh.ravel())


def test_gate_rejects_outlier_and_leaves_state(arm):
    model = ekf.HandPoseModel(arm.base, 7)
    f = ekf.ExtendedKalmanFilter(arm.dh.ravel(), sampling.initial_covariance(7, 0.002, 0.01),
                                 gate=ekf.chi2_gate(6, 0.999))
    q = np.mean(arm.calibration_box, axis=1)
    z = arm.forward_kinematics(q)
    z[:3, 3] += [0.3, 0.0, 0.0]                                  # a 30 cm outlier
    x, P = f.x.copy(), f.P.copy()
    assert not model.update(f, q, z, np.diag([1e-4] * 3 + [1e-3] * 3))
    assert f.n_rejected == 1 and f.n_updates == 0 and f.mahalanobis > f.gate
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)
    assert f.y.shape == (6,) and f.S.shape == (6, 6)


@pytest.mark.parametrize('bad', ['pose', 'q', 'R'])
def test_nan_inputs_raise_and_leave_state(arm, bad):
    model = ekf.HandPoseModel(arm.base, 7)
    f = ekf.ExtendedKalmanFilter(arm.dh.ravel(), sampling.initial_covariance(7))
    q = np.zeros(7)
    z = arm.forward_kinematics(q)
    R = 1e-4 * np.eye(6)
    if bad == 'pose':
        z[0, 3] = np.nan
    elif bad == 'q':
        q = q.copy(); q[3] = np.nan
    else:
        R = R.copy(); R[2, 2] = np.nan
    x, P = f.x.copy(), f.P.copy()
    with pytest.raises(ekf.InvalidInputError, match='NaN'):
        model.update(f, q, z, R)
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)


def test_constructor_validates():
    with pytest.raises(ekf.InvalidInputError, match='positive definite'):
        ekf.ExtendedKalmanFilter(np.zeros(2), np.diag([1.0, -1.0]))
    with pytest.raises(ekf.InvalidInputError, match=r'shape \(2, 2\)'):
        ekf.ExtendedKalmanFilter(np.zeros(2), np.eye(3))
    with pytest.raises(ekf.InvalidInputError, match='NaN'):
        ekf.ExtendedKalmanFilter([0.0, np.nan], np.eye(2))
