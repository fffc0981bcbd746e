"""Acquisition: the closed-form A-optimality cost and the four strategies' guarantees."""
from dataclasses import replace

import numpy as np
import pytest

import body_schema
from body_schema import ekf, sampling
from body_schema.acquisition import (AcquisitionCost, JointSelector, SelectorConfig, Strategy,
                                     expected_trace)
from body_schema.noise import PoseDependentNoise, stereo_covariance
from body_schema.occlusion import OcclusionModel, VisibilityPrior


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


# --- information gain, v-optimality, batched evaluation, batch optimiser, no repeats (issue 14) ---

from scipy.stats import qmc  # noqa: E402

from body_schema import kinematics  # noqa: E402
from body_schema.acquisition import (CRITERIA, DETECTOR_NOISE_SCALES, OCCLUSION_MODES,  # noqa: E402
                                     box_pose_weight, information_gain)
from body_schema.extrinsics import Extrinsics  # noqa: E402
import scipy.linalg  # noqa: E402


@pytest.fixture(scope='module')
def box_configs(arm):
    box = arm.calibration_box
    return box[:, 0] + (box[:, 1] - box[:, 0]) * qmc.Sobol(7, rng=0).random_base2(5)


@pytest.fixture(scope='module')
def learned_occlusion(arm):
    occ = OcclusionModel(arm.calibration_box, 0.5, 1.0, 2.0)
    rng = np.random.default_rng(11)
    for t in sampling.uniform_configs(arm.calibration_box, 20, rng):
        occ.add(t, bool(rng.random() < 0.6))
    return occ


def _cost(arm, box_configs, occlusion, mode='paper', criterion='a_optimal', P=None, seed=4):
    dh = sampling.perturb_dh(arm.dh, seed)
    return AcquisitionCost(arm.base, dh, sampling.initial_covariance(7) if P is None else P, PoseDependentNoise(),
                           arm.camera_pose('left'), arm.markers, occlusion=occlusion, penalty_a=0.05,
                           penalty_b=10.0, occlusion_mode=mode, criterion=criterion, box_configs=box_configs)


def _posterior_covariance(arm, cost, q):
    """Brute force: one real EKF update at q with the noise the cost predicts there."""
    R = cost.noise.hand_covariance(cost.camera_pose, kinematics.forward_kinematics(arm.base, cost.dh, q),
                                   arm.markers)
    f = ekf.ExtendedKalmanFilter(cost.dh.ravel(), cost.P)
    ekf.HandPoseModel(arm.base, 7).update(f, q, kinematics.forward_kinematics(arm.base, cost.dh, q), R)
    return f.P


@pytest.mark.parametrize('criterion', CRITERIA)
@pytest.mark.parametrize('mode', OCCLUSION_MODES)
def test_batched_evaluation_equals_single(arm, box_configs, learned_occlusion, criterion, mode):
    cost = _cost(arm, box_configs, learned_occlusion, mode, criterion)
    qs = sampling.uniform_configs(arm.calibration_box, 64, 5)
    batch = cost.evaluate(qs)
    single = np.array([cost(q) for q in qs])
    np.testing.assert_allclose(batch, single, rtol=1e-12, atol=1e-15)
    assert np.ptp(batch) > 0                               # not a constant function
    gain, eta, px = cost.terms_batch(qs)
    np.testing.assert_allclose(eta, learned_occlusion.mean(qs), rtol=1e-12)
    np.testing.assert_allclose(px, kinematics.forward_kinematics(arm.base, cost.dh, qs)[:, 0, 3], rtol=1e-12)


