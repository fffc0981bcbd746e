"""The online MAP estimator: accuracy against the batch solution, consistency, robustness,
adaptation to a changing body, the sliding window, bad input, state round trip."""
import numpy as np
import pytest
from scipy.stats import chi2

import body_schema
from body_schema import ekf, sampling
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import PoseDependentNoise, sample_pose
from body_schema.synthetic import SyntheticRun


@pytest.fixture(scope='module')
def arm():
    return body_schema.load_robot()


def _true(arm, seed):
    return sampling.perturb_dh(arm.dh, 1000 + seed, 0.004, np.radians(2.0))


def _run(arm, seed, n, settings=MapSettings(), changes=None):
    true = _true(arm, seed)
    obs = SyntheticRun(arm, true, PoseDependentNoise(), seed, changes or {})(n)
    est = MapEstimator(arm.base, sampling.perturb_dh(arm.dh, seed), sampling.initial_covariance(7),
                       settings, limits=arm.limits)
    nis = []
    for o in obs:
        nis.append(est.update(o.q, o.pose, o.R).nis)
    return true, obs, est, np.array(nis)


def test_online_equals_batch_and_beats_ekf(arm):
    """Re-solving after each observation ends where one batch solve of the same data ends,
    and well below the paper's EKF on the same data."""
    true, obs, est, _ = _run(arm, 0, 40)
    batch = MapEstimator(arm.base, sampling.perturb_dh(arm.dh, 0), sampling.initial_covariance(7))
    batch.solve_batch([o.q for o in obs], [o.pose for o in obs], [o.R for o in obs])
    ev = PoseErrorEvaluator(arm.base, true, arm.calibration_box, n=300)
    assert ev(est.x).position_mm == pytest.approx(ev(batch.x).position_mm, rel=0.05)
    f = ekf.ExtendedKalmanFilter(sampling.perturb_dh(arm.dh, 0).ravel(), sampling.initial_covariance(7))
    model = ekf.HandPoseModel(arm.base, 7)
    for o in obs:
        model.update(f, o.q, o.pose, o.R)
    assert ev(est.x).position_mm < 0.5 * ev(f.x).position_mm
    assert ev(est.x).position_mm < 1.5


def test_consistency_nees_and_nis(arm):
    """Over seeded runs with honest noise, NEES and NIS match their chi-square laws."""
    runs = [_run(arm, seed, 30) for seed in range(8)]
    nees = [ekf.nees(t.ravel(), e.x, e.P) for t, _, e, _ in runs]
    n = len(nees)
    lo, hi = chi2.ppf(0.005, 28 * n) / n, chi2.ppf(0.995, 28 * n) / n
    assert lo < np.mean(nees) < hi
    nis = np.concatenate([s[10:] for *_, s in runs])
    assert abs(np.mean(nis) / 6.0 - 1.0) < 0.15
    assert sum(e.n_outliers for _, _, e, _ in runs) <= 1


def test_outlier_is_flagged_and_does_not_spoil_the_estimate(arm):
    true, obs, est, _ = _run(arm, 1, 25)
    ev = PoseErrorEvaluator(arm.base, true, arm.calibration_box, n=300)
    before = ev(est.x).position_mm
    q = obs[3].q
    z = arm.with_dh(true).forward_kinematics(q)
    z[:3, 3] += 0.15                                   # a 15 cm wrong detection
    u = est.update(q + 1e-3, z, obs[3].R)
    assert u.outlier and u.residual_chi2 > chi2.ppf(0.999, 6)
    assert est.n_outliers == 1
    assert ev(est.x).position_mm < before + 1.0        # the robust loss keeps its pull bounded


def test_a_truncated_solve_does_not_judge_clean_data_an_outlier(arm):
    """A re-solve stopped at max_nfev leaves clean observations beyond the bound (the solver's
    misfit, not the data's); verdict_nfev solves on before the verdict, and a real outlier is
    still one."""
    def verdicts(verdict_nfev):
        flagged, resolved = 0, 0
        for seed in range(3):
            obs = SyntheticRun(arm, _true(arm, seed), PoseDependentNoise(), seed)(12)
            est = MapEstimator(arm.base, sampling.perturb_dh(arm.dh, seed), sampling.initial_covariance(7),
                               MapSettings(max_nfev=3, verdict_nfev=verdict_nfev), limits=arm.limits)
            flagged += sum(est.update(o.q, o.pose, o.R).outlier for o in obs)
            resolved += est.n_resolved
        return flagged, resolved

    flagged, resolved = verdicts(0)
    assert flagged >= 3 and resolved == 0              # the truncated solves' verdicts
    flagged, resolved = verdicts(200)
    assert flagged == 0 and resolved >= 3
    true, obs, est, _ = _run(arm, 1, 25, MapSettings(max_nfev=3, verdict_nfev=200))
    z = arm.with_dh(true).forward_kinematics(obs[3].q)
    z[:3, 3] += 0.15                                   # a 15 cm wrong detection
    u = est.update(obs[3].q + 1e-3, z, obs[3].R)
    assert u.outlier and u.resolved


