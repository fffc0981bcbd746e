"""The collision model: exact distances on an analytic case, sound path checks, pairs, and a selector
that never returns an unsafe target."""
import numpy as np
import pytest
import yaml

from body_schema.acquisition import JointSelector, SelectorConfig, UnsafeSelection
from body_schema.collision import CollisionModel
from body_schema.kinematics import chain_frames
from body_schema.robot import load_robot, robot_from_dict, robot_path
from body_schema.sampling import uniform_configs

UR = load_robot('ur5e')
DOWN = np.radians([0.0, -40.0, 130.0, -180.0, -90.0, 0.0])     # in the box, the wrist in the table
UP = np.radians([0.0, -100.0, 60.0, -180.0, -90.0, 0.0])


@pytest.fixture(scope='module')
def ur() -> CollisionModel:
    return CollisionModel(UR)


def test_distance_to_a_sphere_beside_the_elbow_is_the_analytic_one():
    """A 5 cm sphere 0.3 m from the elbow joint along its axis: the nearest geometry is the 2.1 cm
    joint ball (the links' 2 cm cylinders end there), so the distance is 0.3 - 0.021 - 0.05."""
    q = np.radians([10.0, -70.0, 80.0, -200.0, -90.0, 0.0])
    frames = chain_frames(UR.base, UR.dh, q)
    elbow = frames[2]                                  # frame before the elbow joint: its z is the axis
    centre = elbow[:3, 3] + 0.3 * elbow[:3, 2]
    doc = yaml.safe_load(robot_path('ur5e').read_text())
    doc['obstacles'] = [{'name': 'ball', 'shape': 'sphere', 'radius': 0.05, 'xyz': centre.tolist()}]
    doc['collision'] = {'margin': 0.0}
    model = CollisionModel(robot_from_dict(doc))
    to_ball = {pair: d for pair, d in model.pair_distances(q).items() if 'ball' in pair}
    nearest = min(to_ball, key=to_ball.get)
    assert nearest == ('ball', 'elbow_joint_link')
    assert to_ball[nearest] == pytest.approx(0.3 - 0.021 - 0.05, abs=1e-6)
    wider = {**doc, 'collision': {'margin': 0.23, 'self_margin': 0.0}}
    assert model.clear(q) and not CollisionModel(robot_from_dict(wider)).clear(q)
    assert 'ball' in CollisionModel(robot_from_dict(wider)).closest(q).pair


def test_pairs_skip_neighbours_the_allowed_and_what_always_touches(ur):
    pairs = set(ur.pairs)
    assert ('shoulder_pan_joint_link', 'table') in ur.auto_allowed      # it stands on the table
    assert not any('shoulder_pan_joint_link' in p and 'table' in p for p in pairs)
    assert ('hand', 'table') in pairs or ('table', 'hand') in pairs
    assert ('elbow_joint_link', 'hand') in pairs
    assert not any({'wrist_3_joint_link', 'hand'} == set(p) for p in pairs)   # neighbours
    icub = CollisionModel(load_robot('icub_right_arm'))
    assert not any({'r_shoulder_yaw_link', 'chest'} == set(p) for p in icub.pairs)     # the description's
    assert any({'hand', 'head'} == set(p) for p in icub.pairs) and any({'hand', 'chest'} == set(p) for p in icub.pairs)
    assert ur.margin == 0.05 and ur.self_margin == 0.01
    assert 'table' in ur.describe() and '50 mm' in ur.describe()


def test_configurations_into_the_table_are_refused(ur):
    q = DOWN                                                   # the flange below the table top
    hand = UR.forward_kinematics(q)
    assert hand[2, 3] < 0.0 and not ur.clear(q)
    assert 'table' in ur.closest(q).pair
    box = uniform_configs(UR.calibration_box, 400, np.random.default_rng(3))
    clear = ur.clear(box)
    slack = ur.slack(box)
    assert np.array_equal(clear, slack >= 0)                   # the boolean check and the distances agree
    assert 0.85 < clear.mean() < 0.99


