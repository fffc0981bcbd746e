"""Wrong basins of the MAP estimator: exact twins of a DH chain (angles modulo 2 pi, inner frames
turned by pi, a free marker taking the flange's turn) and the move to the twin nearest the prior;
a far guess's wrong basin and the restart from the prior mean."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from body_schema import kinematics, load_robot, sampling
from body_schema.extrinsics import Extrinsics, absorbed_parameters
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.noise import PoseDependentNoise
from body_schema.synthetic import SyntheticRun

UR5E = load_robot('ur5e')
ICUB = load_robot()
CAM = UR5E.camera_pose('left')
MARKER = UR5E.markers[0].hand_T_marker
BOTH = Extrinsics(CAM, MARKER, (0.02, np.radians(2.0)), (0.005, np.radians(5.0)))


@pytest.mark.parametrize('arm', [UR5E, ICUB], ids=['ur5e', 'icub'])
def test_every_twin_table_moves_the_hand_exactly_as_the_table(arm):
    dh = sampling.perturb_dh(arm.dh, 3)
    tables, turns = kinematics.twin_tables(dh)
    assert tables.shape == (2 ** (len(dh) - 1), len(dh), 4) and turns.shape == (len(tables), len(dh) - 1)
    np.testing.assert_array_equal(tables[0], dh)
    assert len({tuple(t) for t in turns}) == len(turns)
    q = sampling.uniform_configs(arm.limits, 20, 0)
    ref = kinematics.forward_kinematics(arm.base, dh, q)
    for t in tables:
        np.testing.assert_allclose(kinematics.forward_kinematics(arm.base, t, q), ref, atol=1e-12)
    # A turned frame negates its link's a and alpha: the twins differ from the table.
    assert np.all(np.any(np.abs(tables[1:] - dh) > 1.0, axis=(1, 2)))
    singles, single_turns = kinematics.twin_tables(dh, max_turned=2)
    assert len(singles) == len(dh) and np.all(single_turns.sum(axis=1) == np.r_[0, np.ones(len(dh) - 1)])
    with pytest.raises(ValueError, match=r'a table of shape \(L, 4\) needed, got \(4,\)'):
        kinematics.twin_tables(dh[0])


def _estimator(x0: np.ndarray, settings: MapSettings = MapSettings()) -> MapEstimator:
    """A UR5e estimate with both extrinsics free and the parameters they absorb held, as the node holds them."""
    n = x0.size
    held = absorbed_parameters(6, camera=True, marker=True)
    v = np.zeros((n, len(held)))
    v[list(held), range(len(held))] = 1.0
    P0 = np.diag(np.r_[np.diag(sampling.initial_covariance(6)), BOTH.prior_std() ** 2])  # noqa: N806
    return MapEstimator(UR5E.base, x0, P0, settings, limits=UR5E.limits, fixed_directions=v, extrinsics=BOTH)


def _twin_of(est: MapEstimator, x: np.ndarray) -> np.ndarray:
    """``x`` with the last inner frame turned (the marker takes the flange's turn) and two angles
    a turn or two away: what the Panda's seed-6 run settled on."""
    xs = est.twins(x)
    tables, turns = kinematics.twin_tables(est.table(x))
    pick = int(np.flatnonzero((turns[:, -1] == 1) & (turns.sum(axis=1) == 2))[0])
    far = xs[pick].copy()
    far[2] += 4 * np.pi                                  # alpha_0 two turns on
    far[4 * 2 + 3] -= 2 * np.pi                          # offset_2 a turn back
    return far


def test_twins_of_an_estimate_predict_the_same_hand_poses():
    x = np.r_[sampling.perturb_dh(UR5E.dh, 5).ravel(), 0.01, -0.005, 0.003, 0.02, -0.01, 0.015,
              0.002, 0.001, -0.003, 0.05, -0.04, 0.03]
    est = _estimator(x)
    q = sampling.uniform_configs(UR5E.limits, 15, 1)
    ref = est._model(x, q, jacobian=False)[0]
    xs = est.twins(x)
    assert len(xs) == 32
    for row in np.vstack([xs, _twin_of(est, x)]):
        np.testing.assert_allclose(est._model(row, q, jacobian=False)[0], ref, atol=1e-9)
    cost = est.prior_cost(xs)
    assert int(np.argmin(cost)) == 0 and np.all(cost[1:] > cost[0] + 100.0)


@pytest.mark.parametrize('twins', [True, False])
def test_an_estimate_on_a_twin_moves_back_to_the_prior_branch(twins):
    """Started on a twin of the truth, the estimate ends where a run started at its prior ends;
    without the move it stays on the twin, its flange half a turn off."""
    true = sampling.perturb_dh(UR5E.dh, 1000, 0.002, np.radians(1.0))
    held = list(absorbed_parameters(6, True, True))
    x0 = np.r_[sampling.perturb_dh(UR5E.dh, 7, 0.004, np.radians(2.0)).ravel(), np.zeros(12)]
    x0[held] = true.ravel()[held]
    obs = SyntheticRun(UR5E, true, PoseDependentNoise(), 2)(12)
    plain, est = _estimator(x0), _estimator(x0, MapSettings(twins=twins))
    est.x = _twin_of(est, np.r_[true.ravel(), np.zeros(12)])
    for o in obs:
        plain.update(o.q, o.pose, o.R)
        est.update(o.q, o.pose, o.R)
    assert plain.n_twin_moves == 0
    q = sampling.uniform_configs(UR5E.limits, 200, 2)
    flange = kinematics.forward_kinematics(UR5E.base, est.table(), q)
    truth = kinematics.forward_kinematics(UR5E.base, true, q)
    turn = np.min(kinematics.rotation_angle_deg(flange[:, :3, :3], truth[:, :3, :3]))
    if twins:
        assert est.n_twin_moves >= 1 and turn < 10.0
        np.testing.assert_allclose(est.x, plain.x, atol=1e-6)
    else:
        assert est.n_twin_moves == 0 and turn > 170.0


def test_an_ordinary_run_never_moves():
    true = sampling.perturb_dh(UR5E.dh, 1001, 0.004, np.radians(2.0))
    est = _estimator(np.r_[sampling.perturb_dh(UR5E.dh, 3).ravel(), np.zeros(12)])
    for o in SyntheticRun(UR5E, true, PoseDependentNoise(), 4)(30):
        est.update(o.q, o.pose, o.R)
    assert est.n_twin_moves == 0
    state = est.state_dict()
    assert int(state['map_n_twin_moves']) == 0
    del state['map_n_twin_moves']                        # a checkpoint without the count still loads
    other = _estimator(np.r_[sampling.perturb_dh(UR5E.dh, 3).ravel(), np.zeros(12)])
    other.load_state_dict(state)
    np.testing.assert_array_equal(other.x, est.x)


def _far_guess_run(settings: MapSettings):
    """A rendered Panda AL run (seed 6, camera and marker estimated) from a guess 442 mm / 61 deg
    off, re-fed from its recorded observations (45 detections, in order)."""
    d = np.load(Path(__file__).parent / 'data' / 'panda_far_guess_run.npz')
    ex = Extrinsics(d['camera'], d['marker'], tuple(d['camera_std']), tuple(d['marker_std']))
    est = MapEstimator(d['base'], d['x0'], d['P0'], settings, limits=d['limits'],
                       fixed_directions=d['fixed_directions'], fixed_std=d['fixed_std'], extrinsics=ex)
    outliers = [est.update(q, z, R).outlier for q, z, R in zip(d['qs'], d['zs'], d['Rs'])]
    return est, outliers, d


@pytest.mark.parametrize('restart_after', [3, 0])
def test_a_far_guess_leaves_its_wrong_basin_by_a_restart(restart_after):
    """The first observation leads the warm-started solver into a wrong basin; every later one is
    an outlier there. Three in a row and the cold solve from the prior mean, with its lower
    objective, is kept: a handful of outliers instead of the whole run."""
    settings = replace(MapSettings(covariance='sandwich_hc3'), restart_after=restart_after)
    est, outliers, d = _far_guess_run(settings)
    if restart_after:
        assert est.n_restarts >= 1 and sum(outliers) <= 5 and not any(outliers[-8:])
        assert np.all(est.residual_chi2()[-8:] < 20.0)     # the last ones explained to their noise
    else:
        assert est.n_restarts == 0 and sum(outliers) > 30


def test_a_restart_is_refused_when_it_does_not_lower_the_objective():
    """A solve from the prior mean that ends no lower is thrown away: the state is that of an
    estimator that never tries one."""
    true = sampling.perturb_dh(UR5E.dh, 1002, 0.004, np.radians(2.0))
    x0 = np.r_[sampling.perturb_dh(UR5E.dh, 3).ravel(), np.zeros(12)]
    est, never = _estimator(x0, MapSettings(restart_after=1)), _estimator(x0, MapSettings(restart_after=0))
    obs = SyntheticRun(UR5E, true, PoseDependentNoise(), 5)(15)
    bad = obs[0].pose.copy()
    bad[:3, 3] += 0.3                                    # a gross detection error: an outlier
    for e in (est, never):
        for o in obs:
            e.update(o.q, o.pose, o.R)
        u = e.update(obs[1].q + 0.01, bad, obs[0].R)
        assert u.outlier and not u.restart
    assert est.n_restarts == 0
    np.testing.assert_array_equal(est.x, never.x)
    np.testing.assert_array_equal(est.P, never.P)
    with pytest.raises(ValueError, match='restart_after must be >= 0, got -1'):
        MapSettings(restart_after=-1)


def test_the_objective_is_what_the_solver_minimises():
    """``objective`` is scipy's cost: at the solution no twin or restart undercuts it, and it is
    0.5 scale^2 sum rho over every row, the prior's too."""
    true = sampling.perturb_dh(UR5E.dh, 1003, 0.004, np.radians(2.0))
    est = _estimator(np.r_[sampling.perturb_dh(UR5E.dh, 3).ravel(), np.zeros(12)])
    for o in SyntheticRun(UR5E, true, PoseDependentNoise(), 6)(12):
        est.update(o.q, o.pose, o.R)
    f = est.objective(est.x)
    for step in (1e-4, -1e-4):
        moved = est.x.copy()
        moved[5] += step
        assert est.objective(moved) > f
    z = (np.r_[est._prior_rows(est.x), est._whitened(est.x).ravel()] / 3.0) ** 2
    assert f == pytest.approx(0.5 * 9.0 * np.sum(np.log1p(z)))