def test_visibility_prior_enters_eta_in_batch_and_single_evaluation(arm, box_configs, learned_occlusion):
    flat = _cost(arm, box_configs, learned_occlusion, 'gain', 'v_optimal')
    geo = replace(flat, visibility=VisibilityPrior(arm.camera))
    qs = sampling.uniform_configs(arm.calibration_box, 64, 5)
    np.testing.assert_allclose(geo.evaluate(qs), [geo(q) for q in qs], rtol=1e-12, atol=1e-15)
    gain, eta, _ = geo.terms_batch(qs)
    np.testing.assert_allclose(gain, flat.terms_batch(qs)[0], rtol=1e-12)
    # eta's prior mean is the geometric prediction, blurred by the predicted hand-pose covariance.
    frames = kinematics.chain_frames(arm.base, geo.dh, qs)
    H = kinematics.pose_jacobian_from_frames(frames)
    var = np.diagonal(H @ geo.P @ np.swapaxes(H, -1, -2), axis1=-2, axis2=-1)
    markers = np.stack([m.hand_T_marker for m in arm.markers])
    p = geo.visibility.probability(geo.camera_pose, frames[:, -1, None] @ markers,
                                   np.sqrt(var[:, :3].mean(-1)), np.degrees(np.sqrt(var[:, 3:].mean(-1))))
    np.testing.assert_allclose(eta, learned_occlusion.mean(qs, p), rtol=1e-12)
    assert np.ptp(p) > 0.1                                 # the geometry tells configurations apart
    # Weight 0: the flat prior again; a bad weight is refused.
    np.testing.assert_allclose(replace(geo, visibility_weight=0.0).terms_batch(qs)[1], learned_occlusion.mean(qs),
                               rtol=1e-12)
    with pytest.raises(ValueError, match='visibility_weight.*1.5'):
        replace(geo, visibility_weight=1.5)
    # Without a learned model the prior alone is eta.
    np.testing.assert_allclose(replace(geo, occlusion=None).terms_batch(qs)[1], p, rtol=1e-12)


def test_a_optimal_gain_is_the_trace_reduction_of_a_real_update(arm, box_configs):
    P = np.diag(np.random.default_rng(2).uniform(0.2, 1.5, 28)) @ sampling.initial_covariance(7)
    cost = _cost(arm, box_configs, None, 'gain', 'a_optimal', P=P)
    for q in sampling.uniform_configs(arm.calibration_box, 4, 6):
        c0, eta, _ = cost.terms(q)
        gain = cost.terms_batch(q[None])[0][0]
        assert eta == 1.0
        assert gain == pytest.approx(np.trace(P) - c0, rel=1e-12)
        assert c0 == pytest.approx(np.trace(_posterior_covariance(arm, cost, q)), rel=1e-9)
        H = kinematics.pose_jacobian_dh(arm.base, cost.dh, q)
        R = cost.noise.hand_covariance(cost.camera_pose, kinematics.forward_kinematics(arm.base, cost.dh, q),
                                       arm.markers)
        assert expected_trace(P, H, R) == pytest.approx(c0, rel=1e-12)


def test_v_optimal_gain_against_brute_force_posterior_pose_variance(arm, box_configs):
    cost = _cost(arm, box_configs, None, 'gain', 'v_optimal', seed=8)
    s_pos, s_rot = DETECTOR_NOISE_SCALES
    W = np.diag([s_pos ** -2] * 3 + [s_rot ** -2] * 3)
    jac = kinematics.pose_jacobian_dh(arm.base, cost.dh, box_configs)            # (M, 6, 28)

    def box_variance(P):                                                        # mean_i tr(W J_i P J_i^T)
        return np.mean([np.trace(W @ J @ P @ J.T) for J in jac])

    assert cost.uncertainty == pytest.approx(box_variance(cost.P), rel=1e-10)
    for q in sampling.uniform_configs(arm.calibration_box, 4, 7):
        gain = cost.terms_batch(q[None])[0][0]
        assert gain == pytest.approx(box_variance(cost.P) - box_variance(_posterior_covariance(arm, cost, q)),
                                     rel=1e-7)
    # v-optimality ranks configurations differently from the plain trace
    qs = sampling.uniform_configs(arm.calibration_box, 200, 9)
    g_v = cost.terms_batch(qs)[0]
    g_a = _cost(arm, box_configs, None, 'gain', 'a_optimal', seed=8).terms_batch(qs)[0]
    assert np.argmax(g_v) != np.argmax(g_a) or np.corrcoef(g_v, g_a)[0, 1] < 0.999


def test_information_gain_with_identity_weight_is_a_optimal():
    rng = np.random.default_rng(3)
    hp = rng.normal(size=(5, 6, 10))
    a = rng.normal(size=(5, 6, 6))
    s = a @ np.swapaxes(a, -1, -2) + np.eye(6)
    np.testing.assert_allclose(information_gain(hp, s, np.eye(10)), information_gain(hp, s), rtol=1e-12)
    ref = [np.trace(np.linalg.inv(s[i]) @ hp[i] @ hp[i].T) for i in range(5)]
    np.testing.assert_allclose(information_gain(hp, s), ref, rtol=1e-10)


