"""Pose lists: written and read back in the description's joint order, bad files name the field."""
import numpy as np
import pytest

from body_schema.robot import load_robot
from calibration_interfaces.pose_list import PoseListError, parse_pose_list, read_pose_list, write_pose_list

UR = load_robot('ur5e')


def test_round_trip_and_any_joint_order(tmp_path):
    q = UR.calibration_box.mean(axis=1) + np.radians([[1, 2, 3, 4, 5, 6], [-6, -5, -4, -3, -2, -1]])
    path = write_pose_list(tmp_path / 'p.yaml', UR, q, {'note': 'kept'}, comment='two poses')
    back = read_pose_list(path, UR)
    np.testing.assert_allclose(back.positions, q, atol=1e-8)
    assert back.extra['note'] == 'kept' and path.read_text().startswith('# two poses')
    names = list(reversed(UR.joint_names))
    doc = {'angle_unit': 'rad', 'joint_names': names, 'poses': [list(reversed(q[0]))]}
    np.testing.assert_allclose(parse_pose_list(doc, UR).positions[0], q[0])


@pytest.mark.parametrize('doc, message', [
    ({'joint_names': ['a'], 'poses': [[0.0]]}, 'joint_names: must name each of'),
    ({'poses': []}, 'poses: must be a non-empty list'),
    ({'poses': [[0.0, 0.0]]}, r'every pose must be 6 numbers, got shape \(1, 2\)'),
    ({'angle_unit': 'deg', 'poses': [[0.0, 0.0, 0.0, 0.0, 0.0, 400.0]]}, r'poses\[0\]: outside the joint limits'),
    ({'angle_unit': 'grad', 'poses': [[0.0] * 6]}, "angle_unit: must be 'deg' or 'rad'"),
])
def test_bad_pose_lists_name_the_field(doc, message):
    with pytest.raises(PoseListError, match=message):
        parse_pose_list(doc, UR, 'f.yaml')


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(PoseListError, match='does not exist'):
        read_pose_list(tmp_path / 'none.yaml', UR)
