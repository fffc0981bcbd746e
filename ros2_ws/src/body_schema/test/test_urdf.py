"""URDF export: the generated chain must reproduce the DH forward kinematics exactly."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from body_schema import kinematics
from body_schema.robot import load_robot
from body_schema.sampling import perturb_dh, uniform_configs
from body_schema.urdf import (FixedLink, Visual, dh_chain_urdf, link_pose, model_urdf, transform_to_xyz_rpy,
                              xyz_rpy_to_transform)


def urdf_fk(text: str, q: dict[str, float], link: str) -> np.ndarray:
    return link_pose(text, link, q)


def test_rpy_round_trip_including_gimbal_lock() -> None:
    rng = np.random.default_rng(0)
    mats = [xyz_rpy_to_transform(rng.normal(size=3), rng.uniform(-3, 3, 3)) for _ in range(20)]
    robot = load_robot()
    mats += [robot.base, np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])]
    for m in mats:
        np.testing.assert_allclose(xyz_rpy_to_transform(*transform_to_xyz_rpy(m)), m, atol=1e-12)


@pytest.mark.parametrize('perturbed', [False, True])
def test_urdf_chain_matches_dh_forward_kinematics(perturbed: bool) -> None:
    robot = load_robot()
    dh = perturb_dh(robot.dh, 3) if perturbed else robot.dh
    text = dh_chain_urdf(dh, robot.joint_names, robot.limits, base=robot.base)
    qs = uniform_configs(robot.limits, 10, seed=1)
    for q in qs:
        want = kinematics.forward_kinematics(robot.base, dh, q)
        got = urdf_fk(text, dict(zip(robot.joint_names, q)), 'hand')
        np.testing.assert_allclose(got, want, atol=1e-12)


def test_limits_names_and_extra_links_are_written() -> None:
    robot = load_robot()
    marker = FixedLink('palm_marker', 'hand', xyz_rpy_to_transform([0, 0, 0.01], [np.pi, 0, 0]),
                       (Visual('box', (0.04, 0.04, 0.001)),))
    text = model_urdf(robot, extra_links=[marker],
                      visuals={'r_elbow_link': [Visual('cylinder', (0.03, 0.1))]})
    root = ET.fromstring(text)
    assert root.get('name') == robot.name
    revolute = [j for j in root.findall('joint') if j.get('type') == 'revolute']
    assert [j.get('name') for j in revolute] == list(robot.joint_names)
    for j, (lo, hi) in zip(revolute, robot.limits):
        assert float(j.find('limit').get('lower')) == pytest.approx(lo, abs=1e-15)
        assert float(j.find('limit').get('upper')) == pytest.approx(hi, abs=1e-15)
    q = dict(zip(robot.joint_names, np.radians([-30, 30, 0, 45, 0, 0, 0])))
    np.testing.assert_allclose(urdf_fk(text, q, 'palm_marker'),
                               urdf_fk(text, q, 'hand') @ marker.parent_T_link, atol=1e-12)
    assert len(root.find("link[@name='r_elbow_link']").findall('visual')) == 1


@pytest.mark.parametrize('kwargs, match', [
    (dict(limits=np.zeros((7, 2))), 'lower limit'),
    (dict(joint_names=['a'] * 6), 'joint names'),
    (dict(visuals={'nope': [Visual('sphere', (0.1,))]}), 'unknown links'),
    (dict(extra_links=[FixedLink('m', 'nowhere', np.eye(4))]), 'unknown parent'),
])
def test_bad_input_is_named(kwargs: dict, match: str) -> None:
    robot = load_robot()
    args = dict(dh=robot.dh, joint_names=robot.joint_names, limits=robot.limits)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        dh_chain_urdf(**args)


def test_visual_validation() -> None:
    with pytest.raises(ValueError, match='box needs 3'):
        Visual('box', (0.1, 0.1))
    with pytest.raises(ValueError, match='shape must be'):
        Visual('cone', (0.1,))


def test_chain_transforms_are_the_urdf_joints_and_compose_to_the_hand_pose() -> None:
    """TF frames and URDF cannot disagree: same parent/child pairs; root -> hand = FK (prefixed too)."""
    from body_schema.urdf import chain_transforms

    robot = load_robot()
    rng = np.random.default_rng(4)
    dh = robot.dh + rng.normal(0, 0.01, robot.dh.shape)
    q = rng.uniform(robot.limits[:, 0], robot.limits[:, 1])
    for prefix in ('', 'estimate/'):
        fixed, moving = chain_transforms(dh, robot.joint_names, q, base=robot.base, prefix=prefix)
        urdf = ET.fromstring(dh_chain_urdf(dh, robot.joint_names, robot.limits, base=robot.base, prefix=prefix))
        pairs = {(j.find('parent').get('link'), j.find('child').get('link')) for j in urdf.iter('joint')}
        assert pairs == {(t.parent, t.child) for t in fixed + moving}
        assert len(moving) == robot.n_joints
        edges = {t.child: t for t in fixed + moving}
        frame, pose = f'{prefix}hand', np.eye(4)
        while frame in edges:
            pose = edges[frame].parent_T_child @ pose
            frame = edges[frame].parent
        assert frame == 'root_link'
        np.testing.assert_allclose(pose, robot.with_dh(dh).forward_kinematics(q), atol=1e-12)
    with pytest.raises(ValueError, match='7 finite joint positions'):
        chain_transforms(dh, robot.joint_names, q[:6])


def test_the_palm_grows_to_hold_markers_larger_than_it_and_only_those() -> None:
    from body_schema.arm_visuals import HAND_SIZE, description_urdf, palm_size, quad_side
    from body_schema.robot import MarkerPlacement
    icub = load_robot()
    assert palm_size(icub.markers, quad_side(icub.marker_dictionary, icub.marker_side_length)) == HAND_SIZE
    # An 8 cm DICT_4X4 marker is printed 8 * 8/6 cm wide with its one-cell quiet zone.
    q = quad_side('DICT_4X4_50', 0.08)
    assert q == pytest.approx(0.08 * 8 / 6)
    centred = MarkerPlacement('plate', 0, np.eye(4))
    assert palm_size([centred], q)[:2] == pytest.approx((q, q))
    # Off-centre and turned by 45 deg about z: the palm reaches the farthest corner on each side.
    t = np.eye(4)
    t[:3, :3] = np.array([[np.cos(np.pi / 4), -np.sin(np.pi / 4), 0], [np.sin(np.pi / 4), np.cos(np.pi / 4), 0],
                          [0, 0, 1]])
    t[:3, 3] = [0.02, -0.01, 0.0]
    x, y, z = palm_size([MarkerPlacement('turned', 1, t)], 0.06)
    assert (x, y, z) == pytest.approx((2 * (0.02 + 0.03 * np.sqrt(2)), 2 * (0.01 + 0.03 * np.sqrt(2)), HAND_SIZE[2]))
    # The published model draws the palm the UR5e's plate marker needs.
    ur = load_robot('ur5e')
    want = palm_size(ur.markers, quad_side(ur.marker_dictionary, ur.marker_side_length))
    assert want[0] > HAND_SIZE[0]
    palm = ET.fromstring(description_urdf(ur)).find("link[@name='hand']/visual/geometry/box")
    assert [float(v) for v in palm.get('size').split()] == pytest.approx(want)
