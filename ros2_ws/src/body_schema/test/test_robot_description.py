"""The robot-description loader validates fields and names the bad one."""
import copy
import re

import numpy as np
import pytest
import yaml

import body_schema
from body_schema.robot import RobotDescriptionError, load_robot, robot_from_dict, robot_path


@pytest.fixture(scope='module')
def raw():
    return yaml.safe_load(robot_path('icub_right_arm').read_text())


def _bare(tmp_path, raw):
    """The iCub's description without its noise_model block (loaded from its own file)."""
    data = copy.deepcopy(raw)
    data.pop('noise_model')
    p = tmp_path / 'bare.yaml'
    p.write_text(yaml.safe_dump(data))
    return body_schema.load_robot(p)


def _write(tmp_path, data):
    p = tmp_path / 'robot.yaml'
    p.write_text(yaml.safe_dump(data))
    return p


def test_packaged_robot_loads(raw):
    arm = body_schema.load_robot('icub_right_arm')
    assert arm.joint_names[0] == 'r_shoulder_pitch' and arm.n_joints == 7 and arm.n_params == 28
    assert arm.dh.shape == (7, 4)
    np.testing.assert_allclose(np.degrees(arm.limits[1]), [0.0, 160.8])
    assert arm.within_limits(np.mean(arm.calibration_box, axis=1))
    assert arm.camera.K[0, 0] == pytest.approx(257.34)
    assert {m.name for m in arm.markers} == {'palm', 'back'}


def test_with_dh_builds_another_model():
    arm = body_schema.load_robot()
    other = arm.with_dh(arm.dh + 0.01)
    assert np.allclose(other.dh, arm.dh + 0.01) and other.joint_names == arm.joint_names
    assert not np.allclose(other.forward_kinematics(np.zeros(7)), arm.forward_kinematics(np.zeros(7)))
    with pytest.raises(RobotDescriptionError, match='NaN'):
        arm.with_dh(np.full(28, np.nan))