def test_a_path_judged_clear_keeps_the_margin_everywhere_and_a_path_through_the_table_is_refused(ur):
    """Soundness against dense sampling: every path the check passes keeps every margin at 400
    evenly spaced points; every path that dips inside a margin there is refused."""
    rng = np.random.default_rng(7)
    box = uniform_configs(UR.calibration_box, 200, rng)
    starts = box[ur.clear(box, extra=ur.resolution)]
    passed = refused = 0
    for a, b in zip(starts[:-1:2][:25], starts[1::2][:25]):
        check = ur.path_clear(a, b)
        dense = ur.slack(a + np.linspace(0.0, 1.0, 401)[1:, None] * (b - a))
        if check.clear:
            passed += 1
            assert np.min(dense) >= 0.0, (a, b, np.min(dense))
        else:
            refused += 1
        if np.min(dense) < 0.0:
            assert not check.clear
    assert passed >= 10
    assert ur.clear(UP) and not ur.path_clear(UP, DOWN).clear
    blocked = ur.path_clear(UP, DOWN)
    assert blocked.samples == 1 and blocked.blocked_at == 1.0          # the target itself, found first


def test_a_path_leaving_a_margin_is_allowed_from_just_inside_it(ur):
    """The start is where the arm is (a target reached a millimetre off): a path from just inside a
    margin straight out of it passes; one that goes deeper does not."""
    lo, hi = 0.0, 1.0                                  # bisect UP -> DOWN for slack -1 mm
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ur.slack(UP + mid * (DOWN - UP)) > -0.001 else (lo, mid)
    inside = UP + lo * (DOWN - UP)
    assert -0.0015 < ur.slack(inside) < 0.0 and not ur.clear(inside)
    assert ur.path_clear(inside, UP).clear
    assert not ur.path_clear(inside, DOWN).clear


class _RefuseRight:
    """A stub safety check that refuses every configuration with the first joint above 0."""

    def __init__(self) -> None:
        self.paths = 0

    def clear(self, q):
        q = np.atleast_2d(q)
        out = q[:, 0] <= 0.0
        return bool(out[0]) if len(out) == 1 else out

    def path_clear(self, q0, q1):
        self.paths += 1
        return type('P', (), {'clear': True})()


@pytest.mark.parametrize('optimizer', ['batch', 'direct'])
def test_the_selector_returns_only_safe_targets_and_counts_what_it_refused(optimizer):
    from body_schema.acquisition import AcquisitionCost
    from body_schema.noise import PoseDependentNoise
    from body_schema.sampling import initial_covariance

    icub = load_robot('icub_right_arm')
    cost = AcquisitionCost(icub.base, icub.dh, initial_covariance(7, 0.046, np.radians(54.0)), PoseDependentNoise(),
                           icub.camera_pose('left'), icub.markers)
    box = icub.calibration_box.copy()
    box[0] = [-0.5, 0.5]                                 # half of it refused by the stub
    cfg = SelectorConfig(optimizer=optimizer, max_evals=200, seed=1)
    free = JointSelector(box, cfg).select(cost, box.mean(axis=1))
    safety = _RefuseRight()
    sel = JointSelector(box, cfg).select(cost, box.mean(axis=1), safety=safety)
    assert sel.theta[0] <= 0.0 and sel.refused_paths == 0 and safety.paths >= 1
    if free.theta[0] > 0.0:                              # the unconstrained optimum was refused
        assert sel.refused > 0 and sel.cost >= free.cost
    with pytest.raises(UnsafeSelection, match='none of the'):
        everything = type('S', (), {'clear': lambda self, q: False, 'path_clear': lambda self, a, b: None})()
        JointSelector(box, cfg).select(cost, box.mean(axis=1), safety=everything)


def test_the_random_strategy_draws_until_safe():
    box = UR.calibration_box
    safety = _RefuseRight()
    sel = JointSelector(box, SelectorConfig(strategy='random', seed=3)).select(None, box.mean(axis=1), safety=safety)
    assert sel.theta[0] <= 0.0


def test_bad_margins_are_refused():
    with pytest.raises(ValueError, match='margin'):
        CollisionModel(UR, -0.1)
    with pytest.raises(ValueError, match='resolution'):
        CollisionModel(UR, resolution=0.0)


PANDA = load_robot('panda')


def _panda_from_link1(tmp_path):
    """The Panda with base_link below its URDF's root (an arm on a pedestal): joint 1 outside the chain."""
    text = robot_path('panda').read_text().replace('base_link: panda_link0', 'base_link: panda_link1')
    # No box in the file: the six joints get their own proposal (cached after the first load).
    path = tmp_path / 'panda_from_link1.yaml'
    path.write_text(text)
    return load_robot(path)


