"""The detector-error replay: variants parse with their types, and a replay scores what it should."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema import load_robot, sampling
from body_schema.noise import PoseDependentNoise, sample_pose
from dh_estimator.estimator import EstimatorSettings
from tools.error_replay import TRUE_BODY_WIDTHS, cached_observations, carry_errors, parse_variant, replay


def test_variants_are_typed_by_the_setting_defaults_and_bad_ones_named() -> None:
    assert parse_variant('covariance=gauss_newton,change_window=4,loss_scale=2') == {
        'covariance': 'gauss_newton', 'change_window': 4, 'loss_scale': 2.0}
    with pytest.raises(ValueError, match="'windw=4' is not name=value"):
        parse_variant('windw=4')
    with pytest.raises(ValueError, match="change_window takes a int, got 'four'"):
        parse_variant('change_window=four')


def test_replay_of_errors_drawn_from_the_law_is_consistent() -> None:
    # Observations whose errors are the law's own: NEES near its dof, no change, small errors.
    arm = load_robot()
    law = PoseDependentNoise.for_robot(arm)
    rng = np.random.default_rng(0)
    pool = []
    cam = arm.camera_pose('left')
    for q in sampling.uniform_configs(arm.calibration_box, 80, 3):
        hand = arm.forward_kinematics(q)
        R = law.hand_covariance(cam, hand, arm.markers)  # noqa: N806
        pool.append((q, sample_pose(hand, R, rng), R))
    r = replay(arm, pool, EstimatorSettings(), trials=4, n_obs=60)
    assert r['band'][0] < np.median(r['nees']) < r['band'][1]
    assert not r['changes'].any() and np.all(r['position_mm'] < 3.0)


def test_errors_are_carried_onto_a_perturbed_arm_unchanged() -> None:
    from body_schema.map_estimator import pose_residuals

    arm = load_robot('ur5e')
    rng = np.random.default_rng(1)
    qs = sampling.uniform_configs(arm.calibration_box, 5, 2)
    R = np.diag([1e-6] * 3 + [1e-5] * 3)  # noqa: N806
    pool = [(q, sample_pose(arm.forward_kinematics(q), R, rng), R) for q in qs]
    true_dh = sampling.perturb_dh(arm.dh, 4, *TRUE_BODY_WIDTHS)
    carried = carry_errors(arm, pool, true_dh)
    nominal = arm.forward_kinematics(qs)
    real = arm.with_dh(true_dh).forward_kinematics(qs)
    np.testing.assert_allclose(pose_residuals(np.array([c[1] for c in carried]), real),
                               pose_residuals(np.array([p[1] for p in pool]), nominal), atol=1e-12)
    assert all(c[2] is p[2] and c[0] is p[0] for c, p in zip(carried, pool))
    assert np.max(np.abs(real[:, :3, 3] - nominal[:, :3, 3])) > 1e-3      # the arm really differs


def test_a_saved_pool_is_read_back_and_one_of_another_robot_refused(tmp_path, monkeypatch) -> None:
    from tools import error_replay

    arm = load_robot()
    rendered = []

    def fake(model, n, seed):                           # stands in for the renderer
        rendered.append((n, seed))
        q = sampling.uniform_configs(model.calibration_box, n, seed)
        return [(qi, model.forward_kinematics(qi), np.eye(6) * 1e-6) for qi in q]
    monkeypatch.setattr(error_replay, 'observations', fake)
    path = tmp_path / 'pool.npz'
    first = cached_observations(arm, 5, 2, path)
    again = cached_observations(arm, 5, 2, path)
    assert rendered == [(5, 2)] and len(again) == 5                  # rendered once, then read
    assert all(np.allclose(a, b) for x, y in zip(first, again) for a, b in zip(x, y))
    with pytest.raises(ValueError, match=r"holds the detections of icub_right_arm/5/2, not icub_right_arm/6/2"):
        cached_observations(arm, 6, 2, path)