def test_change_detection_follows_a_changed_body_and_stays_quiet_otherwise(arm):
    changed = _true(arm, 2).copy()
    changed[4, 1] += 0.010                             # forearm 10 mm longer
    changed[2, 3] += np.radians(3.0)                   # shoulder yaw offset +3 deg
    settings = MapSettings()                           # change detection is on by default
    true, obs, est, _ = _run(arm, 2, 60, settings, {30: changed})
    assert est.n_changes >= 1
    ev = PoseErrorEvaluator(arm.base, changed, arm.calibration_box, n=300)
    assert ev(est.x).position_mm < 2.0
    without = _run(arm, 2, 60, MapSettings(change_probability=0.0), {30: changed})[2]
    assert ev(without.x).position_mm > 2 * ev(est.x).position_mm
    quiet = _run(arm, 3, 60, settings)[2]
    assert quiet.n_changes == 0


def test_one_gross_outlier_is_not_a_change(arm):
    settings = MapSettings(change_probability=0.999, warmup=0)
    true, obs, est, _ = _run(arm, 7, 20, settings)
    z = arm.with_dh(true).forward_kinematics(obs[0].q)
    z[:3, :3] = z[:3, :3] @ np.diag([-1.0, -1.0, 1.0])        # a flipped marker: 180 deg off
    assert est.update(obs[0].q + 1e-3, z, obs[0].R).nis > 1000
    for o in SyntheticRun(arm, true, PoseDependentNoise(), 70)(3):
        est.update(o.q, o.pose, o.R)
    assert est.n_changes == 0 and est.n_outliers == 1


def test_the_same_wrong_view_three_times_is_not_a_change_three_views_are(arm):
    """Exceedances at one configuration count once: the same view repeats its detection error."""
    settings = MapSettings(warmup=0)
    true, obs, _, _ = _run(arm, 8, 20, settings)
    rng = np.random.default_rng(8)
    qs = [obs[i].q for i in (1, 5, 9)]

    def wrong(q):
        z = arm.with_dh(true).forward_kinematics(q)
        z[:3, 3] += 0.02                                   # 2 cm off: far beyond the bound
        return z

    def after(views):
        est = _run(arm, 8, 20, settings)[2]
        for q in views:
            est.update(q + rng.uniform(-1e-3, 1e-3, q.shape), wrong(q), obs[0].R)
        return est

    assert after([qs[0]] * 3).n_changes == 0           # one view, tried three times (0.06 deg apart)
    assert after(qs).n_changes == 1                    # three views: the body changed
    assert after([qs[0]] * 3).n_outliers >= 1
    # Every exceedance counts with the separation at 0 (the test as it was).
    est = _run(arm, 8, 20, MapSettings(warmup=0, change_separation=0.0))[2]
    for _ in range(3):
        est.update(qs[0], wrong(qs[0]), obs[0].R)
    assert est.n_changes == 1
    with pytest.raises(ValueError, match='change_separation'):
        MapSettings(change_separation=-1.0)


