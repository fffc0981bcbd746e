"""Planner: strategies run on an estimate, outcomes teach the occlusion model, movement adds up."""
import numpy as np
import pytest

import body_schema
from active_selector.planner import Planner, PlannerSettings
from body_schema import sampling
from body_schema.acquisition import SelectorConfig
from body_schema.noise import PoseDependentNoise

ARM = body_schema.load_robot()


@pytest.mark.parametrize('strategy', ['random', 'al', 'ucsal', 'ccsal'])
def test_select_and_record(strategy):
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy=strategy, max_evals=200)))
    with pytest.raises(RuntimeError, match='start'):
        pl.select(ARM.dh, sampling.initial_covariance(7), ARM.camera_pose())
    pl.start = np.mean(ARM.calibration_box, axis=1)
    sel = pl.select(ARM.dh, sampling.initial_covariance(7), ARM.camera_pose())
    assert ARM.within_limits(sel.theta)
    a = pl.record(sel.theta, sel.theta, 'failed', False, sel.seconds)
    assert a.movement_deg == pytest.approx(np.degrees(np.abs(sel.theta - pl.start).sum()))
    assert pl.discarded == 1 and pl.occlusion.n_configs == 1
    assert pl.occlusion.mean(sel.theta) < 0.5                 # the failure was learned
    b = pl.record(sel.theta, pl.start, 'accepted', True, 0.0)
    assert b.movement_deg == pytest.approx(2 * a.movement_deg)
    assert pl.previous is not None and np.array_equal(pl.previous, pl.start)


@pytest.mark.parametrize('criterion', ['a_optimal', 'v_optimal'])
def test_planner_never_revisits_and_passes_the_new_modes(criterion):
    settings = PlannerSettings(SelectorConfig(strategy='al', optimizer='batch', n_candidates=256, seed=4),
                               occlusion_mode='gain', criterion=criterion, box_samples=32,
                               occlusion_prior='flat')   # the geometric prior's weight learns from history
    pl = Planner(ARM, PoseDependentNoise(), settings)
    pl.start = np.mean(ARM.calibration_box, axis=1)
    P = sampling.initial_covariance(7)
    cost = pl.cost(ARM.dh, P, ARM.camera_pose())
    assert cost.criterion == criterion and cost.occlusion_mode == 'gain'
    assert pl.box_configs.shape == (32, 7)
    first = pl.select(ARM.dh, P, ARM.camera_pose())
    assert first.optimizer == 'batch:BOBYQA'
    # A fresh planner (same seed, same candidates) that has visited `first` but learned nothing
    # from it would pick `first` again were it not for the visited list.
    again = Planner(ARM, PoseDependentNoise(), settings)
    again.start = pl.start
    again.record(first.theta, first.theta, 'failed', False, first.seconds)
    again.occlusion = Planner(ARM, PoseDependentNoise(), settings).occlusion
    assert again.visited.shape == (2, 7)
    second = again.select(ARM.dh, P, ARM.camera_pose())
    assert second.excluded >= 1
    assert np.max(np.abs(second.theta - first.theta)) > settings.selector.repeat_tolerance


def test_box_samples_must_be_a_power_of_two():
    with pytest.raises(ValueError, match='box_samples.*100'):
        PlannerSettings(box_samples=100)


def test_occlusion_prior_setting_reaches_the_cost():
    geo = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='geometric'))
    flat = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='flat'))
    P = sampling.initial_covariance(7)
    assert geo.cost(ARM.dh, P, ARM.camera_pose()).visibility.camera == ARM.camera
    assert flat.cost(ARM.dh, P, ARM.camera_pose()).visibility is None
    q = sampling.uniform_configs(ARM.calibration_box, 32, 3)
    eta_flat = flat.cost(ARM.dh, P, ARM.camera_pose()).terms_batch(q)[1]
    np.testing.assert_allclose(eta_flat, 1.0 / 3.0)            # Be(1, 2) without data
    assert np.ptp(geo.cost(ARM.dh, P, ARM.camera_pose()).terms_batch(q)[1]) > 0.1
    with pytest.raises(ValueError, match="occlusion_prior must be one of .* got 'sharp'"):
        PlannerSettings(occlusion_prior='sharp')


def test_visibility_constants_come_from_the_description_unless_set():
    v = Planner(ARM, PoseDependentNoise()).visibility
    assert (v.margin, v.margin_marker_widths, v.marker_side) == (0.02, 0.5, ARM.marker_side_length)   # the iCub's
    fixed = Planner(ARM, PoseDependentNoise(), PlannerSettings(visibility_margin=0.06,
                                                               visibility_marker_widths=0.0)).visibility
    assert (fixed.margin, fixed.margin_marker_widths, fixed.marker_side) == (0.06, 0.0, None)
    ur5e = body_schema.load_robot('ur5e')
    assert Planner(ur5e, PoseDependentNoise()).visibility_constants == (0.06, 0.0)


