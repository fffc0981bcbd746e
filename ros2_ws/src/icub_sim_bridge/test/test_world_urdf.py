"""The simulated arm of a description read from a URDF: that URDF, meshes and all, its joint origins
corrected to the simulated robot's real (perturbed) DH table."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body_schema.noise import PoseDependentNoise
from body_schema.robot import load_robot
from body_schema.sampling import perturb_dh, uniform_configs
from body_schema.urdf_model import calibrated_tip_link, model_chain
from icub_sim_bridge.world import SimWorld
from marker_detector.detection import HandPoseEstimator

PANDA = load_robot('panda')


@pytest.mark.parametrize('name', ['panda', 'kuka_iiwa'])
def test_the_loaded_urdf_arm_follows_the_perturbed_table(name: str) -> None:
    """Tip link, hand and marker from PyBullet (float32) equal the model's FK with the real table."""
    robot = load_robot(name)
    dh = perturb_dh(robot.dh, 11, 0.004, np.radians(2.0))
    real = robot.with_dh(dh)
    tip = calibrated_tip_link(model_chain(robot)[0])      # the iiwa's link 7 is on its joint's axis
    with SimWorld(robot, dh) as w:
        for q in uniform_configs(robot.limits, 30, seed=4):
            w.set_joint_positions(q)
            hand = real.forward_kinematics(q)
            np.testing.assert_allclose(w.link_pose(tip), real.flange_pose(q), atol=1e-6)
            np.testing.assert_allclose(w.hand_pose(), hand, atol=1e-6)
            for m in robot.markers:
                np.testing.assert_allclose(w.link_pose(f'marker_{m.name}'), hand @ m.hand_T_marker, atol=1e-6)


def test_the_links_beyond_the_tip_stay_as_in_the_urdf_and_set_dh_reloads() -> None:
    """The Panda's hand hangs from the flange as written (-45 deg about z); a changed body reloads
    the URDF with the new joint origins and keeps the joint positions."""
    q = PANDA.calibration_box.mean(axis=1)
    changed = PANDA.dh.copy()
    changed[3, 1] += 0.01
    changed[1, 3] += np.radians(2.0)
    with SimWorld(PANDA) as w:
        w.set_joint_positions(q)
        flange = w.link_pose('panda_link8')
        hand_mount = np.eye(4)
        hand_mount[:3, :3] = Rotation.from_euler('z', -np.pi / 4).as_matrix()
        np.testing.assert_allclose(w.link_pose('panda_hand'), flange @ hand_mount, atol=1e-6)
        w.set_dh(changed)
        np.testing.assert_allclose(w.joint_positions(), q, atol=1e-12)
        np.testing.assert_allclose(w.link_pose('panda_link8'), PANDA.with_dh(changed).flange_pose(q), atol=1e-6)
        assert 'panda_leftfinger' in w._link_index


def test_the_camera_sees_the_meshes_and_the_marker_is_still_measured() -> None:
    """A render of the Panda from its URDF is not the DH-drawn arm (the meshes are there), and the
    detector still measures the hand to a few millimetres (a marker held past the fingertips)."""
    cam, intr = PANDA.camera_pose('left'), PANDA.camera
    est = HandPoseEstimator(PANDA, PoseDependentNoise.for_robot(PANDA))
    configs = uniform_configs(PANDA.calibration_box, 6, seed=0)
    errors = []
    with SimWorld(PANDA) as meshes, SimWorld(dataclasses.replace(PANDA, urdf=None)) as drawn:
        for q in configs:
            meshes.set_joint_positions(q)
            drawn.set_joint_positions(q)
            img = meshes.render(cam, intr)
            differ = np.any(np.abs(img.astype(int) - drawn.render(cam, intr).astype(int)) > 30, axis=2)
            assert differ.mean() > 0.01, f'the mesh arm looks like the drawn one at q={q}'
            result = est.process(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), intr.K, None, cam)
            if result.hand is not None:
                errors.append(np.linalg.norm(result.hand.pose[:3, 3] - meshes.hand_pose()[:3, 3]))
    assert len(errors) >= 4, f'the marker was measured in {len(errors)} of {len(configs)} configurations'
    assert np.median(errors) < 0.003 and max(errors) < 0.01, errors


