"""Paper metrics: pose errors on a fixed set, geodesic orientation error, movement."""
import numpy as np
import pytest
from scipy.linalg import logm
from scipy.spatial.transform import Rotation

import body_schema
from body_schema import metrics, sampling


def test_orientation_error_matches_the_paper_formula():
    rng = np.random.default_rng(0)
    a = Rotation.random(random_state=1).as_matrix()
    for angle in (0.5, 10.0, 120.0):
        axis = rng.normal(size=3)
        b = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix() @ a
        paper = np.degrees(np.sqrt(np.linalg.norm(logm(a.T @ b), 'fro') ** 2 / 2))
        assert metrics.orientation_errors_deg(a, b) == pytest.approx(paper, rel=1e-6)
        assert metrics.orientation_errors_deg(a, b) == pytest.approx(angle, rel=1e-6)


def test_evaluator_zero_for_truth_and_positive_for_perturbation():
    arm = body_schema.load_robot()
    ev = metrics.PoseErrorEvaluator(arm.base, arm.dh, arm.calibration_box)
    assert ev.configs.shape == (metrics.EVAL_CONFIGS, 7)
    assert ev(arm.dh).position_m == pytest.approx(0.0, abs=1e-12)
    assert ev(arm.dh).orientation_deg == pytest.approx(0.0, abs=1e-5)
    shifted = arm.dh.copy()
    shifted[6, 1] += 0.01                                   # d of the last link: hand moves 10 mm
    e = ev(shifted)
    assert e.position_mm == pytest.approx(10.0, rel=1e-6) and e.orientation_deg < 1e-5
    # Same seed, same configurations: methods are scored on one set.
    np.testing.assert_array_equal(ev.configs, metrics.PoseErrorEvaluator(arm.base, arm.dh, arm.calibration_box).configs)


def test_accumulated_movement_and_discarded():
    thetas = np.radians([[0, 0], [10, -5], [10, 5]])
    np.testing.assert_allclose(metrics.accumulated_movement_deg(thetas), [15.0, 25.0])
    assert metrics.discarded_samples([True, False, False, True]) == 2


def test_initial_guess_sampler_widths():
    arm = body_schema.load_robot()
    draws = np.stack([sampling.perturb_dh(arm.dh, s) for s in range(400)]) - arm.dh
    assert np.all(np.abs(draws[..., :2]) <= 0.023 + 1e-12)
    assert np.all(np.abs(draws[..., 2:]) <= np.radians(27) + 1e-12)
    assert np.abs(draws[..., :2]).max() > 0.02                # the full width is used
    np.testing.assert_array_equal(sampling.perturb_dh(arm.dh, 7), sampling.perturb_dh(arm.dh, 7))