def test_eye_correlation_reaches_a_stereo_cost():
    planner = Planner(ARM, PoseDependentNoise(), PlannerSettings(eye_correlation=0.3))
    pair = np.stack([ARM.camera_pose('left'), ARM.camera_pose('right')])
    cost = planner.cost(ARM.dh, sampling.initial_covariance(7), pair)
    assert cost.eye_correlation == 0.3 and cost.terms_batch(ARM.calibration_box.mean(1)[None])[0].shape == (1,)


def test_each_eye_learns_its_own_verdicts():
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_per_eye=True), eyes=('left', 'right'))
    pl.start = np.mean(ARM.calibration_box, axis=1)
    q = sampling.uniform_configs(ARM.calibration_box, 4, 3)
    pl.record(q[0], q[0], 'accepted', True, 0.0, eyes={'left': False, 'right': True})
    pl.record(q[1], q[1], 'failed', False, 0.0)                        # no eye saw it: both learn
    pl.record(q[2], q[2], 'accepted', True, 0.0)                       # which eye saw it is unknown
    pl.record(q[3], q[3], 'failed', False, 0.0, eyes={'left': False})  # the right eye was not judged
    left, right = (pl.eye_occlusion[e].attempts for e in ('left', 'right'))
    assert left[1].tolist() == [False, False, False] and right[1].tolist() == [True, False]
    np.testing.assert_allclose(left[0], q[[0, 1, 3]])
    assert pl.occlusion.attempts[1].tolist() == [True, False, True, False]      # the pair's, unchanged
    # The cost plans with them: the untaught right eye's geometric weight is 0.5, the left's from its attempts.
    pair = np.stack([ARM.camera_pose('left'), ARM.camera_pose('right')])
    cost = pl.cost(ARM.dh, sampling.initial_covariance(7) * 1e-4, pair)
    assert cost.eye_occlusion == (pl.eye_occlusion['left'], pl.eye_occlusion['right'])
    assert cost.eye_visibility_weights[0] != 0.5 and cost.visibility_weight == 1.0
    # One camera, or the setting off: the pair's model alone.
    assert pl.cost(ARM.dh, sampling.initial_covariance(7), ARM.camera_pose()).eye_occlusion is None
    off = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_per_eye=False), eyes=('left', 'right'))
    assert off.eye_occlusion == {} and off.cost(ARM.dh, sampling.initial_covariance(7), pair).eye_occlusion is None
    assert pl.eye_occlusion['left'].length_scale == 0.2 and pl.occlusion.length_scale == 0.5
    assert not Planner(ARM, PoseDependentNoise(), eyes=('left', 'right')).eye_occlusion, 'off by default'
    with pytest.raises(ValueError, match="eyes must name.*'left', 'left'"):
        Planner(ARM, PoseDependentNoise(), eyes=('left', 'left'))


def test_geometric_prior_loses_weight_when_its_predictions_fail():
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='geometric'))
    pl.start = np.mean(ARM.calibration_box, axis=1)
    P = sampling.initial_covariance(7) * 1e-4                   # a confident estimate
    assert pl.cost(ARM.dh, P, ARM.camera_pose()).visibility_weight == 0.5
    q = sampling.uniform_configs(ARM.calibration_box, 64, 2)
    p = pl.cost(ARM.dh, P, ARM.camera_pose()).visibility_probability(q)
    likely = q[np.argsort(p)[-3:]]                              # where geometry expects the hand
    for theta in likely:
        pl.record(theta, theta, 'failed', False, 0.0)
    assert pl.cost(ARM.dh, P, ARM.camera_pose()).visibility_weight < 0.05
    right = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='geometric'))
    right.start = pl.start
    for theta in likely:
        right.record(theta, theta, 'accepted', True, 0.0)
    assert right.cost(ARM.dh, P, ARM.camera_pose()).visibility_weight > 0.8


def test_the_cost_is_computed_on_the_covariance_the_next_update_starts_from():
    """The paper's C0 is the expected trace after the next update, which starts from P + Q."""
    P = sampling.initial_covariance(7) * 1e-3
    plain = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='flat')).cost(ARM.dh, P, ARM.camera_pose())
    np.testing.assert_array_equal(plain.P, P)
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(occlusion_prior='flat', criterion='a_optimal',
                                                            q_length=1e-8, q_angle=4e-6))
    cost = pl.cost(ARM.dh, P, ARM.camera_pose())
    np.testing.assert_allclose(cost.P - P, np.diag(np.tile([1e-8, 1e-8, 4e-6, 4e-6], 7)), atol=1e-20)
    assert cost.uncertainty == pytest.approx(np.trace(P) + 7 * (2e-8 + 8e-6))
    with pytest.raises(ValueError, match='q_angle -1'):
        PlannerSettings(q_angle=-1.0)