@pytest.mark.parametrize('base_link', ['panda_link0', 'panda_link1'])
def test_a_urdf_description_is_checked_as_its_urdf_where_the_kinematics_put_it(base_link, tmp_path):
    """A description read from a URDF is checked with that URDF's collision geometry (the gripper
    beyond the tip, its fingers held at 0, and the marker's plate), every link where the
    description's kinematics (its table, its base) put it, base_link below the URDF's root too."""
    import pinocchio as pin

    from body_schema.sampling import perturb_dh

    robot = PANDA if base_link == 'panda_link0' else _panda_from_link1(tmp_path)
    dh = perturb_dh(robot.dh, 3, 0.004, np.radians(2.0))
    c = CollisionModel(robot, dh=dh, probe_configs=8)
    assert {'panda_link7', 'panda_hand', 'panda_leftfinger', 'panda_rightfinger', 'marker_plate_flange'} <= set(c.links)
    assert c.model.nq == robot.n_joints
    real = robot.with_dh(dh)
    data = c.model.createData()
    for q in uniform_configs(robot.limits, 20, seed=3):
        pin.framesForwardKinematics(c.model, data, c._pin_q(q))
        hand = c.root_T_model @ data.oMf[c.model.getFrameId('hand')].homogeneous
        np.testing.assert_allclose(hand, real.forward_kinematics(q), atol=1e-9)
        plate = c.root_T_model @ data.oMf[c.model.getFrameId('marker_plate_flange')].homogeneous
        np.testing.assert_allclose(plate, real.forward_kinematics(q) @ robot.markers[0].hand_T_marker, atol=1e-9)


def test_a_marker_plate_held_past_the_gripper_is_kept_off_the_table():
    """The Panda's marker plate, 12 cm past the flange: a configuration that puts it (and nothing
    else) within the margin of the table is refused, with the plate named as the closest pair."""
    c = CollisionModel(PANDA, probe_configs=16)
    for q in uniform_configs(PANDA.limits, 3000, seed=5):
        d = c.pair_distances(q)
        others = [v - (c.margin if 'table' in k else c.self_margin) for k, v in d.items()
                  if k != ('marker_plate_flange', 'table')]
        if d[('marker_plate_flange', 'table')] < c.margin - 0.01 and min(others) > 0.005:
            break
    else:
        pytest.fail('no configuration with the plate alone near the table')
    assert not c.clear(q)
    assert c.closest(q).pair == ('marker_plate_flange', 'table')


def test_meshes_are_checked_as_their_convex_hulls():
    """A mesh link is its convex hull (read as a convex shape, the mesh's own triangles missed a
    wrist link 6 cm inside the table): a link whose vertices lie on both sides of the table's
    top inside its outline is in contact with it."""
    import coal
    import pinocchio as pin

    c = CollisionModel(PANDA, margin=0.0, self_margin=0.0, probe_configs=0)
    table = next(o for o in c.obstacles if o.name == 'table')
    half = np.asarray(table.size) / 2
    data = pin.GeometryData(c.geometry)
    crossing = 0
    for q in uniform_configs(PANDA.limits, 300, seed=4):
        pin.updateGeometryPlacements(c.model, c._data, c.geometry, data, c._pin_q(q))
        d = c.pair_distances(q)
        for k, g in enumerate(c.geometry.geometryObjects):
            if not g.name.startswith('panda_link') or g.name.startswith('panda_link0'):
                continue
            assert isinstance(g.geometry, coal.ConvexBase)
            pts = np.asarray(g.geometry.points())
            world = pts @ data.oMg[k].rotation.T + data.oMg[k].translation
            local = (world - table.pose[:3, 3]) @ table.pose[:3, :3]     # in the table's frame
            inside = np.all(np.abs(local[:, :2]) < half[:2], axis=1)
            if inside.all() and local[:, 2].min() < -half[2] / 2 and local[:, 2].max() > half[2] / 2:
                crossing += 1
                assert d[tuple(sorted((g.name.rsplit('_', 1)[0], 'table')))] <= 0.0, g.name
    assert crossing >= 5