def test_a_change_no_body_explains_is_withdrawn(arm):
    """Flipped markers at three views pass the count, but the re-solved body leaves them outliers:
    the jump is withdrawn and the estimate is the one without a change test; a real change stands."""
    true, obs, _, _ = _run(arm, 9, 20, MapSettings(warmup=0))

    def flipped(q):
        z = arm.with_dh(true).forward_kinematics(q)
        z[:3, :3] = z[:3, :3] @ np.diag([-1.0, -1.0, 1.0])     # a planar flip: 180 deg about the normal
        return z

    def after(settings):
        est = _run(arm, 9, 20, settings)[2]
        updates = [est.update(obs[i].q + 1e-3, flipped(obs[i].q), obs[0].R) for i in (2, 6, 11)]
        return est, updates

    confirmed, updates = after(MapSettings(warmup=0))
    assert confirmed.n_changes == 0 and confirmed.n_changes_withdrawn >= 1
    assert updates[-1].change_withdrawn and updates[-1].outlier and not updates[-1].change_detected
    no_test = after(MapSettings(warmup=0, change_probability=0.0))[0]
    np.testing.assert_array_equal(confirmed.x, no_test.x)
    np.testing.assert_array_equal(confirmed.P, no_test.P)
    unconfirmed = after(MapSettings(warmup=0, change_confirm=False))[0]
    assert unconfirmed.n_changes == 1 and unconfirmed.n_changes_withdrawn == 0
    assert not np.array_equal(unconfirmed.x, no_test.x)
    # A body that did change is explained by the re-solve at once: the change stands.
    changed = _true(arm, 9).copy()
    changed[4, 1] += 0.010
    changed[2, 3] += np.radians(3.0)
    est = _run(arm, 9, 40, MapSettings(), {25: changed})[2]
    assert est.n_changes == 1 and est.n_changes_withdrawn == 0
    # A window shorter than the test's has folded older exceedances into the prior: the stored ones
    # are judged (two of the three flips here), and an update never fails for it.
    short, updates = after(MapSettings(warmup=0, window=2))
    assert short.n_observations == 2 and short.n_changes_withdrawn >= 1 and updates[-1].change_withdrawn


def test_window_folds_old_observations_into_the_prior(arm):
    true, obs, full, _ = _run(arm, 4, 30)
    windowed = _run(arm, 4, 30, MapSettings(window=10))[2]
    assert windowed.n_observations == 10 and windowed.n_marginalised == 20
    ev = PoseErrorEvaluator(arm.base, true, arm.calibration_box, n=300)
    assert ev(windowed.x).position_mm < 1.3 * ev(full.x).position_mm + 0.1
    # Marginalisation keeps the information: the covariances agree closely.
    np.testing.assert_allclose(np.sqrt(np.diag(windowed.P)), np.sqrt(np.diag(full.P)), rtol=0.2)


@pytest.mark.parametrize('bad', ['nan', 'shape', 'singular', 'indefinite', 'limits', 'rotation'])
def test_bad_input_raises_and_changes_nothing(arm, bad):
    _, obs, est, _ = _run(arm, 5, 3)
    before = est.state_dict()
    q, z, R = obs[0].q.copy(), obs[0].pose.copy(), obs[0].R.copy()  # noqa: N806
    if bad == 'nan':
        z[0, 3] = np.nan
    elif bad == 'shape':
        R = R[:5, :5]  # noqa: N806
    elif bad == 'singular':
        R = np.zeros((6, 6))  # noqa: N806
    elif bad == 'indefinite':
        R = np.diag([1e-6, -1e-6, 1e-6, 1e-4, 1e-4, 1e-4])  # noqa: N806
    elif bad == 'limits':
        q[0] = arm.limits[0, 0] - 0.1
    else:
        z[:3, :3] *= 2.0
    with pytest.raises(ekf.InvalidInputError):
        est.update(q, z, R)
    after = est.state_dict()
    for k in before:
        np.testing.assert_array_equal(after[k], before[k])


def test_state_dict_round_trip_continues_identically(arm):
    _, obs, est, _ = _run(arm, 6, 8)
    again = MapEstimator(arm.base, np.zeros(28), np.eye(28))
    again.load_state_dict(est.state_dict())
    extra = SyntheticRun(arm, _true(arm, 6), PoseDependentNoise(), 99)(2)
    for o in extra:
        est.update(o.q, o.pose, o.R)
        again.update(o.q, o.pose, o.R)
    np.testing.assert_array_equal(again.x, est.x)
    np.testing.assert_array_equal(again.P, est.P)


def test_state_dict_keeps_the_change_test_window_and_reads_an_older_checkpoint(arm):
    """Fresh (nothing recent), mid-run (the recent exceedances' configurations) and a checkpoint
    written before the configurations were kept (each exceedance then counts)."""
    fresh = MapEstimator(arm.base, np.zeros(28), np.eye(28))
    d = fresh.state_dict()
    assert d['map_recent_q'].shape == (0, 7)
    MapEstimator(arm.base, np.zeros(28), np.eye(28)).load_state_dict(d)
    _, _, est, _ = _run(arm, 6, 8)
    d = est.state_dict()
    assert d['map_recent_q'].shape == (len(d['map_recent_nis']), 7) and len(d['map_recent_nis']) > 0
    again = MapEstimator(arm.base, np.zeros(28), np.eye(28))
    again.load_state_dict(d)
    np.testing.assert_array_equal(np.array(again._recent_q), d['map_recent_q'])
    old = {k: v for k, v in d.items() if k != 'map_recent_q'}
    again.load_state_dict(old)
    assert np.isnan(np.array(again._recent_q)).all() and len(again._recent_q) == len(d['map_recent_nis'])


