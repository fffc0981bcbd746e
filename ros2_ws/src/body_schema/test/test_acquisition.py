"""Acquisition: the closed-form A-optimality cost and the four strategies' guarantees."""
import numpy as np
import pytest

import body_schema
from body_schema import ekf, sampling
from body_schema.acquisition import (AcquisitionCost, JointSelector, SelectorConfig, Strategy,
                                     expected_trace)
from body_schema.noise import PoseDependentNoise
from body_schema.occlusion import OcclusionModel


@pytest.fixture(scope='module')
def arm():
    return body_schema.load_robot()


@pytest.fixture(scope='module')
def cost(arm):
    dh = sampling.perturb_dh(arm.dh, 4)
    return AcquisitionCost(arm.base, dh, sampling.initial_covariance(7), PoseDependentNoise(),
                           arm.camera_pose('left'), arm.markers,
                           occlusion=OcclusionModel(arm.calibration_box), penalty_a=0.01, penalty_b=10.0)


def test_expected_trace_equals_trace_after_a_real_update(arm):
    dh = sampling.perturb_dh(arm.dh, 9)
    P = sampling.initial_covariance(7)
    q = np.mean(arm.calibration_box, axis=1)
    H = arm.with_dh(dh).jacobian_dh(q)
    R = np.diag([1e-5] * 3 + [1e-3] * 3)
    f = ekf.ExtendedKalmanFilter(dh.ravel(), P)
    ekf.HandPoseModel(arm.base, 7).update(f, q, arm.forward_kinematics(q), R)
    assert expected_trace(P, H, R) == pytest.approx(np.trace(f.P), rel=1e-9)
    assert expected_trace(P, H, R) < np.trace(P)


def test_cost_combines_terms_as_the_paper(arm, cost):
    q = np.mean(arm.calibration_box, axis=1)
    c0, eta, px = cost.terms(q)
    assert eta == pytest.approx(0.5)                      # Be(1, 1) prior, no data
    assert cost(q) == pytest.approx(c0 / eta + 0.01 * np.arctan(10.0 * px))
    expected = AcquisitionCost(cost.base, cost.dh, cost.P, cost.noise, cost.camera_pose,
                               cost.markers, cost.occlusion, occlusion_mode='expected')
    tr = np.trace(cost.P)
    assert expected(q) == pytest.approx(tr - eta * (tr - c0))


def test_occlusion_failures_raise_the_cost(arm):
    occ = OcclusionModel(arm.calibration_box)
    c = AcquisitionCost(arm.base, arm.dh, sampling.initial_covariance(7), PoseDependentNoise(),
                        arm.camera_pose('left'), arm.markers, occlusion=occ)
    q = np.mean(arm.calibration_box, axis=1)
    before = c(q)
    for _ in range(3):
        occ.add(q, False)
    assert c(q) > 1.5 * before


def _inside(theta, bounds):
    return np.all(theta >= bounds[:, 0] - 1e-12) and np.all(theta <= bounds[:, 1] + 1e-12)


@pytest.mark.parametrize('strategy', list(Strategy))
def test_every_strategy_stays_in_the_box_and_limits(arm, cost, strategy):
    sel = JointSelector(arm.calibration_box, SelectorConfig(strategy=strategy, max_evals=300, seed=1))
    prev = np.mean(arm.calibration_box, axis=1)
    for _ in range(3):
        s = sel.select(cost, prev)
        assert s.theta.shape == (7,)
        assert _inside(s.theta, arm.calibration_box) and arm.within_limits(s.theta)
        prev = s.theta


def test_al_finds_lower_cost_than_random_points(arm, cost):
    sel = JointSelector(arm.calibration_box, SelectorConfig(strategy='al', max_evals=600))
    s = sel.select(cost)
    assert s.evaluations <= 600 + 50
    rand = sampling.uniform_configs(arm.calibration_box, 200, 0)
    assert s.cost <= np.percentile([cost(t) for t in rand], 5)


def test_ccsal_stays_in_its_delta_box(arm, cost):
    delta = 0.1
    sel = JointSelector(arm.calibration_box, SelectorConfig(strategy='ccsal', delta=delta, max_evals=300))
    prev = sampling.uniform_configs(arm.calibration_box, 1, 3)[0]
    s = sel.select(cost, prev)
    span = arm.calibration_box[:, 1] - arm.calibration_box[:, 0]
    assert np.all(np.abs(s.theta - prev) <= delta * span + 1e-12)
    assert _inside(s.theta, arm.calibration_box)


def test_ucsal_with_huge_gamma_stays_next_to_previous(arm, cost):
    prev = sampling.uniform_configs(arm.calibration_box, 1, 5)[0]
    far = JointSelector(arm.calibration_box, SelectorConfig(strategy='ucsal', gamma=0.0, max_evals=600))
    near = JointSelector(arm.calibration_box, SelectorConfig(strategy='ucsal', gamma=1e6, max_evals=600))
    d_far = far.distance(far.select(cost, prev).theta, prev)
    d_near = near.distance(near.select(cost, prev).theta, prev)
    assert d_near < 0.05                                   # normalised L1 over 7 joints
    assert d_far > 10 * d_near


def test_selection_is_deterministic(arm, cost):
    cfg = SelectorConfig(strategy='al', max_evals=200)
    a = JointSelector(arm.calibration_box, cfg).select(cost)
    b = JointSelector(arm.calibration_box, cfg).select(cost)
    np.testing.assert_array_equal(a.theta, b.theta)
    r1 = JointSelector(arm.calibration_box, SelectorConfig(strategy='random', seed=3)).select(None)
    r2 = JointSelector(arm.calibration_box, SelectorConfig(strategy='random', seed=3)).select(None)
    np.testing.assert_array_equal(r1.theta, r2.theta)


def test_bad_configuration_raises(arm, cost):
    with pytest.raises(ValueError, match='unknown strategy'):
        SelectorConfig(strategy='greedy')
    with pytest.raises(ValueError, match='delta'):
        SelectorConfig(delta=0.0)
    with pytest.raises(ValueError, match='algorithm'):
        SelectorConfig(algorithm='CMAES')
    with pytest.raises(ValueError, match='previous configuration'):
        JointSelector(arm.calibration_box, SelectorConfig(strategy='ucsal')).select(cost, None)
    with pytest.raises(ValueError, match='NaN'):
        AcquisitionCost(arm.base, np.full((7, 4), np.nan), np.eye(28), PoseDependentNoise(),
                        np.eye(4), arm.markers)