class _Refuse:
    """A safety check refusing configurations whose first joint is above ``limit`` [rad]."""

    def __init__(self, limit: float) -> None:
        self.limit = limit

    def clear(self, q):
        q = np.atleast_2d(q)
        out = q[:, 0] <= self.limit
        return bool(out[0]) if len(out) == 1 else out

    def path_clear(self, q0, q1):
        return type('P', (), {'clear': True})()


def test_a_pose_list_comes_first_unsafe_poses_are_skipped_then_the_strategy_selects():
    safety = _Refuse(np.radians(-40.0))
    pl = Planner(ARM, PoseDependentNoise(), PlannerSettings(SelectorConfig(strategy='al', n_candidates=64)),
                 safety=safety)
    pl.start = np.mean(ARM.calibration_box, axis=1)
    good = pl.start.copy()
    good[0] = np.radians(-50.0)
    bad = pl.start.copy()
    bad[0] = np.radians(-30.0)                             # beyond the stub's -40 deg: refused
    pl.queue_poses([good, bad, good + 0.01])
    P, cam = sampling.initial_covariance(7), ARM.camera_pose()
    first = pl.select(ARM.dh, P, cam)
    assert first.optimizer == 'pose_list[0]' and np.array_equal(first.theta, good)
    second = pl.select(ARM.dh, P, cam)
    assert second.optimizer == 'pose_list[2]' and second.refused == 1
    assert pl.skipped == [(1, 'inside a collision margin')]
    third = pl.select(ARM.dh, P, cam)
    assert third.optimizer.startswith('batch') and third.theta[0] <= np.radians(-40.0)
    with pytest.raises(ValueError, match='outside the joint limits'):
        pl.queue_poses([ARM.limits[:, 1] + 0.1])


def test_plan_picks_distinct_safe_poses_shrinks_the_covariance_and_leaves_the_history():
    safety = _Refuse(np.radians(-40.0))
    settings = PlannerSettings(SelectorConfig(strategy='al', n_candidates=64, seed=2), box_samples=32)
    pl = Planner(ARM, PoseDependentNoise(), settings, safety=safety)
    pl.start = np.mean(ARM.calibration_box, axis=1)
    P = sampling.initial_covariance(7)
    plan = pl.plan(ARM.dh, P, ARM.camera_pose(), 4)
    q = np.array([s.theta for s in plan])
    assert q.shape == (4, 7) and np.all(q[:, 0] <= np.radians(-40.0))
    assert min(np.max(np.abs(a - b)) for i, a in enumerate(q) for b in q[i + 1:]) > 2e-3   # no repeats
    assert pl.history == [] and pl.movement_deg == 0.0
    cost = pl.cost(ARM.dh, P, ARM.camera_pose())
    after = cost.posterior(q[0])
    assert np.trace(after) < np.trace(P) and np.all(np.linalg.eigvalsh(after) > 0)


def test_the_body_penalty_applies_only_where_the_description_has_a_body():
    # The Panda's camera is at +x: a*arctan(b*p_x) would reward hands turned away from it (a run
    # with it discarded 40 of 50 attempts at one corner behind the base).
    panda = body_schema.load_robot('panda')
    P = sampling.initial_covariance(panda.n_joints)
    settings = PlannerSettings(SelectorConfig(strategy='al'), penalty_a=0.05)
    assert Planner(panda, PoseDependentNoise(), settings).cost(panda.dh, P, panda.camera_pose('left')).penalty_a == 0.0
    assert Planner(ARM, PoseDependentNoise(), settings).cost(ARM.dh, P, ARM.camera_pose()).penalty_a == 0.05


def test_the_planned_eyes_follow_the_description_and_the_extrinsics():
    from active_selector.node_settings import SelectorNodeSettings

    assert SelectorNodeSettings(use_right_eye=True).planned_eyes(ARM) == ('left', 'right')
    assert SelectorNodeSettings(use_right_eye=False, eye='right').planned_eyes(ARM) == ('right',)
    assert SelectorNodeSettings(use_right_eye=True).planned_eyes(body_schema.load_robot('ur5e')) == ('left',)
    # A "0" prior estimates nothing; a real one is one camera's correction.
    assert SelectorNodeSettings(use_right_eye=True, camera_prior='0').planned_eyes(ARM) == ('left', 'right')
    with pytest.raises(ValueError, match='use_right_eye cannot be combined with camera_prior'):
        SelectorNodeSettings(use_right_eye=True, marker_prior='0.005 5').planned_eyes(ARM)
