"""The scene state: arm polylines, covariance ellipsoids, the error curve (pure, no ROS, no server)."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema.robot import load_robot
from calibration_viz.scene import SceneState, arm_points, covariance_ellipsoid

ROBOT = load_robot()


def test_arm_points_run_from_the_root_to_the_hand() -> None:
    q = ROBOT.calibration_box.mean(axis=1)
    pts = arm_points(ROBOT, ROBOT.dh, q)
    assert pts.shape == (ROBOT.n_joints + 2, 3)
    np.testing.assert_allclose(pts[0], 0.0)
    np.testing.assert_allclose(pts[-1], ROBOT.forward_kinematics(q)[:3, 3], atol=1e-12)


def test_covariance_ellipsoid_axes_are_the_position_block_eigenvectors() -> None:
    rot = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    cov = np.zeros((6, 6))
    cov[:3, :3] = rot @ np.diag([1e-6, 4e-6, 9e-6]) @ rot.T
    cov[3:, 3:] = np.eye(3)                       # the rotation block is not drawn
    radii, axes = covariance_ellipsoid(cov.ravel(), n_sigma=3.0)
    np.testing.assert_allclose(radii, [0.003, 0.006, 0.009], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.det(axes), 1.0)
    np.testing.assert_allclose(axes @ np.diag((radii / 3) ** 2) @ axes.T, cov[:3, :3], atol=1e-15)
    cov[0, 0] = np.nan
    with pytest.raises(ValueError, match='not finite'):
        covariance_ellipsoid(cov)


def test_error_curve_scores_estimates_against_the_real_arm_even_if_it_comes_later() -> None:
    s = SceneState(ROBOT, n_configs=50)
    far = ROBOT.dh + 0.01
    s.set_estimate(far)                 # before the real arm is known: scored when it arrives
    assert s.errors.position_mm == []
    v = s.version
    s.set_true(ROBOT.dh)
    s.set_estimate(ROBOT.dh)
    assert s.version == v + 2
    assert len(s.errors.position_mm) == 2
    assert s.errors.position_mm[0] > 5.0 and s.errors.position_mm[1] == pytest.approx(0.0, abs=1e-9)
    assert s.estimated_arm() is None    # no joints yet
    s.set_joints(ROBOT.calibration_box.mean(axis=1))
    np.testing.assert_allclose(s.estimated_arm(), s.real_arm())


def test_observations_keep_the_latest_history() -> None:
    s = SceneState(ROBOT, history=3)
    for i in range(5):
        pose = np.eye(4)
        pose[0, 3] = i
        s.add_observation(pose, np.eye(6))
    assert [o.root_T_hand[0, 3] for o in s.observations] == [2.0, 3.0, 4.0]