def test_the_contact_monitor_checks_the_urdfs_collision_geometry() -> None:
    """For a URDF description the monitor's bodies are the URDF's links with collision shapes (the
    gripper beyond the tip included), parent and child unchecked; the box is free of contacts and
    a hand pushed into the table is reported."""
    from icub_sim_bridge.contacts import ContactMonitor

    mon = ContactMonitor(PANDA, probe_configs=16)
    links = set(mon.link_of.values())
    assert {'panda_link0', 'panda_link7', 'panda_hand', 'panda_leftfinger', 'panda_rightfinger'} <= links
    assert frozenset(('panda_link3', 'panda_link4')) in mon.unchecked
    assert not any(mon.check(q) for q in uniform_configs(PANDA.calibration_box, 10, seed=0))
    # A configuration whose flange is inside the 4 cm table slab, over its middle.
    inside = lambda t: -0.035 < t[2, 3] < -0.005 and abs(t[1, 3]) < 0.4 and 0.0 < t[0, 3] < 0.9  # noqa: E731
    q = next(q for q in uniform_configs(PANDA.limits, 2000, seed=1) if inside(PANDA.flange_pose(q)))
    assert any('table' in pair and pair[0].startswith('panda_') for pair in mon.check(q))
    mon.close()


def test_a_base_link_below_the_urdfs_root_is_placed_where_the_description_puts_it(tmp_path) -> None:
    """base_link need not be the URDF's root (an arm on a mobile base, a robot with a pedestal):
    the loaded file is placed so that base_link, not the root, lands on the description's base."""
    from body_schema.robot import robot_path

    text = robot_path('panda').read_text().replace('base_link: panda_link0', 'base_link: panda_link1')
    # No box in the file: the six joints get their own proposal (cached after the first load).
    path = tmp_path / 'panda_from_link1.yaml'
    path.write_text(text)
    robot = load_robot(path)
    assert robot.n_joints == 6 and robot.joint_names[0] == 'panda_joint2'
    dh = perturb_dh(robot.dh, 5, 0.004, np.radians(2.0))
    real = robot.with_dh(dh)
    with SimWorld(robot, dh) as w:
        for q in uniform_configs(robot.limits, 10, seed=2):
            w.set_joint_positions(q)
            np.testing.assert_allclose(w.hand_pose(), real.forward_kinematics(q), atol=1e-6)
            np.testing.assert_allclose(w.link_pose('panda_link1'), robot.base @ np.linalg.inv(
                model_chain(robot)[1].base), atol=1e-6)


@pytest.mark.parametrize('name', ['panda', 'kuka_iiwa'])
def test_the_selectors_check_and_the_simulators_monitor_see_the_same_arm(name: str) -> None:
    """Two libraries, one geometry: the selector's check (Pinocchio and Coal) and the simulator's
    monitor (Bullet) load the same URDF links, gripper and marker plate. Over configurations across
    the limits, every contact Bullet reports is a pair Coal finds within 2.5 mm (Bullet reports
    contacts a little before touch), and no pair Coal finds overlapping is free for Bullet."""
    from body_schema.collision import CollisionModel
    from icub_sim_bridge.contacts import ContactMonitor

    robot = load_robot(name)
    dh = perturb_dh(robot.dh, 7, 0.004, np.radians(2.0))
    mon = ContactMonitor(robot, dh, probe_configs=16)
    col = CollisionModel(robot, margin=0.0, self_margin=0.0, dh=dh, probe_configs=16)
    assert {n for pair in col.pairs for n in pair} - {'table'} == set(mon.link_of.values())
    in_contact = 0
    for q in uniform_configs(robot.limits, 150, seed=4):
        contacts = {frozenset(p) for p in mon.check(q)}
        in_contact += bool(contacts)
        for pair, d in col.pair_distances(q).items():
            if frozenset(pair) in contacts:
                assert d < 0.0025, (pair, d)
            elif frozenset(pair) not in mon.unchecked:
                assert d > 0.0, (pair, d)
    assert in_contact >= 10
    mon.close()
