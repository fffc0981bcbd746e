"""Identifiability of DH tables: the unidentifiable directions are the ones the geometry predicts."""
from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.linalg

from body_schema import kinematics
from body_schema.identifiability import (analyse, analyse_jacobian, parallel_axis_groups, parameter_names,
                                         subspace_nees)
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.robot import load_robot
from body_schema.sampling import uniform_configs

UR5E = load_robot('ur5e')
ICUB = load_robot('icub_right_arm')


def _predicted_ur_null_space() -> np.ndarray:
    """Derived from the geometry, not from the module: joint axes in the root frame at a random
    configuration; every pair of consecutive parallel axes makes the difference of their links'
    ``d`` (both translate along the same line, and nothing in between turns that line) invisible."""
    q = uniform_configs(UR5E.calibration_box, 1, 7)[0]
    frames = kinematics.chain_frames(UR5E.base, UR5E.dh, q[None])[0]      # (L + 1, 4, 4)
    axes = frames[:-1, :3, 2]                                              # joint i turns about z of frame i
    cols = []
    for i in range(UR5E.n_joints - 1):
        if np.linalg.norm(np.cross(axes[i], axes[i + 1])) < 1e-9:
            v = np.zeros(UR5E.n_params)
            v[4 * i + 1], v[4 * (i + 1) + 1] = 1.0, -1.0
            cols.append(v)
    return scipy.linalg.orth(np.array(cols).T)


def test_ur5e_unidentifiable_directions_are_the_parallel_axis_ones():
    predicted = _predicted_ur_null_space()
    assert predicted.shape == (24, 2)           # shoulder lift, elbow, wrist 1: two parallel pairs
    found = analyse(UR5E, n=60, seed=3)
    assert found.rank == 22 and found.n_unidentifiable == 2
    angles = scipy.linalg.subspace_angles(found.null_space, predicted)
    assert np.max(angles) < 1e-8
    # Named by parameters, and explained by the parallel axes.
    for combo, why in zip(found.combinations(), found.reasons):
        assert set(combo.replace('-', ' ').replace('+', ' ').split()) <= {
            'shoulder_lift_joint.d', 'elbow_joint.d', 'wrist_1_joint.d'}
        assert 'parallel' in why and 'elbow_joint' in why
    # The sum of the three d is observed: the hand moves along it.
    s = np.zeros(24)
    s[[5, 9, 13]] = 1.0
    J = UR5E.jacobian_dh(uniform_configs(UR5E.calibration_box, 5, 0)).reshape(-1, 24)  # noqa: N806
    assert np.linalg.norm(J @ s) > 0.1
    assert np.linalg.norm(J @ found.null_space) < 1e-10


def test_parallel_axis_directions_are_flagged_approximate_and_split_from_the_exact_ones():
    from body_schema.extrinsics import Extrinsics

    found = analyse(UR5E, n=60, seed=3)
    assert found.approximate == (True, True)
    exact, parallel = found.held_groups()
    assert exact.shape == (24, 0) and parallel.shape == (24, 2)
    assert np.max(scipy.linalg.subspace_angles(parallel, found.held_directions)) < 1e-8
    # With the camera and marker estimated: 6 exact (what they absorb), the same 2 approximate.
    both = Extrinsics(UR5E.camera_pose('left'), UR5E.markers[0].hand_T_marker, (0.02, 0.03), (0.005, 0.08))
    found = analyse(UR5E, n=60, seed=3, extrinsics=both)
    assert sorted(found.approximate) == [False] * 6 + [True] * 2
    exact, parallel = found.held_groups()
    assert exact.shape == (36, 6) and parallel.shape == (36, 2)
    assert np.allclose(exact.T @ parallel, 0.0, atol=1e-12)
    assert np.max(scipy.linalg.subspace_angles(np.hstack([exact, parallel]), found.held_directions)) < 1e-8
    assert set(np.flatnonzero(np.abs(parallel).sum(axis=1) > 1e-9)) == {5, 9, 13}