def test_gain_mode_discounts_the_gain_by_eta(arm, box_configs, learned_occlusion):
    cost = _cost(arm, box_configs, learned_occlusion, 'gain')
    qs = sampling.uniform_configs(arm.calibration_box, 16, 12)
    gain, eta, px = cost.terms_batch(qs)
    np.testing.assert_allclose(cost.evaluate(qs), -eta * gain / np.trace(cost.P) + 0.05 * np.arctan(10.0 * px),
                               rtol=1e-12)
    paper = _cost(arm, box_configs, learned_occlusion, 'paper')
    np.testing.assert_allclose(paper.evaluate(qs), (np.trace(cost.P) - gain) / eta + 0.05 * np.arctan(10.0 * px),
                               rtol=1e-12)


def test_box_pose_weight_rejects_bad_inputs(arm):
    with pytest.raises(ValueError, match='noise_scales'):
        box_pose_weight(arm.base, arm.dh, np.zeros((2, 7)), (0.0, 0.01))
    with pytest.raises(ValueError, match=r'box_configs must have shape \(M, L\)'):
        box_pose_weight(arm.base, arm.dh, np.zeros((0, 7)))


@pytest.mark.parametrize('optimizer', ['direct', 'batch'])
def test_no_configuration_is_selected_twice(arm, box_configs, learned_occlusion, optimizer):
    cost = _cost(arm, box_configs, learned_occlusion, 'gain')
    cfg = SelectorConfig(strategy='al', optimizer=optimizer, max_evals=300, n_candidates=256, seed=2)
    first = JointSelector(arm.calibration_box, cfg).select(cost)
    again = JointSelector(arm.calibration_box, cfg).select(cost, None, first.theta[None])
    assert np.max(np.abs(again.theta - first.theta)) > cfg.repeat_tolerance
    # The objective itself: inf within the tolerance of a visited configuration, finite outside.
    sel = JointSelector(arm.calibration_box, cfg)
    tree = sel.visited_tree(first.theta[None])
    step = np.zeros(7)
    step[3] = 0.9 * cfg.repeat_tolerance
    near_far = np.stack([first.theta + step, first.theta + 1.2 * step / 0.9 * 2])
    v = sel.objective(cost, near_far, None, tree)
    assert np.isinf(v[0]) and np.isfinite(v[1])
    many = np.repeat(near_far, 10, axis=0)                  # the tree query path (N > 8) agrees
    np.testing.assert_array_equal(sel.is_repeat(many, tree), np.repeat([True, False], 10))


def test_every_candidate_a_repeat_raises(arm, box_configs):
    cost = _cost(arm, box_configs, None, 'gain')
    sel = JointSelector(arm.calibration_box, SelectorConfig(optimizer='batch', n_candidates=64,
                                                            repeat_tolerance=10.0))
    with pytest.raises(RuntimeError, match='repeat a visited one'):
        sel.select(cost, None, np.mean(arm.calibration_box, axis=1)[None])


@pytest.mark.parametrize('strategy', ['al', 'ucsal', 'ccsal'])
def test_batch_optimizer_record_bounds_and_quality(arm, box_configs, learned_occlusion, strategy):
    cost = _cost(arm, box_configs, learned_occlusion, 'gain', 'v_optimal')
    cfg = SelectorConfig(strategy=strategy, optimizer='batch', n_candidates=512, refine_starts=2,
                         refine_evals=20, seed=3)
    prev = sampling.uniform_configs(arm.calibration_box, 1, 4)[0]
    sel = JointSelector(arm.calibration_box, cfg)
    s = sel.select(cost, prev)
    assert s.optimizer == 'batch:BOBYQA'
    # candidates; 2 local starts of 1 + 20 and 1 of 1 + 10 evaluations; 2 snapping rounds of <= 7 steps x 21
    assert 512 < s.evaluations <= 512 + 2 * 21 + 11 + 2 * 7 * 21
    assert _inside(s.theta, s.bounds)
    cand = sampling.uniform_configs(s.bounds, 500, 21)
    assert s.cost <= np.min(sel.objective(cost, cand, prev))     # beats 500 uniform draws
    assert s.cost == pytest.approx(float(sel.objective(cost, s.theta[None], prev)[0]), rel=1e-12)
    again = JointSelector(arm.calibration_box, cfg).select(cost, prev)
    np.testing.assert_array_equal(s.theta, again.theta)         # seeded: reproducible
    d = JointSelector(arm.calibration_box, SelectorConfig(strategy=strategy, optimizer='direct',
                                                          max_evals=100)).select(cost, prev)
    assert d.optimizer == 'direct:DIRECT_L' and d.evaluations >= 100