@pytest.mark.parametrize('kw, words', [({'loss': 'l2'}, 'loss'), ({'window': 1}, 'window'),
                                       ({'q_length': -1.0}, 'q_length'),
                                       ({'change_probability': 1.0}, 'change_probability'),
                                       ({'change_count': 5}, 'change_count')])
def test_settings_name_the_bad_value(kw, words):
    with pytest.raises(ValueError, match=words):
        MapSettings(**kw)


def test_information_limit_predicts_the_achieved_error(arm):
    """With honest noise the error the posterior implies matches, on average, the error reached."""
    from body_schema.metrics import expected_pose_errors
    achieved, expected = [], []
    for seed in range(6):
        true, _, est, _ = _run(arm, seed, 30)
        achieved.append(PoseErrorEvaluator(arm.base, true, arm.calibration_box, n=300)(est.x).position_mm)
        expected.append(expected_pose_errors(arm.base, est.x, est.P, arm.calibration_box, n=300).position_mm)
    assert np.mean(achieved) == pytest.approx(np.mean(expected), rel=0.3)
    # A covariance four times larger implies twice the error.
    doubled = expected_pose_errors(arm.base, est.x, 4 * est.P, arm.calibration_box, n=300).position_mm
    assert doubled == pytest.approx(2 * expected[-1], rel=0.05)


def test_innovation_is_what_the_update_reports_and_changes_nothing(arm):
    _, obs, est, _ = _run(arm, 8, 12)
    extra = SyntheticRun(arm, _true(arm, 8), PoseDependentNoise(), 81)(1)[0]
    before = est.state_dict()
    y, S = est.innovation(extra.q, extra.pose, extra.R)  # noqa: N806
    for k, v in est.state_dict().items():
        np.testing.assert_array_equal(v, before[k])
    u = est.update(extra.q, extra.pose, extra.R)
    np.testing.assert_allclose(u.innovation, y)
    np.testing.assert_allclose(u.S, S)
    assert u.nis == pytest.approx(float(y @ np.linalg.solve(S, y)))


# --------------------------------------------------------------------------------------------
# The robust estimate's own covariance (Huber's sandwich)

def _robust_fits(noise, trials: int = 300, n: int = 150, seed: int = 0, leverage: bool = False):
    """Robust (Cauchy, scale 3) fits of a linear model with unit stated noise: the estimates' errors
    and the sandwich and Gauss-Newton covariances each fit reported."""
    from scipy.optimize import least_squares

    from body_schema.map_estimator import sandwich_covariance

    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 4))  # noqa: N806
    beta = np.array([1.0, -2.0, 0.5, 3.0])
    jp = 1e-3 * np.eye(4)                       # a weak Gaussian prior at 0
    errors, sandwiches = [], []
    for _ in range(trials):
        y = X @ beta + noise(rng, n)

        def fun(b):
            return np.concatenate([jp @ b, y - X @ b])
        res = least_squares(fun, np.zeros(4), loss='cauchy', f_scale=3.0)
        errors.append(res.x - beta)
        sandwiches.append(sandwich_covariance(jp, -X, res.fun[4:], 'cauchy', 3.0, leverage=leverage))
    gauss_newton = np.linalg.inv(jp.T @ jp + X.T @ X)
    return np.array(errors), np.array(sandwiches), gauss_newton


def test_sandwich_is_gauss_newton_for_gaussian_noise_of_the_stated_scale():
    errors, sandwiches, gn = _robust_fits(lambda rng, n: rng.normal(size=n))
    ratio = np.trace(sandwiches.mean(axis=0)) / np.trace(gn)
    assert 1.0 < ratio < 1.12                          # Cauchy at 3 sigma: a few per cent of efficiency
    nees = np.einsum('ti,tij,tj->t', errors, np.linalg.inv(sandwiches), errors)
    assert np.mean(nees) == pytest.approx(4.0, rel=0.15)


