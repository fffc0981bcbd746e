"""The detector-error replay: variants parse with their types, and a replay scores what it should."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema import load_robot, sampling
from body_schema.noise import PoseDependentNoise, sample_pose
from dh_estimator.estimator import EstimatorSettings
from tools.error_replay import parse_variant, replay


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