@pytest.mark.parametrize('seed', [11, 12, 13])
def test_pinning_nearly_parallel_axes_at_a_wrong_guess_biases_the_rest_and_the_prior_hold_does_not(seed):
    """A real UR's joints 2-4 are parallel only to a fraction of a degree: their d differences are
    weakly observable. Pinned at a guess 20 mm off (the paper-wide initial spread), the other
    parameters absorb the error and the identifiable part is far outside its chi-square band at
    a camera's lateral precision (0.1 mm); held by the guess's own uncertainty instead, it is
    consistent."""
    rng = np.random.default_rng(seed)
    widths = np.tile([0.004, 0.004, np.radians(2.0), np.radians(2.0)], 6)
    true = UR5E.dh.ravel() + rng.uniform(-0.5, 0.5, 24) * widths
    parallel = analyse(UR5E, n=60).held_groups()[1]
    x0 = true + parallel @ np.array([0.02, -0.02])          # right but for the parallel d
    P0 = np.diag((np.tile([0.02, 0.02, np.radians(5.0), np.radians(5.0)], 6)) ** 2)  # noqa: N806
    qs, zs, Rs = _ur_observations(true.reshape(6, 4), 60, 4, scale=0.2)  # noqa: N806
    ident = analyse(UR5E, n=60).identifiable_basis
    nees = {}
    for name, std in (('pinned', 1e-6), ('prior', 0.02)):
        est = MapEstimator(UR5E.base, x0, P0, MapSettings(loss='linear', warmup=0),
                           fixed_directions=parallel, fixed_std=std)
        est.solve_batch(qs, zs, Rs)
        nees[name] = subspace_nees(est.x - true, est.P, ident)
    assert nees['pinned'] > 48.3                            # chi-square 22 dof: its 99.9 % bound
    assert nees['prior'] < 48.3


def test_the_icub_table_is_fully_identifiable_over_its_box():
    found = analyse(ICUB, n=60, seed=0)
    assert found.rank == 28 and found.n_unidentifiable == 0
    assert 'all 28 parameters identifiable' in found.describe()[0]
    assert parallel_axis_groups(ICUB.dh) == []


def test_parallel_axis_groups_of_the_ur5e():
    assert parallel_axis_groups(UR5E.dh) == [[1, 2, 3]]


def test_analyse_jacobian_names_a_planted_dependency():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(30, 4))  # noqa: N806
    J[:, 3] = 2.0 * J[:, 0] - J[:, 1]
    found = analyse_jacobian(J, ('p', 'q', 'r', 's'))
    assert found.rank == 3
    (combo,) = found.combinations()
    # s = 2 p - q: the direction e_s - 2 e_p + e_q (any of the three may be the dependent one).
    v = found.dependencies[0]
    assert np.allclose(J @ v, 0.0, atol=1e-10)
    assert np.isclose(abs(scipy.linalg.subspace_angles(v[:, None], np.array([[-2.0, 1.0, 0.0, 1.0]]).T)[0]), 0.0,
                      atol=1e-8)
    assert set(re.findall(r'[a-z_][a-z_.]*', combo)) == {'p', 'q', 's'}
    with pytest.raises(ValueError, match='rows for 4 parameters'):
        analyse_jacobian(J[:3], ('p', 'q', 'r', 's'))


def test_parameter_names_follow_the_table_order():
    names = parameter_names(UR5E.joint_names)
    assert names[:4] == ('shoulder_pan_joint.a', 'shoulder_pan_joint.d', 'shoulder_pan_joint.alpha',
                         'shoulder_pan_joint.offset')
    assert len(names) == 24


def test_subspace_nees_is_the_chi_square_of_the_projected_error():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 5))
    P = a @ a.T + np.eye(5)  # noqa: N806
    e = rng.normal(size=5)
    assert np.isclose(subspace_nees(e, P, np.eye(5)), e @ np.linalg.solve(P, e))
    u = np.eye(5)[:, :2]
    assert np.isclose(subspace_nees(e, P, u), e[:2] @ np.linalg.solve(P[:2, :2], e[:2]))


def test_average_nees_band_is_the_band_of_the_summed_chi_square_over_the_runs():
    from scipy.stats import chi2

    from body_schema.identifiability import average_nees_band

    assert np.allclose(average_nees_band([28]), chi2.ppf([0.025, 0.975], 28))      # one run: its own band
    lo, hi = average_nees_band([28] * 10)
    assert np.allclose((lo, hi), chi2.ppf([0.025, 0.975], 280) / 10)
    assert 23.0 < lo < 24.0 and 32.5 < hi < 33.0                                    # far narrower than 15.3-44.5
    assert np.allclose(average_nees_band([20, 36]), chi2.ppf([0.025, 0.975], 56) / 2)
    with pytest.raises(ValueError, match=r'dofs must be >= 1 and not empty, got \[\]'):
        average_nees_band([])
    with pytest.raises(ValueError, match='probability must be in'):
        average_nees_band([3], probability=1.0)