@pytest.mark.parametrize('mutate, message', [
    (lambda d: d['joints'][2].__setitem__('dh', [0.0, 0.1, 90.0]), r'joints\[2\] \(r_shoulder_yaw\): dh: expected shape \(4,\)'),
    (lambda d: d['joints'][0].__setitem__('limits', [5.0, -95.5]), r'joints\[0\] \(r_shoulder_pitch\)\.limits: min must be below max'),
    (lambda d: d['joints'][1].__setitem__('dh', [0.0, float('nan'), 0.0, 0.0]), r'joints\[1\].*NaN'),
    (lambda d: d.__setitem__('H0', [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), r'H0: expected shape \(4, 4\)'),
    (lambda d: d.__setitem__('angle_unit', 'grad'), r"angle_unit: must be 'deg' or 'rad'"),
    (lambda d: d['joints'][3].__setitem__('dh', [15.0, 0.0, 90.0, 0.0]), r'above 2 m .*mm'),
    (lambda d: d['calibration_box'].__setitem__(0, [-120.0, 0.0]), r'calibration_box\[0\] \(r_shoulder_pitch\)'),
    (lambda d: d.pop('joints'), r'joints: must be a non-empty list'),
    (lambda d: d['hand_markers'].__setitem__('side_length', -1), r'hand_markers\.side_length'),
    (lambda d: d.__setitem__('noise_model', {'a_pos': -1e-7}),
     r"noise_model\.a_pos: must be finite and >= 0, got -1e-07"),
    (lambda d: d.__setitem__('noise_model', {'depth_ratio': 0}),
     r"noise_model\.depth_ratio: must be finite and > 0, got 0"),
    (lambda d: d.__setitem__('noise_model', {'a_p0s': 1e-7}), r"noise_model: unknown keys \['a_p0s'\]"),
    (lambda d: d.__setitem__('noise_model', {'b_rot': 'small'}), r"noise_model\.b_rot: must be a number, got 'small'"),
    (lambda d: d.__setitem__('noise_model', [1e-7]), r'noise_model: must be a mapping'),
    (lambda d: d.__setitem__('noise_model', {'covariance': 'robust'}),
     r"noise_model\.covariance: must be one of "
     r"\['sandwich', 'sandwich_hc3', 'sandwich_blocks', 'sandwich_white', 'sandwich_white_hc2', 'sandwich_white_hc3', 'gauss_newton'\], got 'robust'"),
    (lambda d: d.__setitem__('selection', {'body_penalty': 'yes'}),
     r"selection\.body_penalty: must be true or false, got 'yes'"),
    (lambda d: d.__setitem__('selection', {'body_penalty': True, 'penalty': 0.1}),
     r"selection: must be a mapping with any of \['body_penalty', 'visibility_margin'"),
    (lambda d: d.__setitem__('selection', {'visibility_marker_widths': -0.5}),
     r'selection\.visibility_marker_widths: must be a number in \[0, 10\], got -0.5'),
    (lambda d: d.__setitem__('selection', {'visibility_margin': 'wide'}),
     r"selection\.visibility_margin: must be a number in \[-1, 10\], got 'wide'"),
])
def test_bad_descriptions_name_the_field(tmp_path, raw, mutate, message):
    data = copy.deepcopy(raw)
    mutate(data)
    with pytest.raises(RobotDescriptionError, match=message):
        body_schema.load_robot(_write(tmp_path, data))


def test_unknown_packaged_robot():
    with pytest.raises(FileNotFoundError, match='icub_right_arm'):
        body_schema.load_robot('no_such_robot')


def test_ur5e_has_a_fixed_camera_and_the_published_dh_table():
    ur = load_robot('ur5e')
    np.testing.assert_allclose(ur.dh[:, 0], [0, -0.425, -0.3922, 0, 0, 0])
    np.testing.assert_allclose(ur.dh[:, 1], [0.1625, 0, 0, 0.1333, 0.0997, 0.0996])
    np.testing.assert_allclose(ur.dh[:, 2], np.pi / 2 * np.array([1, 0, 0, 1, -1, 0]), atol=1e-12)
    assert ur.camera_names == ('left',) and ur.eyes is None
    cam = ur.camera_pose('left')
    np.testing.assert_allclose(cam[:3, 3], [-1.7, -0.13, 0.5])
    np.testing.assert_allclose(cam[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)       # looks along +x at the arm
    np.testing.assert_allclose(ur.camera_pose('left', np.zeros(5)), cam)    # no head moves it
    assert (ur.camera.width, ur.camera.height, ur.camera.fx) == (1280, 1024, 1200.0)
    with pytest.raises(RobotDescriptionError, match="no camera 'right'"):
        ur.camera_pose('right')


def test_icub_cameras_are_its_eyes_and_its_torso_is_obstacles():
    icub = load_robot('icub_right_arm')
    assert icub.camera_names == ('left', 'right') and not icub.fixed_cameras
    assert [(o.name, o.shape, o.size) for o in icub.obstacles] == [
        ('chest', 'box', (0.12, 0.15, 0.32)), ('hips', 'box', (0.10, 0.24, 0.08))]
    np.testing.assert_allclose(icub.obstacles[0].pose[:3, 3], [0.01, 0.0, 0.05])
    assert icub.obstacle_names == ('chest', 'hips', 'head')          # the head behind the eyes too
    assert icub.collision.margin == 0.02 and icub.collision.link_margin == 0.02
    assert icub.collision.allowed_pairs == (('r_shoulder_yaw_link', 'chest'), ('hand', 'r_wrist_prosup_link'))
    assert icub.exports == ('ikin',) and icub.torso.shape == (3, 4)
    # base = H0 times the blocked torso at 0
    from body_schema.kinematics import forward_kinematics
    np.testing.assert_allclose(forward_kinematics(icub.h0, icub.torso, np.zeros(3)), icub.base, atol=1e-12)


def test_ur5e_stands_on_a_table_beside_its_cameras_stand():
    ur = load_robot('ur5e')
    table, stand = ur.obstacles
    assert (table.name, table.shape, stand.name, stand.shape, stand.size) == \
        ('table', 'box', 'camera_stand', 'cylinder', (0.025, 1.2))
    assert table.pose[2, 3] + table.size[2] / 2 == pytest.approx(0.0)   # its top is the mounting plane
    assert ur.collision.margin == 0.05 and ur.collision.link_margin == 0.01 and ur.exports == ('ur_kinematics',)


@pytest.mark.parametrize('mutate, message', [
    (lambda d: d['obstacles'][0].__setitem__('shape', 'cone'), r"obstacles\[0\] \(table\)\.shape: must be one of"),
    (lambda d: d['obstacles'][1].pop('radius'), r'obstacles\[1\] \(camera_stand\)\.radius: missing'),
    (lambda d: d['obstacles'][1].__setitem__('length', -1), r'camera_stand\)\.length: must be a positive length'),
    (lambda d: d['obstacles'][0].__setitem__('size', [1, 1]), r'table\)\.size: expected shape \(3,\)'),
    (lambda d: d['obstacles'][0].pop('xyz'), r'table\)\.xyz: missing'),
    (lambda d: d['obstacles'][1].__setitem__('name', 'table'), r'obstacles: duplicate names'),
    (lambda d: d['obstacles'][1].__setitem__('name', 'hand'), r"obstacles: names \['hand'\] are taken"),
    (lambda d: d['collision'].__setitem__('margin', -0.1), r'collision\.margin: must be in \[0, 1\] m'),
    (lambda d: d['collision'].__setitem__('self_margin', 'far'), r'collision\.self_margin: must be a number'),
    (lambda d: d['collision'].__setitem__('allowed_pairs', [['hand', 'tabel']]),
     r"collision\.allowed_pairs\[0\]: unknown names \['tabel'\]"),
    (lambda d: d['collision'].__setitem__('padding', 1), r"collision: unknown keys \['padding'\]"),
    (lambda d: d.__setitem__('exports', ['urdf']), r"exports: must be a list of \['ur_kinematics', 'ikin'\]"),
])
def test_bad_obstacles_and_collision_settings_name_the_field(tmp_path, mutate, message):
    doc = yaml.safe_load(robot_path('ur5e').read_text())
    mutate(doc)
    with pytest.raises(RobotDescriptionError, match=message):
        load_robot(_write(tmp_path, doc))


def test_fixed_camera_entries_are_validated():
    doc = yaml.safe_load(robot_path('ur5e').read_text())
    doc['fixed_cameras'] = [{'name': 'left', 'xyz': [0, 0], 'rpy': [0, 0, 0]}]
    with pytest.raises(RobotDescriptionError, match=r'fixed_cameras\[0\]\.xyz: expected shape'):
        robot_from_dict(doc)
    doc['fixed_cameras'] = [{'name': 'a', 'xyz': [0, 0, 0], 'rpy': [0, 0, 0]}] * 2
    with pytest.raises(RobotDescriptionError, match='unique non-empty name'):
        robot_from_dict(doc)


def test_a_fitted_noise_law_replaces_the_defaults_it_names(tmp_path, raw):
    from body_schema.noise import PoseDependentNoise

    bare = _bare(tmp_path, raw)
    assert bare.noise_law == {}                                          # without a block: the built-in fit
    assert PoseDependentNoise.for_robot(bare) == PoseDependentNoise()
    icub = PoseDependentNoise.for_robot(body_schema.load_robot('icub_right_arm'))   # its own, with stereo ratios
    assert icub != PoseDependentNoise() and (icub.stereo_pos, icub.stereo_rot) == (0.099, 1.1)
    data = copy.deepcopy(raw)
    data['noise_model'] = {'a_pos': 3e-7, 'floor_rot': 1e-6}
    arm = body_schema.load_robot(_write(tmp_path, data))
    law = PoseDependentNoise.for_robot(arm)
    assert (law.a_pos, law.floor_rot, law.b_rot) == (3e-7, 1e-6, PoseDependentNoise().b_rot)
    assert PoseDependentNoise.for_robot(arm, a_pos=1e-5).a_pos == 1e-5          # a node parameter wins
    ur = PoseDependentNoise.for_robot(body_schema.load_robot('ur5e'))
    # The UR5e's 1280x1024 camera and 8 cm marker: far below the iCub law at its distance (1.7 m, 20 deg).
    assert ur.variances(1.7, 20.0)[1] < PoseDependentNoise().variances(1.7, 20.0)[1] / 50


def test_a_description_can_name_the_covariance_its_errors_need(tmp_path, raw):
    from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
    from body_schema.sampling import initial_covariance

    data = copy.deepcopy(raw)
    data['noise_model'] = {'a_pos': 3e-7, 'covariance': 'sandwich_hc3'}
    arm = body_schema.load_robot(_write(tmp_path, data))
    assert (arm.noise_law, arm.noise_covariance) == ({'a_pos': 3e-7}, 'sandwich_hc3')
    bare = _bare(tmp_path, raw)
    assert bare.noise_covariance == ''
    assert body_schema.load_robot('ur5e').noise_covariance == 'sandwich_hc3'

    def used(model, **kw):
        est = OnlineEstimator(model, model.dh, initial_covariance(model.n_joints), EstimatorSettings(**kw))
        return est.map.settings.covariance
    assert used(arm) == 'sandwich_hc3'                                       # the description's
    assert used(arm, covariance='gauss_newton') == 'gauss_newton'            # a parameter wins
    assert used(bare) == 'sandwich'                                          # none named: the default


def test_a_description_can_set_the_loss_scale_its_heavy_tailed_law_needs(tmp_path, raw):
    from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
    from body_schema.sampling import initial_covariance

    data = copy.deepcopy(raw)
    data['noise_model'] = {'a_pos': 3e-7, 'loss_scale': 1.2}
    arm = body_schema.load_robot(_write(tmp_path, data))
    assert (arm.noise_law, arm.noise_loss_scale) == ({'a_pos': 3e-7}, 1.2)
    bare = _bare(tmp_path, raw)
    assert bare.noise_loss_scale == 0.0
    assert body_schema.load_robot('icub_right_arm').noise_loss_scale == 1.8

    def used(model, **kw):
        est = OnlineEstimator(model, model.dh, initial_covariance(model.n_joints), EstimatorSettings(**kw))
        return est.map.settings.loss_scale
    assert used(arm) == 1.2                                                  # the description's
    assert used(arm, loss_scale=2.5) == 2.5                                  # a parameter wins
    assert used(bare) == 3.0                                                 # none set: the default
    for bad, words in ((0.05, 'must be in [0.1, 100]'), ('wide', 'must be a number')):
        data['noise_model'] = {'a_pos': 3e-7, 'loss_scale': bad}
        with pytest.raises(RobotDescriptionError, match=re.escape(f'noise_model.loss_scale: {words}')):
            body_schema.load_robot(_write(tmp_path, data))
    with pytest.raises(ValueError, match="loss_scale must be negative .* or >= 0.1, got 0.05"):
        EstimatorSettings(loss_scale=0.05)


def test_the_body_penalty_is_on_for_a_body_with_eyes_and_off_for_fixed_cameras(tmp_path, raw):
    # The iCub's root x points backward from its body; a fixed camera has no body to be behind.
    assert body_schema.load_robot('icub_right_arm').body_penalty
    assert not body_schema.load_robot('panda').body_penalty
    assert body_schema.load_robot('ur5e').body_penalty           # said so in its YAML (measured with it)
    data = copy.deepcopy(raw)
    data['selection'] = {'body_penalty': False}
    assert not body_schema.load_robot(_write(tmp_path, data)).body_penalty
    ur = yaml.safe_load(robot_path('ur5e').read_text())
    ur.pop('selection')
    assert not body_schema.load_robot(_write(tmp_path, ur)).body_penalty


def test_the_visibility_constants_come_from_the_selection_block(tmp_path, raw):
    assert body_schema.load_robot('icub_right_arm').visibility == (0.02, 0.5)     # the whole marker in view
    assert body_schema.load_robot('ur5e').visibility == (0.06, 0.0)               # the fitted fixed margin
    data = copy.deepcopy(raw)
    data['selection'] = {'visibility_marker_widths': 1}
    model = body_schema.load_robot(_write(tmp_path, data))
    assert model.visibility == (0.06, 1.0) and model.body_penalty == (model.eyes is not None)