def test_new_settings_reject_bad_values(arm, box_configs):
    with pytest.raises(ValueError, match="unknown optimizer 'cmaes'"):
        SelectorConfig(optimizer='cmaes')
    with pytest.raises(ValueError, match='n_candidates must be a power of two >= 16.*1000'):
        SelectorConfig(n_candidates=1000)
    with pytest.raises(ValueError, match="unknown local_algorithm 'LBFGS'"):
        SelectorConfig(local_algorithm='LBFGS')
    with pytest.raises(ValueError, match='repeat_tolerance.*-0.1'):
        SelectorConfig(repeat_tolerance=-0.1)
    with pytest.raises(ValueError, match='refine_starts'):
        SelectorConfig(n_candidates=16, refine_starts=17)
    with pytest.raises(ValueError, match="criterion must be one of.*'d_optimal'"):
        _cost(arm, box_configs, None, criterion='d_optimal')
    with pytest.raises(ValueError, match="occlusion_mode must be one of.*'ratio'"):
        _cost(arm, box_configs, None, mode='ratio')
    with pytest.raises(ValueError, match='v_optimal.*box_configs'):
        _cost(arm, None, None, criterion='v_optimal')
    cost = _cost(arm, box_configs, None)
    with pytest.raises(ValueError, match=r'visited must be .*\(K, 7\).*\(3,\)'):
        JointSelector(arm.calibration_box).select(cost, None, np.zeros(3))


def test_batch_snaps_onto_the_previous_configuration_under_a_huge_ucsal_weight(arm, cost):
    prev = sampling.uniform_configs(arm.calibration_box, 1, 5)[0]
    cfg = SelectorConfig(strategy='ucsal', gamma=1e6, optimizer='batch', n_candidates=256, seed=1)
    s = JointSelector(arm.calibration_box, cfg).select(cost, prev)
    np.testing.assert_array_equal(s.theta, prev)      # exactly: the L1 kink, not merely near it


def test_search_names_the_optimizer_that_runs():
    """The benchmark and the node's log say which search ran (a 'DIRECT' label on a batch run
    once made the acquisition benchmark compare the batch optimiser with itself)."""
    assert SelectorConfig(optimizer='direct', max_evals=300).search == 'DIRECT_L, 300 evaluations'
    assert SelectorConfig(optimizer='batch').search.startswith('batch: 512 candidates + BOBYQA')


# ------------------------------------------------------------------ a stereo pair of cameras

def _stereo(arm, box_configs, **kw):
    mono = replace(_cost(arm, box_configs, None, 'gain', 'v_optimal'), **kw)
    pair = np.stack([arm.camera_pose('left'), arm.camera_pose('right')])
    return mono, replace(mono, camera_pose=pair)


def test_stereo_without_visibility_prior_gains_what_the_stereo_detection_teaches(arm, box_configs):
    mono, stereo = _stereo(arm, box_configs)
    right = replace(mono, camera_pose=arm.camera_pose('right'))
    qs = sampling.uniform_configs(arm.calibration_box, 32, 7)
    gain, eta, _ = stereo.terms_batch(qs)
    np.testing.assert_array_equal(eta, 1.0)                # no prior: both eyes assumed to see it
    hands = kinematics.forward_kinematics(arm.base, stereo.dh, qs)
    r1, r2 = (PoseDependentNoise().hand_covariance(c, hands, arm.markers) for c in stereo.camera_pose)
    fused = stereo_covariance(np.stack([r1, r2], axis=-3), PoseDependentNoise())    # the stereo detection's
    frames = kinematics.chain_frames(arm.base, stereo.dh, qs)
    hp = kinematics.pose_jacobian_from_frames(frames) @ stereo.P
    expected = information_gain(hp, hp @ np.swapaxes(kinematics.pose_jacobian_from_frames(frames), -1, -2) + fused,
                                stereo.weight)
    np.testing.assert_allclose(gain, expected, rtol=1e-10)
    # Two eyes teach more than either alone (on average: the stereo orientation, 1.4 times the
    # independent fusion's variance, can be worse than one eye's where the other sees badly), and
    # the update's covariance is the stereo detection's.
    assert gain.mean() > mono.terms_batch(qs)[0].mean() and gain.mean() > right.terms_batch(qs)[0].mean()
    assert np.mean(gain > mono.terms_batch(qs)[0]) > 0.9
    np.testing.assert_allclose(stereo.evaluate(qs), [stereo(q) for q in qs], rtol=1e-12, atol=1e-15)
    H = kinematics.pose_jacobian_from_frames(frames[:1])[0]
    S = H @ stereo.P @ H.T + fused[0]
    np.testing.assert_allclose(stereo.posterior(qs[0]),
                               stereo.P - stereo.P @ H.T @ np.linalg.solve(S, H @ stereo.P), rtol=1e-8, atol=1e-14)