def test_sandwich_is_consistent_where_a_variance_matched_gaussian_law_is_not():
    # Heavy tails (Student t, 1.3 dof: as the simulated ArUco detector's errors at 1.7 m), stated
    # noise 1: most residuals are far below 1, so the robust fit is far better than (X^T X)^-1 says.
    errors, sandwiches, gn = _robust_fits(lambda rng, n: 0.1 * rng.standard_t(1.3, size=n))
    nees_gn = np.einsum('ti,ij,tj->t', errors, np.linalg.inv(gn), errors)
    nees = np.einsum('ti,tij,tj->t', errors, np.linalg.inv(sandwiches), errors)
    assert np.mean(nees_gn) < 0.5                      # pessimistic: the expected value is 4
    assert np.mean(nees) == pytest.approx(4.0, rel=0.2)


def test_leverage_corrected_spread_is_gauss_newton_or_a_little_more_for_gaussian_noise():
    errors, sandwiches, gn = _robust_fits(lambda rng, n: rng.normal(size=n), leverage=True)
    ratio = np.trace(sandwiches.mean(axis=0)) / np.trace(gn)
    assert 1.0 < ratio < 1.2
    nees = np.einsum('ti,tij,tj->t', errors, np.linalg.inv(sandwiches), errors)
    assert np.mean(nees) == pytest.approx(4.0, rel=0.15)


def test_leverage_correction_grows_where_few_observations_inform_a_direction():
    # The same residuals, two designs: every row alike, or parameter 3 seen by 3 rows of 150
    # (as an active selector's few decisive poses). The degrees-of-freedom spread cannot tell
    # them apart; the leverage-corrected one inflates the second.
    from body_schema.map_estimator import sandwich_covariance

    rng = np.random.default_rng(4)
    u = rng.normal(size=150)
    even = rng.normal(size=(150, 4))
    uneven = even.copy()
    uneven[3:, 3] = 0.0
    uneven[:3, 3] *= 3.0
    jp = 1e-3 * np.eye(4)

    def inflation(x):
        return np.trace(sandwich_covariance(jp, x, u, 'cauchy', 3.0, leverage=True)) / \
            np.trace(sandwich_covariance(jp, x, u, 'cauchy', 3.0))
    assert 0.98 < inflation(even) < 1.05
    assert inflation(uneven) > inflation(even) + 0.05

    def row_inflation(x):        # each row's own spread, with and without its leverage correction
        return np.trace(sandwich_covariance(jp, x, u, 'cauchy', 3.0, per_row=True, leverage=True)) / \
            np.trace(sandwich_covariance(jp, x, u, 'cauchy', 3.0, per_row=True))
    assert 1.0 < row_inflation(even) < 1.1                  # HC3 widens a little more than HC1 even so
    assert row_inflation(uneven) > row_inflation(even) + 0.1
    hc2 = np.trace(sandwich_covariance(jp, uneven, u, 'cauchy', 3.0, per_row=True, leverage=True, leverage_power=1))
    hc1, hc3 = (np.trace(sandwich_covariance(jp, uneven, u, 'cauchy', 3.0, per_row=True, leverage=lev))
                for lev in (False, True))
    assert hc1 < hc2 < hc3                                  # HC2's correction: half of HC3's, in the exponent
    with pytest.raises(ValueError, match='leverage_power must be 1 .* got 3'):
        sandwich_covariance(jp, uneven, u, 'cauchy', 3.0, per_row=True, leverage=True, leverage_power=3)