def _ur_observations(true_dh: np.ndarray, n: int, seed: int, scale: float = 1.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    qs = uniform_configs(UR5E.calibration_box, n, seed)
    poses = UR5E.with_dh(true_dh).forward_kinematics(qs)
    sig = scale * np.array([5e-4] * 3 + [np.radians(0.1)] * 3)
    noisy = poses.copy()
    for k in range(n):
        dp = rng.normal(scale=sig)
        noisy[k, :3, 3] += dp[:3]
        noisy[k, :3, :3] = scipy.linalg.expm(np.cross(np.eye(3), dp[3:])) @ poses[k, :3, :3]
    return qs, noisy, np.tile(np.diag(sig ** 2), (n, 1, 1))


def test_map_holds_the_unidentifiable_directions_at_the_initial_guess():
    rng = np.random.default_rng(5)
    widths = np.tile([0.004, 0.004, np.radians(2.0), np.radians(2.0)], 6)
    true = UR5E.dh.ravel() + rng.uniform(-0.5, 0.5, 24) * widths
    x0 = UR5E.dh.ravel()
    P0 = np.diag((np.tile([0.02, 0.02, np.radians(5.0), np.radians(5.0)], 6)) ** 2)  # noqa: N806
    null = analyse(UR5E, n=60).null_space
    qs, zs, Rs = _ur_observations(true.reshape(6, 4), 60, 2)  # noqa: N806
    settings = MapSettings(loss='linear', warmup=0)
    fixed = MapEstimator(UR5E.base, x0, P0, settings, fixed_directions=null, fixed_std=1e-6)
    fixed.solve_batch(qs, zs, Rs)
    # Nothing moved along the unidentifiable directions, and the covariance says so.
    assert np.max(np.abs(null.T @ (fixed.x - x0))) < 1e-7
    assert np.max(np.abs(null.T @ fixed.P @ null)) < 1e-11
    # The hand is still right over the box: the held directions do not move it.
    test_q = uniform_configs(UR5E.calibration_box, 50, 9)
    err = np.linalg.norm(UR5E.with_dh(fixed.table()).forward_kinematics(test_q)[:, :3, 3]
                         - UR5E.with_dh(true.reshape(6, 4)).forward_kinematics(test_q)[:, :3, 3], axis=1)
    assert err.mean() < 5e-4
    # The identifiable part is consistent (chi-square 22 dof: 99.9% bound 48.3).
    ident = analyse(UR5E, n=60).identifiable_basis
    assert ident.shape == (24, 22)
    assert subspace_nees(fixed.x - true, fixed.P, ident) < 48.3
    # Without the fixing prior the data alone would leave those directions to the wide prior.
    free = MapEstimator(UR5E.base, x0, P0, settings)
    free.solve_batch(qs, zs, Rs)
    assert np.min(np.linalg.eigvalsh(null.T @ free.P @ null)) > 1e-4


def test_map_refuses_directions_that_are_not_orthonormal():
    from body_schema.ekf import InvalidInputError
    x0 = UR5E.dh.ravel()
    with pytest.raises(InvalidInputError, match='orthonormal'):
        MapEstimator(UR5E.base, x0, np.eye(24) * 1e-4, fixed_directions=np.ones((24, 1)))
    with pytest.raises(InvalidInputError, match='fixed_std'):
        MapEstimator(UR5E.base, x0, np.eye(24) * 1e-4, fixed_directions=np.eye(24)[:, :1], fixed_std=0.0)
    with pytest.raises(InvalidInputError, match=r'fixed_std must be one or 2 finite values > 0'):
        MapEstimator(UR5E.base, x0, np.eye(24) * 1e-4, fixed_directions=np.eye(24)[:, :2], fixed_std=[1e-6])
    # One value is one per direction; the estimator keeps what it was given (the export reads it).
    one = MapEstimator(UR5E.base, x0, np.eye(24) * 1e-4, fixed_directions=np.eye(24)[:, :2], fixed_std=3e-3)
    np.testing.assert_array_equal(one.fixed_std, [3e-3, 3e-3])