def test_stereo_visibility_is_either_eye_by_the_correlation(arm, box_configs):
    prior = VisibilityPrior(arm.camera)
    mono, _ = _stereo(arm, box_configs, visibility=prior)
    left = arm.camera_pose('left')
    qs = sampling.uniform_configs(arm.calibration_box, 64, 3)
    p = mono.visibility_probability(qs)
    assert 0.1 < p.mean() < 0.9
    twin = np.stack([left, left])                          # the same camera twice: p1 = p2 = p
    np.testing.assert_allclose(replace(mono, camera_pose=twin, eye_correlation=1.0).visibility_probability(qs), p,
                               rtol=1e-12)
    np.testing.assert_allclose(replace(mono, camera_pose=twin, eye_correlation=0.0).visibility_probability(qs),
                               1 - (1 - p) ** 2, rtol=1e-12)
    # The gain given success weighs the outcomes: with the same camera twice and nested visibility
    # the hand is seen by both or by neither, so the gain is the fused detection's.
    nested = replace(mono, camera_pose=twin, eye_correlation=1.0)
    fused = replace(mono, camera_pose=twin, visibility=None)
    np.testing.assert_allclose(nested.terms_batch(qs)[0], fused.terms_batch(qs)[0], rtol=1e-10)
    independent = replace(nested, eye_correlation=0.0)
    gain_mono = mono.terms_batch(qs)[0]
    g = independent.terms_batch(qs)[0]
    assert np.all(g > gain_mono - 1e-12) and np.all(g < fused.terms_batch(qs)[0] + 1e-12)


@pytest.mark.parametrize('depth_ratio', [1.0, 4.0])
def test_stereo_single_evaluation_equals_batched(arm, box_configs, learned_occlusion, depth_ratio):
    # The local search evaluates one configuration at a time through the noise model's single-pose
    # path and one stacked solve for the three outcomes; the Sobol batch through the batched path.
    law = PoseDependentNoise(depth_ratio=depth_ratio)
    _, stereo = _stereo(arm, box_configs, visibility=VisibilityPrior(arm.camera), noise=law,
                        occlusion=learned_occlusion, occlusion_mode='gain')
    qs = sampling.uniform_configs(arm.calibration_box, 64, 11)
    batch = stereo.terms_batch(qs)
    single = [stereo.terms_batch(q[None]) for q in qs]
    for k in range(3):
        np.testing.assert_allclose(batch[k], [s[k][0] for s in single], rtol=1e-12, atol=1e-15)
    assert np.ptp(batch[0]) > 0 and np.ptp(batch[1]) > 0.1


def test_one_view_per_camera_serves_the_noise_law_and_the_prior(arm, box_configs):
    # A cost evaluation computes each camera's view of the markers once and hands it to both; each
    # must get what it computes on its own, for its own camera (not the other eye's).
    law = PoseDependentNoise(depth_ratio=4.0)
    prior = VisibilityPrior(arm.camera, marker_side=0.03, margin_marker_widths=0.5)
    _, stereo = _stereo(arm, box_configs, visibility=prior, noise=law)
    qs = sampling.uniform_configs(arm.calibration_box, 16, 13)
    hands = kinematics.forward_kinematics(arm.base, arm.dh, qs)
    cams = [arm.camera_pose(eye) for eye in ('left', 'right')]
    marker_poses = hands[:, None] @ np.stack([m.hand_T_marker for m in arm.markers])
    for n in (len(hands), 1):                              # the Sobol batch and the local search's one pose
        views = stereo._views(hands[:n])
        both, r1, r2 = stereo._pair_covariances(hands[:n], views)
        for cam, r in zip(cams, (r1, r2)):
            own = law.hand_covariance(cam, hands[:n], arm.markers)
            np.testing.assert_array_equal(r, own)
        for cam, view in zip(cams, views):
            np.testing.assert_array_equal(prior.probability(cam, view[0], 0.001, 0.5, view[1:]),
                                          prior.probability(cam, marker_poses[:n], 0.001, 0.5))
    assert not np.allclose(r1, r2)                         # the eyes' laws differ: a swap would show


