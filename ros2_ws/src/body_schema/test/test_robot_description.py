"""The robot-description loader validates fields and names the bad one."""
import copy

import numpy as np
import pytest
import yaml

import body_schema
from body_schema.robot import RobotDescriptionError, robot_path


@pytest.fixture(scope='module')
def raw():
    return yaml.safe_load(robot_path('icub_right_arm').read_text())


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
])
def test_bad_descriptions_name_the_field(tmp_path, raw, mutate, message):
    data = copy.deepcopy(raw)
    mutate(data)
    with pytest.raises(RobotDescriptionError, match=message):
        body_schema.load_robot(_write(tmp_path, data))


def test_unknown_packaged_robot():
    with pytest.raises(FileNotFoundError, match='icub_right_arm'):
        body_schema.load_robot('no_such_robot')
