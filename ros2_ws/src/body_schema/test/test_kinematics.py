"""Forward kinematics against the iCub reference points; Jacobians against central differences."""
import numpy as np
import pytest

import body_schema
from body_schema import kinematics
from body_schema.sampling import uniform_configs


@pytest.fixture(scope='module')
def arm():
    return body_schema.load_robot('icub_right_arm')


def test_fk_reference_configurations(arm):
    # docs/architecture.md section 4 (robotology iKinFwd.cpp).
    np.testing.assert_allclose(arm.forward_kinematics(np.zeros(7))[:3, 3], [-0.011, 0.094, -0.177], atol=1e-3)
    q = np.radians([-30, 30, 0, 45, 0, 0, 0])
    np.testing.assert_allclose(arm.forward_kinematics(q)[:3, 3], [-0.298, 0.211, 0.029], atol=1e-3)


def test_left_eye_at_zero_head(arm):
    np.testing.assert_allclose(arm.camera_pose('left', np.zeros(5))[:3, 3], [-0.063, -0.034, 0.341], atol=1e-3)
    right = arm.camera_pose('right', np.zeros(5))[:3, 3]
    assert right[1] == pytest.approx(0.034, abs=1e-3)      # eyes are 68 mm apart along y


def test_batched_fk_matches_single(arm):
    q = uniform_configs(arm.limits, 50, seed=3)
    batch = arm.forward_kinematics(q)
    assert batch.shape == (50, 4, 4)
    for i in (0, 17, 49):
        np.testing.assert_allclose(batch[i], arm.forward_kinematics(q[i]), atol=1e-12)
    np.testing.assert_allclose(batch[:, :3, :3] @ np.swapaxes(batch[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)


def _numeric_pose_jacobian(fun, x, eps=1e-6):
    """Central differences of a pose-valued function: position and base-frame rotation vector."""
    t0 = fun(x)
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        tp, tm = fun(x + dx), fun(x - dx)
        dp = (tp[:3, 3] - tm[:3, 3]) / (2 * eps)
        dw = (kinematics.rotation_vector_error(tp[:3, :3], t0[:3, :3])
              - kinematics.rotation_vector_error(tm[:3, :3], t0[:3, :3])) / (2 * eps)
        cols.append(np.concatenate([dp, dw]))
    return np.array(cols).T


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_dh_jacobian_matches_central_differences(arm, seed):
    q = uniform_configs(arm.limits, 1, seed)[0]
    x = arm.dh.ravel()
    num = _numeric_pose_jacobian(lambda v: kinematics.forward_kinematics(arm.base, v.reshape(7, 4), q), x)
    ana = arm.jacobian_dh(q)
    assert ana.shape == (6, 28)
    np.testing.assert_allclose(ana, num, atol=1e-7)


def test_joint_jacobian_matches_central_differences(arm):
    q = uniform_configs(arm.limits, 1, 7)[0]
    num = _numeric_pose_jacobian(lambda v: arm.forward_kinematics(v), q)
    np.testing.assert_allclose(arm.jacobian_joints(q), num, atol=1e-7)


def test_batched_jacobian_matches_single(arm):
    q = uniform_configs(arm.limits, 4, 11)
    batch = arm.jacobian_dh(q)
    assert batch.shape == (4, 6, 28)
    np.testing.assert_allclose(batch[2], arm.jacobian_dh(q[2]), atol=1e-12)


def test_wrong_configuration_shape_raises(arm):
    with pytest.raises(ValueError, match=r'shape \(7,\)'):
        arm.forward_kinematics(np.zeros(6))


@pytest.mark.parametrize('angle_deg', [0.0, 1e-7, 0.3, 45.0, 170.0, 179.95, 180.0])
def test_so3_log_matches_scipy(angle_deg):
    from scipy.spatial.transform import Rotation

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    w = np.radians(angle_deg) * axis
    r = Rotation.from_rotvec(w).as_matrix()
    got = kinematics.so3_log(r)
    assert np.linalg.norm(got) == pytest.approx(np.radians(angle_deg), abs=1e-9)
    if angle_deg < 180.0:                      # at exactly pi, w and -w are the same rotation
        np.testing.assert_allclose(got, w, atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(got).as_matrix(), r, atol=1e-9)


def test_equivalent_table_finds_the_twin_an_estimate_settled_on():
    # The UR5e's elbow with a > 0 and both neighbouring offsets turned by pi (one trial in 48 of
    # tools.error_replay settles there): the same hand poses, written another way.
    ur = body_schema.load_robot('ur5e')
    twin = ur.dh.copy()
    twin[2, 0], twin[2, 2], twin[2, 3], twin[3, 3] = -twin[2, 0], -twin[2, 2], twin[2, 3] + np.pi, twin[3, 3] + np.pi
    twin[0, 3] += 2 * np.pi                                  # and an angle a turn away
    q = uniform_configs(ur.calibration_box, 20, 0)
    assert np.abs(kinematics.forward_kinematics(ur.base, twin, q)
                  - kinematics.forward_kinematics(ur.base, ur.dh, q)).max() < 1e-12
    np.testing.assert_allclose(kinematics.equivalent_table(ur.dh, twin), twin, atol=1e-12)
    np.testing.assert_allclose(kinematics.equivalent_table(twin, ur.dh), ur.dh, atol=1e-12)
    np.testing.assert_allclose(kinematics.equivalent_table(ur.dh, ur.dh + 0.01), ur.dh, atol=1e-12)  # near: as is
    with pytest.raises(ValueError, match=r'tables of shape \(L, 4\) needed, got \(6, 4\) and \(5, 4\)'):
        kinematics.equivalent_table(ur.dh, ur.dh[:5])
