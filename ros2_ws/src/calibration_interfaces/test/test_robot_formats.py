"""The exports a robot stack reads, loaded back by independent readers written from the consumers'
own rules (ur_description's xacro, iKin's fromLinksProperties) and compared with the estimate's FK."""
import re

import numpy as np
import pytest
import yaml

from body_schema.robot import load_robot
from body_schema.sampling import perturb_dh, uniform_configs
from calibration_interfaces.robot_formats import UR_LINKS, ikin_ini, write_exports, write_ur_kinematics


def _rot(axis: str, t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    r = {'x': [[1, 0, 0], [0, c, -s], [0, s, c]], 'y': [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         'z': [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    m = np.eye(4)
    m[:3, :3] = r
    return m


def _origin(xyz, rpy) -> np.ndarray:
    """A URDF <origin>: translation, then R = Rz(yaw) Ry(pitch) Rx(roll) (URDF's fixed-axis rpy)."""
    m = _rot('z', rpy[2]) @ _rot('y', rpy[1]) @ _rot('x', rpy[0])
    m[:3, 3] = xyz
    return m


def ur_description_fk(doc: dict, q: np.ndarray) -> np.ndarray:
    """tool0 in the controller's base frame, built as ur_description's xacro builds the chain: each
    kinematics entry the <origin> of the next revolute joint (about z), then wrist_3_link -> flange
    (rpy 0 -pi/2 -pi/2) -> tool0 (rpy pi/2 0 pi/2). base_link_inertia and base are both base_link
    turned by pi about z, so the chain starts in base."""
    kin = doc['kinematics']
    t = np.eye(4)
    for name, qk in zip(UR_LINKS, q):
        e = kin[name]
        t = t @ _origin([e['x'], e['y'], e['z']], [e['roll'], e['pitch'], e['yaw']]) @ _rot('z', qk)
    return t @ _origin([0, 0, 0], [0, -np.pi / 2, -np.pi / 2]) @ _origin([0, 0, 0], [np.pi / 2, 0, np.pi / 2])


def test_the_ur_kinematics_yaml_reproduces_the_estimate_through_ur_descriptions_chain(tmp_path):
    ur = load_robot('ur5e')
    estimate = perturb_dh(ur.dh, 4, 0.004, np.radians(2.0))
    estimate[5, 0] = estimate[5, 2] = 0.0              # the flange offset the format has no place for
    path = write_ur_kinematics(tmp_path / 'ur.yaml', ur, estimate)
    doc = yaml.safe_load(path.read_text())
    assert list(doc['kinematics']) == [*UR_LINKS, 'hash'] and doc['kinematics']['hash'].startswith('calib_')
    q = uniform_configs(ur.limits, 50, np.random.default_rng(1))
    for qi in q:
        np.testing.assert_allclose(ur_description_fk(doc, qi), ur.with_dh(estimate).forward_kinematics(qi), atol=1e-9)
    # The nominal table gives ur_description's default_kinematics.yaml for the UR5e.
    nominal = yaml.safe_load(write_ur_kinematics(tmp_path / 'nominal.yaml', ur).read_text())['kinematics']
    assert nominal['shoulder']['z'] == pytest.approx(0.1625) and nominal['upper_arm']['roll'] == pytest.approx(np.pi / 2)
    assert nominal['forearm']['x'] == pytest.approx(-0.425) and nominal['wrist_1']['x'] == pytest.approx(-0.3922)
    assert nominal['wrist_1']['z'] == pytest.approx(0.1333) and nominal['wrist_2']['y'] == pytest.approx(-0.0997)
    assert nominal['wrist_3']['y'] == pytest.approx(0.0996)


def test_a_flange_offset_is_kept_beside_the_format_and_explains_the_difference(tmp_path):
    ur = load_robot('ur5e')
    estimate = perturb_dh(ur.dh, 5, 0.004, np.radians(2.0))
    doc = yaml.safe_load(write_ur_kinematics(tmp_path / 'ur.yaml', ur, estimate).read_text())
    r = doc['body_schema']['flange_residual']
    residual = _origin([r['x'], r['y'], r['z']], [r['roll'], r['pitch'], r['yaw']])
    q = np.radians([10.0, -80.0, 90.0, -190.0, -90.0, 20.0])
    np.testing.assert_allclose(ur_description_fk(doc, q) @ residual, ur.with_dh(estimate).forward_kinematics(q),
                               atol=1e-9)
    assert abs(r['x'] - estimate[5, 0]) < 1e-12


def ikin_fk(text: str, q: np.ndarray) -> np.ndarray:
    """Parse an iKin links file (key value lines, link_<i> groups of (key value) lists) and run
    standard DH, H_i = Rz(q + offset) Tz(D) Tx(A) Rx(alpha), blocked links at their angle."""
    props: dict[str, str] = {}
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if line:
            key, _, rest = line.partition(' ')
            props[key] = rest.strip()
    h0 = np.array([float(v) for v in props['H0'].strip('()').split()]).reshape(4, 4)
    t, free = h0, iter(q)
    for i in range(int(props['numLinks'])):
        group = dict((k, float(v)) for k, v in re.findall(r'\((\w+) ([-+0-9.eE]+)\)', props[f'link_{i}']))
        angle = np.radians(group['blocked']) if 'blocked' in group else next(free)
        c, s = np.cos(angle + np.radians(group.get('offset', 0.0))), np.sin(angle + np.radians(group.get('offset', 0.0)))
        al = np.radians(group.get('alpha', 0.0))
        a, d = group.get('A', 0.0), group.get('D', 0.0)
        t = t @ np.array([[c, -s * np.cos(al), s * np.sin(al), a * c], [s, c * np.cos(al), -c * np.sin(al), a * s],
                          [0, np.sin(al), np.cos(al), d], [0, 0, 0, 1]])
    return t


def test_the_ikin_file_reproduces_the_estimate_with_its_blocked_torso_and_limits(tmp_path):
    icub = load_robot('icub_right_arm')
    estimate = perturb_dh(icub.dh, 6, 0.004, np.radians(2.0))
    paths = write_exports(tmp_path, icub, estimate)
    assert [p.name for p in paths] == ['calibrated_ikin.ini']
    text = paths[0].read_text()
    assert 'numLinks 10' in text and text.count('(blocked 0.0)') == 3
    assert '(min -95.5) (max 5.0)' in text                        # r_shoulder_pitch's limits, degrees
    for qi in uniform_configs(icub.calibration_box, 50, np.random.default_rng(2)):
        np.testing.assert_allclose(ikin_fk(text, qi), icub.with_dh(estimate).forward_kinematics(qi), atol=1e-9)
    assert ikin_ini(icub) != ikin_ini(icub, estimate)


def test_the_ur_format_needs_six_joints():
    with pytest.raises(ValueError, match='6 joints'):
        write_ur_kinematics('/tmp/never.yaml', load_robot('icub_right_arm'))
