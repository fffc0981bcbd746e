"""The plan view draws the obstacles where the description puts them and each planned pose's arm."""
import numpy as np

from body_schema.robot import load_robot
from calibration_viz.plan_view import obstacle_meshes, plan_geometry, serve


def test_obstacle_meshes_span_the_described_bodies():
    ur = load_robot('ur5e')
    meshes = {name: v for name, v, _f, _rgb in obstacle_meshes(ur)}
    assert set(meshes) == {'table', 'camera_stand'}
    np.testing.assert_allclose(meshes['table'].min(axis=0), [-1.0, -0.6, -0.04], atol=1e-6)
    np.testing.assert_allclose(meshes['table'].max(axis=0), [0.3, 0.6, 0.0], atol=1e-6)
    np.testing.assert_allclose(meshes['camera_stand'][:, 2].max(), 0.45, atol=1e-6)
    assert {name for name, *_ in obstacle_meshes(load_robot('icub_right_arm'))} == {'chest', 'hips', 'head'}


def test_plan_geometry_puts_the_hand_where_the_kinematics_do_and_the_path_from_the_start():
    ur = load_robot('ur5e')
    start = ur.calibration_box.mean(axis=1)
    poses = start + np.radians([[10, 5, -5, 0, 10, 20], [-20, 0, 10, 5, 0, -30]])
    geo = plan_geometry(ur, poses, start)
    assert geo.arms.shape == (2, ur.n_joints + 2, 3) and geo.flange_path.shape == (2, 20, 3)
    np.testing.assert_allclose(geo.arms[:, -1], ur.forward_kinematics(poses)[:, :3, 3])
    np.testing.assert_allclose(geo.flange_path[0, 0], ur.forward_kinematics(start)[:3, 3])
    np.testing.assert_allclose(geo.flange_path[1, 0], geo.arms[0, -1])
    np.testing.assert_allclose(geo.flange_path[1, -1], geo.arms[1, -1])


def test_the_view_serves_without_a_browser():
    ur = load_robot('ur5e')
    start = ur.calibration_box.mean(axis=1)
    server = serve(ur, start[None] + 0.1, start, port=0, block=False)
    try:
        assert server.get_port() > 0
    finally:
        server.stop()