def test_per_row_spread_follows_a_law_of_the_wrong_shape_where_the_pooled_one_cannot():
    # Stated noise 1 everywhere; the rows that see parameters 0-2 are really 0.4 wide and those
    # that see parameter 3 0.8 wide (a law that overstates one component of a detection more
    # than another). One pooled scale is too wide for the first and too narrow for the second.
    from scipy.optimize import least_squares

    from body_schema.map_estimator import sandwich_covariance

    rng = np.random.default_rng(5)
    X = np.zeros((200, 4))  # noqa: N806
    X[:100, :3] = rng.normal(size=(100, 3))
    X[100:, 3] = rng.normal(size=100)
    sigma = np.r_[np.full(100, 0.4), np.full(100, 0.8)]
    jp = 1e-3 * np.eye(4)
    groups = np.repeat([0, 1], 100)
    nees = {'pooled': [], 'per_row': [], 'groups': []}
    for _ in range(300):
        y = sigma * rng.normal(size=200)                     # truth 0

        def fun(b):
            return np.concatenate([jp @ b, y - X @ b])
        res = least_squares(fun, np.zeros(4), loss='cauchy', f_scale=3.0)
        u = res.fun[4:]
        for name, P in (('pooled', sandwich_covariance(jp, -X, u, 'cauchy', 3.0)),  # noqa: N806
                        ('per_row', sandwich_covariance(jp, -X, u, 'cauchy', 3.0, per_row=True)),
                        ('groups', sandwich_covariance(jp, -X, u, 'cauchy', 3.0, leverage=True, groups=groups))):
            nees[name].append(res.x ** 2 / np.diag(P))      # per parameter, 1 on average if right
    pooled, per_row, grouped = (np.mean(nees[k], axis=0) for k in ('pooled', 'per_row', 'groups'))
    assert pooled[3] > 1.5 and np.all(pooled[:3] < 0.6)        # too narrow, then too wide
    assert np.all((per_row > 0.7) & (per_row < 1.4)), per_row    # 300 trials: +-0.1 of noise
    assert np.all((grouped > 0.7) & (grouped < 1.4)), grouped    # a spread per group of rows: as right


def test_one_group_of_rows_is_the_pooled_spread():
    from body_schema.map_estimator import sandwich_covariance

    rng = np.random.default_rng(6)
    jo, u, jp = rng.normal(size=(120, 5)), rng.normal(size=120), 1e-2 * np.eye(5)
    for leverage in (False, True):
        np.testing.assert_allclose(
            sandwich_covariance(jp, jo, u, 'cauchy', 3.0, leverage=leverage, groups=np.zeros(120, int)),
            sandwich_covariance(jp, jo, u, 'cauchy', 3.0, leverage=leverage), rtol=1e-12)
    with pytest.raises(ValueError, match=r'groups must have shape \(120,\).*got \(6,\)'):
        sandwich_covariance(jp, jo, u, 'cauchy', 3.0, groups=np.zeros(6, int))


def test_sandwich_declines_without_enough_residuals():
    from body_schema.map_estimator import sandwich_covariance

    rng = np.random.default_rng(1)
    jo = rng.normal(size=(12, 6))
    assert sandwich_covariance(np.eye(6) * 1e-3, jo, rng.normal(size=12), 'cauchy', 3.0) is None   # 6 dof left
    far = 100 * (1 + rng.random(12))                   # every residual beyond the loss scale: no spread to measure
    assert sandwich_covariance(np.eye(6) * 1e-3, jo, far, 'cauchy', 3.0, min_dof=1) is None
    assert sandwich_covariance(np.eye(6) * 1e-3, jo, far, 'cauchy', 3.0, min_dof=1, leverage=True) is None
    with pytest.raises(ValueError, match="covariance must be one of .*'sandwich'.*got 'robust'"):
        MapSettings(covariance='robust')


def test_a_loss_scale_at_the_typical_error_beats_the_default_under_a_variance_matched_law(arm):
    """Heavy-tailed errors (9 in 10 from a core, 1 in 10 ten times wider) described by a law fitted
    to their variance (11x the core's): with the loss departing from the square at 3 of the law's
    sigmas the tails pull the estimate; at 3 typical errors (``tools.fit_noise``'s
    ``loss_scale``) they do not, and the estimate ends closer to the truth."""
    inflation = 0.9 + 0.1 * 10.0 ** 2                   # the variance-matched law over the core
    spread = 1.0 / np.sqrt(inflation)                   # the typical error in that law's sigmas (about 0.3)
    errors = {3.0: [], 3.0 * spread: []}
    for seed in range(3):
        true = _true(arm, seed)
        rng = np.random.default_rng(50 + seed)
        core = SyntheticRun(arm, true, PoseDependentNoise(), seed)(50)
        ev = PoseErrorEvaluator(arm.base, true, arm.calibration_box, n=300)
        obs = [(o.q, sample_pose(arm.with_dh(true).forward_kinematics(o.q),
                                 o.R * (100.0 if rng.random() < 0.1 else 1.0), rng), inflation * o.R)
               for o in core]
        for scale in errors:
            est = MapEstimator(arm.base, sampling.perturb_dh(arm.dh, seed), sampling.initial_covariance(7),
                               MapSettings(loss_scale=scale), limits=arm.limits)
            for q, z, r in obs:
                est.update(q, z, r)
            errors[scale].append(ev(est.x).position_mm)
    default, typical = (np.mean(v) for v in errors.values())
    assert typical < 0.85 * default, errors
