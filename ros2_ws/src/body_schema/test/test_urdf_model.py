"""Descriptions from a URDF and from a modified-DH table: the derived standard table against two
independent readers (Pinocchio to 1e-9 m, PyBullet to its single precision), Franka's MDH table
against the Panda URDF, the parallel / intersecting / nearly parallel cases, the calibrated URDF."""
from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml

from body_schema import kinematics
from body_schema.identifiability import analyse
from body_schema.modified_dh import modified_forward_kinematics, modified_to_standard, standard_to_modified
from body_schema.robot import RobotDescriptionError, load_robot, robot_from_dict, robot_path
from body_schema.urdf import dh_chain_urdf
from body_schema.urdf_model import (NearlyParallelAxesWarning, UrdfDescriptionError, calibrated_urdf, derive_dh,
                                    urdf_chain)

pybullet_data = pytest.importorskip('pybullet_data')
DATA = Path(pybullet_data.getDataPath())
ARMS = {'panda': (DATA / 'franka_panda' / 'panda.urdf', 'panda_link0', 'panda_link8'),
        'kuka_iiwa': (DATA / 'kuka_iiwa' / 'model.urdf', 'lbr_iiwa_link_0', 'lbr_iiwa_link_7')}


def _configs(limits: np.ndarray, n: int = 1000, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(limits[:, 0], limits[:, 1], (n, len(limits)))


def _pinocchio_tip(path: Path, base: str, tip: str, names: tuple[str, ...], q: np.ndarray) -> np.ndarray:
    """``tip`` in ``base`` by Pinocchio's URDF reader, (N, 4, 4)."""
    pin = pytest.importorskip('pinocchio')
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    fb, ft = model.getFrameId(base), model.getFrameId(tip)
    idx = [model.joints[model.getJointId(n)].idx_q for n in names]
    out = []
    for qq in q:
        qp = pin.neutral(model)
        qp[idx] = qq
        pin.framesForwardKinematics(model, data, qp)
        out.append((data.oMf[fb].inverse() * data.oMf[ft]).homogeneous)
    return np.array(out)


def _pybullet_tip(path: Path, tip: str, names: tuple[str, ...], q: np.ndarray) -> np.ndarray:
    """``tip`` in the fixed base's link frame by PyBullet, (N, 4, 4)."""
    import pybullet as pb

    c = pb.connect(pb.DIRECT)
    try:
        body = pb.loadURDF(str(path), useFixedBase=True, physicsClientId=c)
        info = [pb.getJointInfo(body, i, physicsClientId=c) for i in range(pb.getNumJoints(body, physicsClientId=c))]
        joint = {i[1].decode(): i[0] for i in info}
        link = {i[12].decode(): i[0] for i in info}
        out = []
        for qq in q:
            for name, v in zip(names, qq):
                pb.resetJointState(body, joint[name], v, physicsClientId=c)
            s = pb.getLinkState(body, link[tip], computeForwardKinematics=True, physicsClientId=c)
            t = np.eye(4)
            t[:3, :3] = np.array(pb.getMatrixFromQuaternion(s[5])).reshape(3, 3)
            t[:3, 3] = s[4]
            out.append(t)
        return np.array(out)
    finally:
        pb.disconnect(c)


@pytest.mark.parametrize('robot', sorted(ARMS))
def test_the_derived_table_moves_the_tip_as_two_independent_urdf_readers_do(robot: str) -> None:
    path, base, tip = ARMS[robot]
    model = load_robot(robot)
    assert model.joint_names == urdf_chain(path, base, tip).joint_names
    assert model.root_frame == base and model.urdf is not None and model.urdf.tip_link == tip
    q = _configs(model.limits)
    ours = model.flange_pose(q)
    # Pinocchio computes in double precision: the derived table is exact.
    assert np.abs(ours - _pinocchio_tip(path, base, tip, model.joint_names, q)).max() < 1e-9
    # PyBullet reports link states in single precision (measured: 5.4e-7 Panda, 4.9e-7 iiwa).
    assert np.abs(ours - _pybullet_tip(path, tip, model.joint_names, q)).max() < 2e-6


def test_franka_mdh_table_gives_the_panda_urdf_kinematics() -> None:
    urdf, mdh = load_robot('panda'), load_robot('panda_mdh')
    assert mdh.convention == 'modified' and mdh.joint_names == urdf.joint_names
    q = _configs(mdh.limits)
    # pybullet_data's panda.urdf writes pi/2 as 1.57079632679 (5e-12 rad off): measured 2.1e-11 m.
    assert np.abs(mdh.flange_pose(q) - urdf.flange_pose(q)).max() < 1e-10
    doc = yaml.safe_load(robot_path('panda_mdh').read_text())
    rows = np.array([j['dh'] for j in doc['joints']], dtype=float)
    rows[:, 2:] = np.radians(rows[:, 2:])
    flange = np.array(doc['flange'], dtype=float)
    reference = np.array([modified_forward_kinematics(rows, qq, flange) for qq in q[:50]])
    assert np.allclose(mdh.flange_pose(q[:50]), reference, atol=1e-12)
    back, back_flange = mdh.modified_table()
    assert np.allclose(back, rows, atol=1e-15) and np.allclose(back_flange, flange, atol=1e-15)


def test_modified_regrouping_is_exact_and_its_inverse_is_exact() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        rows = np.column_stack([rng.normal(0, 0.2, 6), rng.normal(0, 0.2, 6), rng.uniform(-np.pi, np.pi, 6),
                                rng.uniform(-np.pi, np.pi, 6)])
        flange = np.array([rng.normal(0, 0.1), rng.normal(0, 0.1), rng.uniform(-1, 1), rng.uniform(-1, 1)])
        dh, pre, tool = modified_to_standard(rows, flange)
        q = rng.uniform(-np.pi, np.pi, 6)
        assert np.allclose(pre @ kinematics.forward_kinematics(np.eye(4), dh, q) @ tool,
                           modified_forward_kinematics(rows, q, flange), atol=1e-12)
        back, back_flange = standard_to_modified(dh, (rows[0, 0], rows[0, 2]), (flange[1], flange[3]))
        assert np.allclose(back, rows) and np.allclose(back_flange, flange)


def _ur5e_urdf(tmp_path: Path, dh: np.ndarray | None = None) -> Path:
    """The UR5e's table written as a URDF (fixed offset / dh joints between revolute ones)."""
    ur = load_robot('ur5e')
    path = tmp_path / 'ur5e.urdf'
    path.write_text(dh_chain_urdf(ur.dh if dh is None else dh, ur.joint_names, ur.limits, root_link='base'))
    return path


def test_parallel_axes_take_the_normal_through_the_previous_origin(tmp_path: Path) -> None:
    ur = load_robot('ur5e')
    chain = urdf_chain(_ur5e_urdf(tmp_path), 'base', 'hand')
    derived = derive_dh(chain)
    q = _configs(ur.limits, 200)
    assert np.allclose(kinematics.forward_kinematics(derived.base, derived.dh, q) @ derived.tool,
                       ur.forward_kinematics(q), atol=1e-12)
    # shoulder_lift -> elbow -> wrist_1 are parallel: d = 0 on the first two (Spong's choice), alpha 0 / 180 deg
    assert np.allclose(derived.dh[1:3, 1], 0.0, atol=1e-12)
    assert np.allclose(np.sin(derived.dh[1:3, 2]), 0.0, atol=1e-12)
    # the same table as UR's up to that choice: link lengths and the unidentifiable d sum
    assert np.allclose(np.abs(derived.dh[:, 0]), np.abs(ur.dh[:, 0]), atol=1e-12)
    ident = analyse(_model_from_urdf(tmp_path, ur))
    assert ident.rank == 22          # as the hand-written table: only the sum of the parallel d is seen


def _model_from_urdf(tmp_path: Path, ur: 'ArmModel') -> 'ArmModel':  # noqa: F821
    doc = {'name': 'ur5e_urdf', 'angle_unit': 'rad',
           'urdf': {'file': str(tmp_path / 'ur5e.urdf'), 'base_link': 'base', 'tip_link': 'hand'},
           'calibration_box': ur.calibration_box.tolist()}
    return robot_from_dict(doc)


def test_nearly_parallel_axes_warn_with_the_joint_names(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation

    from body_schema.urdf_model import _set_origin

    ur = load_robot('ur5e')
    straight = urdf_chain(_ur5e_urdf(tmp_path), 'base', 'hand')
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        derive_dh(straight)                                                # exactly parallel: silent
    # Tilt the elbow's axis half a degree about the upper arm's y: the common normal runs off.
    dh_joint = next(j for j in straight.joints if j.name == 'shoulder_lift_joint_dh')
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_euler('y', 0.5, degrees=True).as_matrix()
    bent_path = tmp_path / 'bent.urdf'
    bent_path.write_text(_set_origin(straight.text, dh_joint.name, dh_joint.origin @ tilt))
    chain = urdf_chain(bent_path, 'base', 'hand')
    with pytest.warns(NearlyParallelAxesWarning, match="'shoulder_lift_joint' and 'elbow_joint'"):
        derived = derive_dh(chain)
    assert ('shoulder_lift_joint', 'elbow_joint') in derived.nearly_parallel
    q = _configs(ur.limits, 200)
    assert np.abs(kinematics.forward_kinematics(derived.base, derived.dh, q) @ derived.tool
                  - [chain.tip_pose(qq) for qq in q]).max() < 1e-9           # still exact
    assert np.abs(derived.dh[1, 1]) > 10.0                                   # ill-conditioned: d metres away


@pytest.mark.parametrize('robot', sorted(ARMS))
def test_calibrated_urdf_moves_the_tip_as_the_estimate_and_changes_only_joint_origins(robot: str,
                                                                                    tmp_path: Path) -> None:
    path, base, tip = ARMS[robot]
    model = load_robot(robot)
    chain = urdf_chain(path, base, tip)
    derived = derive_dh(chain)
    rng = np.random.default_rng(7)
    estimate = model.dh + np.column_stack([rng.normal(0, 0.003, (7, 2)), rng.normal(0, 0.01, (7, 2))])
    out = tmp_path / path.name
    out.write_text(calibrated_urdf(chain, derived, estimate, mesh_base=path.parent))   # meshes found from here
    as_written = ET.fromstring(calibrated_urdf(chain, derived, estimate))
    tip_out = tip if robot == 'panda' else f'{tip}_calibrated'   # iiwa: link 7 is the last joint's own child
    q = _configs(model.limits, 300)
    expected = model.with_dh(estimate).flange_pose(q)
    again = urdf_chain(out, base, tip_out)
    assert np.abs(np.array([again.tip_pose(qq) for qq in q]) - expected).max() < 1e-9
    assert np.abs(_pinocchio_tip(out, base, tip_out, model.joint_names, q) - expected).max() < 1e-9
    assert np.abs(_pybullet_tip(out, tip_out, model.joint_names, q[:20]) - expected[:20]).max() < 2e-6
    # Everything but the chain's joint origins is as written.
    old, new = ET.parse(path).getroot(), as_written
    changed = {j.name for j in chain.joints if j.kind != 'fixed'} | {'panda_joint8'}
    new_joints = {j.get('name'): j for j in new.findall('joint')}
    for j in old.findall('joint'):
        n = new_joints[j.get('name')]
        for child in j:
            if not (child.tag == 'origin' and j.get('name') in changed):
                match = [c for c in n if c.tag == child.tag]
                assert match and match[0].attrib == child.attrib, (j.get('name'), child.tag)
    def text(link: ET.Element) -> bytes:
        link.tail = None
        return ET.tostring(link)

    old_links = [text(ln) for ln in old.findall('link')]
    assert [text(ln) for ln in new.findall('link')][:len(old_links)] == old_links


def test_a_xacro_is_expanded_and_errors_name_the_bad_value(tmp_path: Path) -> None:
    (tmp_path / 'arm.urdf.xacro').write_text('''<?xml version="1.0"?>
<robot name="two" xmlns:xacro="http://www.ros.org/wiki/xacro">
  <xacro:property name="len" value="0.3"/>
  <xacro:macro name="seg" params="i parent">
    <link name="l${i}"/>
    <joint name="j${i}" type="revolute"><parent link="${parent}"/><child link="l${i}"/>
      <origin xyz="0 0 ${len}" rpy="${pi/2} 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
    </joint>
  </xacro:macro>
  <link name="base"/>
  <xacro:seg i="1" parent="base"/>
  <xacro:seg i="2" parent="l1"/>
  <link name="slider"/>
  <joint name="p" type="prismatic"><parent link="l2"/><child link="slider"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.1" effort="1" velocity="1"/></joint>
</robot>''')
    doc = {'name': 'two', 'urdf': {'file': 'arm.urdf.xacro', 'base_link': 'base', 'tip_link': 'l2'}}
    model = robot_from_dict(doc, source=str(tmp_path / 'two.yaml'))
    assert model.joint_names == ('j1', 'j2') and np.allclose(model.limits, [[-1, 1], [-1, 1]])
    chain = urdf_chain(tmp_path / 'arm.urdf.xacro', 'base', 'l2')
    q = _configs(model.limits, 50)
    assert np.allclose(model.flange_pose(q), [chain.tip_pose(qq) for qq in q], atol=1e-12)
    with pytest.raises(UrdfDescriptionError, match="'nowhere'"):
        robot_from_dict({**doc, 'urdf': {**doc['urdf'], 'tip_link': 'nowhere'}}, source=str(tmp_path / 'two.yaml'))
    with pytest.raises(UrdfDescriptionError, match="'p' is prismatic"):
        robot_from_dict({**doc, 'urdf': {**doc['urdf'], 'tip_link': 'slider'}}, source=str(tmp_path / 'two.yaml'))
    with pytest.raises(UrdfDescriptionError, match='missing.urdf'):
        robot_from_dict({**doc, 'urdf': {**doc['urdf'], 'file': 'missing.urdf'}}, source=str(tmp_path / 'two.yaml'))
    with pytest.raises(RobotDescriptionError, match='joints'):
        robot_from_dict({**doc, 'joints': []}, source=str(tmp_path / 'two.yaml'))
    with pytest.raises(RobotDescriptionError, match="convention.*'craig'"):
        robot_from_dict({'convention': 'craig'})


@pytest.mark.parametrize('robot', ['panda', 'kuka_iiwa', 'panda_mdh'])
def test_the_new_descriptions_are_fully_identifiable(robot: str) -> None:
    # Condition numbers of the stacked pose Jacobian over the box (measured): panda 14.6, iiwa 16.1,
    # panda_mdh 14.0 (no parallel consecutive axes: all 28 parameters identifiable).
    ident = analyse(load_robot(robot))
    assert ident.rank == 28
    assert ident.singular_values[0] / ident.singular_values[-1] < 30


def test_package_urls_resolve_to_python_packages() -> None:
    model = load_robot('panda')
    assert model.urdf.path == (DATA / 'franka_panda' / 'panda.urdf').resolve()
    with pytest.raises(RobotDescriptionError, match='no_such_package'):
        robot_from_dict({'urdf': {'file': 'package://no_such_package/x.urdf', 'base_link': 'a', 'tip_link': 'b'}})
    assert os.path.isfile(model.urdf.path)


def test_the_palm_is_drawn_on_the_flange_where_the_markers_are() -> None:
    from body_schema.arm_visuals import model_visuals

    mdh, urdf = load_robot('panda_mdh'), load_robot('panda')
    assert np.allclose(mdh.tool[:3, 3], [0, 0, 0.107]) and np.allclose(urdf.tool, np.eye(4), atol=1e-12)
    palm_mdh, palm_urdf = model_visuals(mdh)['hand'][0], model_visuals(urdf)['hand'][0]
    q = np.radians([0, -10, 0, -110, 0, 170, 45])
    assert np.allclose(mdh.forward_kinematics(q) @ palm_mdh.origin, urdf.forward_kinematics(q) @ palm_urdf.origin,
                       atol=1e-9)
    assert palm_mdh.size == palm_urdf.size


@pytest.mark.parametrize('robot', ['panda', 'kuka_iiwa'])
def test_a_urdf_arm_is_described_by_what_its_urdf_lacks(robot: str) -> None:
    """Issue 33's shape of a description: at most 30 lines, no joint table and no box (it is
    proposed on loading, inside the limits), the camera's own fitted noise law."""
    text = robot_path(robot).read_text()
    doc = yaml.safe_load(text)
    assert len(text.splitlines()) <= 30
    assert 'joints' not in doc and 'calibration_box' not in doc and 'urdf' in doc
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model = load_robot(robot)
    assert np.all(model.calibration_box[:, 0] >= model.limits[:, 0])
    assert np.all(model.calibration_box[:, 1] <= model.limits[:, 1])
    assert np.all(np.ptp(model.calibration_box, axis=1) > np.radians(10.0))
    assert set(model.noise_law) >= {'a_pos', 'floor_pos', 'floor_rot'} and model.noise_covariance == 'sandwich_hc3'