def test_per_eye_occlusion_without_attempts_is_the_geometric_either_eye(arm, box_configs, learned_occlusion):
    # Untaught, each eye's model returns its prior mean (the eye's geometric visibility): the
    # either-eye success probability and the gain are those of the shared model before it learns.
    prior = VisibilityPrior(arm.camera)
    _, shared = _stereo(arm, box_configs, visibility=prior, occlusion=OcclusionModel(arm.calibration_box, 0.5, 1.0, 2.0))
    untaught = tuple(OcclusionModel(arm.calibration_box, 0.5, 1.0, 2.0) for _ in range(2))
    per_eye = replace(shared, occlusion=learned_occlusion, eye_occlusion=untaught)   # the shared one is unused
    qs = sampling.uniform_configs(arm.calibration_box, 64, 12)
    for a, b in zip(per_eye.terms_batch(qs), shared.terms_batch(qs)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(per_eye.evaluate(qs), [per_eye(q) for q in qs], rtol=1e-12, atol=1e-15)


def test_per_eye_occlusion_plans_for_the_eye_that_sees(arm, box_configs):
    # Where the left eye has failed and the right has seen the hand, the attempt is still likely to
    # succeed (either eye), and the gain expected is the right eye's alone.
    models = tuple(OcclusionModel(arm.calibration_box, 0.5, 1.0, 2.0) for _ in range(2))
    q = sampling.uniform_configs(arm.calibration_box, 1, 13)[0]
    for _ in range(10):
        models[0].add(q, False)
        models[1].add(q, True)
    mono, stereo = _stereo(arm, box_configs)
    stereo = replace(stereo, eye_occlusion=models)
    gain, eta, _ = stereo.terms_batch(q[None])
    p_left, p_right = (m.mean(q) for m in models)
    assert p_left < 0.2 < 0.8 < p_right
    assert max(p_left, p_right) <= eta[0] <= p_left + p_right
    right = replace(mono, camera_pose=arm.camera_pose('right'))
    both = replace(stereo, eye_occlusion=None)                 # both eyes assumed to see it
    g_right, g_both = right.terms_batch(q[None])[0][0], both.terms_batch(q[None])[0][0]
    assert abs(gain[0] - g_right) < 0.2 * abs(g_both - g_right)
    # Both eyes failing there: the attempt is unlikely to succeed.
    for _ in range(20):
        models[1].add(q, False)
    assert stereo.terms_batch(q[None])[1][0] < 0.5 * eta[0]


def test_stereo_cost_refuses_what_it_cannot_model(arm, box_configs):
    mono, stereo = _stereo(arm, box_configs)
    with pytest.raises(ValueError, match=r'camera_pose must have shape.*\(3, 4, 4\)'):
        replace(mono, camera_pose=np.stack([arm.camera_pose('left')] * 3))
    with pytest.raises(ValueError, match='eye_correlation.*1.5'):
        replace(stereo, eye_correlation=1.5)
    models = (OcclusionModel(arm.calibration_box), OcclusionModel(arm.calibration_box))
    with pytest.raises(ValueError, match=r'eye_occlusion needs two cameras.*1 camera'):
        replace(mono, eye_occlusion=models)
    with pytest.raises(ValueError, match=r'eye_visibility_weights.*1.2'):
        replace(stereo, eye_visibility_weights=(0.5, 1.2))
    extrinsics = Extrinsics(arm.camera_pose('left'), arm.markers[0].hand_T_marker, (0.01, 0.01), None)
    with pytest.raises(ValueError, match='one camera'):
        AcquisitionCost(arm.base, stereo.dh, scipy.linalg.block_diag(stereo.P, np.eye(extrinsics.n) * 1e-4),
                        PoseDependentNoise(), stereo.camera_pose, arm.markers, extrinsics=extrinsics)
