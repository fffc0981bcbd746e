"""Camera pose and marker offset estimated with the DH table: model, Jacobian, gauge, recovery."""
from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from body_schema import kinematics, sampling
from body_schema.acquisition import AcquisitionCost
from body_schema.extrinsics import (Extrinsics, absorbed_parameters, align_truth, corrections, parse_std,
                                    perturb_pose, pose_delta, random_delta, static_transform)
from body_schema.identifiability import analyse, parameter_names, subspace_nees
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import PoseDependentNoise
from body_schema.robot import load_robot
from body_schema.sampling import uniform_configs
from body_schema.synthetic import SyntheticRun

UR5E = load_robot('ur5e')
CAM = UR5E.camera_pose('left')
MARKER = UR5E.markers[0].hand_T_marker
BOTH = Extrinsics(CAM, MARKER, (0.02, np.radians(2.0)), (0.005, np.radians(5.0)))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def test_perturb_pose_and_pose_delta_are_inverse_and_mean_what_they_say():
    rng = np.random.default_rng(0)
    d = random_delta(rng, 0.02, np.radians(2.0))
    assert np.linalg.norm(d[:3]) == pytest.approx(0.02) and np.degrees(np.linalg.norm(d[3:])) == pytest.approx(2.0)
    moved = perturb_pose(CAM, d)
    np.testing.assert_allclose(moved[:3, 3] - CAM[:3, 3], d[:3], atol=1e-15)
    assert kinematics.rotation_angle_deg(moved[:3, :3], CAM[:3, :3]) == pytest.approx(2.0)
    np.testing.assert_allclose(pose_delta(moved, CAM), d, atol=1e-12)


def test_the_observation_is_what_the_detector_makes_of_a_real_camera_and_marker():
    """h = E FK F equals C_nom (C^-1 FK M) M_nom^-1, the detector's hand pose from the nominal poses."""
    rng = np.random.default_rng(1)
    c, m = random_delta(rng, 0.02, 0.03), random_delta(rng, 0.005, 0.08)
    q = uniform_configs(UR5E.calibration_box, 5, 2)
    fk = kinematics.forward_kinematics(UR5E.base, UR5E.dh, q)
    cam_t_marker = np.linalg.inv(perturb_pose(CAM, c)) @ fk @ perturb_pose(MARKER, m)
    detector = CAM @ cam_t_marker @ np.linalg.inv(MARKER)
    hands, _ = BOTH.predict(kinematics.chain_frames(UR5E.base, UR5E.dh, q), np.concatenate([c, m]), jacobian=False)
    np.testing.assert_allclose(hands, detector, atol=1e-12)


def test_jacobian_matches_central_differences_of_the_whole_model():
    rng = np.random.default_rng(2)
    dh = sampling.perturb_dh(UR5E.dh, rng, 0.01, np.radians(3.0))
    e = np.concatenate([random_delta(rng, 0.02, 0.05), random_delta(rng, 0.005, 0.1)])
    q = uniform_configs(UR5E.calibration_box, 4, 3)
    x = np.concatenate([dh.ravel(), e])

    def model(v):
        return BOTH.predict(kinematics.chain_frames(UR5E.base, v[:24].reshape(6, 4), q), v[24:], jacobian=False)[0]

    _, jac = BOTH.predict(kinematics.chain_frames(UR5E.base, dh, q), e)
    h = 1e-6
    for k in range(x.size):
        step = np.zeros(x.size)
        step[k] = h
        plus, minus = model(x + step), model(x - step)
        col = np.concatenate([(plus[:, :3, 3] - minus[:, :3, 3]),
                              kinematics.rotation_vector_error(plus[:, :3, :3], minus[:, :3, :3])], axis=1) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], col, atol=2e-6, err_msg=f'column {k}')


def test_correction_columns_at_zero_are_the_closed_form():
    """At zero corrections: a camera shift moves the hand by -dp, a camera turn w by -w about the
    camera centre; a marker shift dp (flange frame) by R_T dp, a marker turn w by R_T w about the marker."""
    q = uniform_configs(UR5E.calibration_box, 3, 4)
    frames = kinematics.chain_frames(UR5E.base, UR5E.dh, q)
    _, jac = BOTH.predict(frames, np.zeros(12))
    for n in range(3):
        fk = frames[n, -1]
        r_t, p = fk[:3, :3], fk[:3, 3]
        expected = np.zeros((6, 12))
        expected[:3, :3] = -np.eye(3)
        expected[:3, 3:6] = _skew(p - CAM[:3, 3])
        expected[3:, 3:6] = -np.eye(3)
        expected[:3, 6:9] = r_t
        expected[:3, 9:12] = r_t @ _skew(MARKER[:3, 3])
        expected[3:, 9:12] = r_t
        np.testing.assert_allclose(jac[n, :, 24:], expected, atol=1e-7)


def test_augmented_ur5e_unidentifiable_directions_are_the_ones_the_geometry_predicts():
    """A free camera absorbs the first link's d and offset, a free marker the last row; the three
    parallel axes still hide two d differences: 8 of 36 combinations, the dependent columns named."""
    found = analyse(UR5E, n=60, seed=3, extrinsics=BOTH)
    names = parameter_names(UR5E.joint_names) + BOTH.names
    assert found.rank == 28 and found.n_unidentifiable == 8
    dependent = {names[int(np.argmax(v == 1.0))] for v in found.dependencies}
    absorbed = {names[i] for i in absorbed_parameters(6, True, True)}
    assert absorbed == {'shoulder_pan_joint.d', 'shoulder_pan_joint.offset', 'wrist_3_joint.a', 'wrist_3_joint.d',
                        'wrist_3_joint.alpha', 'wrist_3_joint.offset'}
    assert absorbed <= dependent and len(dependent - absorbed) == 2
    assert all(n.endswith('.d') for n in dependent - absorbed)
    # Each is a null vector of the Jacobian at other configurations too (an exact dependency).
    q = uniform_configs(UR5E.calibration_box, 20, 9)
    jac = BOTH.predict(kinematics.chain_frames(UR5E.base, UR5E.dh, q), np.zeros(12))[1].reshape(-1, 36)
    assert np.max(np.abs(jac @ found.null_space)) < 1e-8 * np.max(np.abs(jac))
    # The camera's yaw about the base axis through the origin trades with the pan offset: the
    # camera at (-1.7, -0.13) moves by w x p, so the dependency names camera.x, camera.y, camera.rz.
    pan = next(v for v in found.dependencies if v[3] == 1.0)
    w = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(pan[24:30], np.concatenate([np.cross(w, CAM[:3, 3]), w]), atol=1e-6)
    # Held: the absorbed DH parameters themselves (the camera and marker stay free).
    held = found.held_directions
    assert np.allclose(held[24:], 0.0)
    for i in absorbed_parameters(6, True, True):
        assert np.linalg.norm(held.T[:, i]) == pytest.approx(1.0)


def test_without_extrinsics_nothing_changes():
    plain = analyse(UR5E, n=60, seed=3)
    assert analyse(UR5E, n=60, seed=3, extrinsics=Extrinsics(CAM, MARKER)).null_space.shape == plain.null_space.shape
    np.testing.assert_array_equal(plain.held_directions, plain.null_space)


def test_aligned_truth_sees_the_same_and_holds_the_absorbed_parameters():
    rng = np.random.default_rng(5)
    true_dh = sampling.perturb_dh(UR5E.dh, rng, 0.004, np.radians(2.0))
    cam, mk = perturb_pose(CAM, random_delta(rng, 0.02, 0.035)), perturb_pose(MARKER, random_delta(rng, 0.005, 0.09))
    held = sampling.perturb_dh(UR5E.dh, rng)                 # a wide guess: the alignment is exact, not linear
    dh2, cam2, mk2 = align_truth(UR5E.base, true_dh, cam, mk, held, True, True)
    q = uniform_configs(UR5E.calibration_box, 10, 6)
    seen = np.linalg.inv(cam) @ kinematics.forward_kinematics(UR5E.base, true_dh, q) @ mk
    seen2 = np.linalg.inv(cam2) @ kinematics.forward_kinematics(UR5E.base, dh2, q) @ mk2
    np.testing.assert_allclose(seen2, seen, atol=1e-12)
    idx = list(absorbed_parameters(6, True, True))
    np.testing.assert_array_equal(dh2.ravel()[idx], held.ravel()[idx])
    rest = [i for i in range(24) if i not in idx]
    np.testing.assert_array_equal(dh2.ravel()[rest], true_dh.ravel()[rest])


class _Scaled(PoseDependentNoise):
    """The pose-dependent model at a fifth of its standard deviation (a 1280x1024 camera's detector
    is far better than the iCub's 320x240 eye the model was fitted on)."""

    def hand_covariance(self, *args, **kwargs):
        return 0.04 * super().hand_covariance(*args, **kwargs)


def test_map_recovers_camera_marker_and_table_in_the_gauge_of_the_description():
    rng = np.random.default_rng(11)
    true_dh = sampling.perturb_dh(UR5E.dh, rng, 0.004, np.radians(2.0))
    c, m = random_delta(rng, 0.02, np.radians(2.0)), random_delta(rng, 0.005, np.radians(5.0))
    obs = SyntheticRun(UR5E, true_dh, _Scaled(), rng, camera_delta=c, marker_delta=m)(150)
    idx = list(absorbed_parameters(6, True, True))
    x0 = UR5E.dh.ravel().copy()
    x0[[i for i in range(24) if i not in idx]] = sampling.perturb_dh(UR5E.dh, rng, 0.01, np.radians(3.0)).ravel()[
        [i for i in range(24) if i not in idx]]
    std = np.concatenate([np.tile([0.01, 0.01, np.radians(3.0), np.radians(3.0)], 6) / np.sqrt(3.0), BOTH.prior_std()])
    ident = analyse(UR5E, extrinsics=BOTH)
    est = MapEstimator(UR5E.base, np.concatenate([x0, np.zeros(12)]), np.diag(std ** 2), MapSettings(),
                       fixed_directions=ident.held_directions, extrinsics=BOTH)
    est.solve_batch([o.q for o in obs], [o.pose for o in obs], [o.R for o in obs])
    dh_a, cam_a, mk_a = align_truth(UR5E.base, true_dh, perturb_pose(CAM, c), perturb_pose(MARKER, m),
                                    est.table(), True, True)
    errors = PoseErrorEvaluator(UR5E.base, dh_a, UR5E.calibration_box)(est.table())
    assert errors.position_m < 1.5e-3 and errors.orientation_deg < 0.15
    # Far better than ignoring the camera and marker errors, and the camera within 4 sigma per axis.
    cam_err = pose_delta(perturb_pose(CAM, est.x[24:30]), cam_a)
    sigma = np.sqrt(np.diag(est.P))[24:30]
    assert np.all(np.abs(cam_err) < 4 * sigma)
    x_true = np.concatenate([dh_a.ravel(), pose_delta(cam_a, CAM), pose_delta(mk_a, MARKER)])
    nees = subspace_nees(est.x - x_true, est.P, ident.identifiable_basis)
    assert nees < 60.0                                  # chi-square 28 dof: 99.99% bound ~ 62


def test_map_without_extrinsics_is_the_same_estimator():
    obs = SyntheticRun(UR5E, UR5E.dh, PoseDependentNoise(), 3)(8)
    x0 = sampling.perturb_dh(UR5E.dh, 4)
    P0 = sampling.initial_covariance(6)
    a = MapEstimator(UR5E.base, x0, P0)
    b = MapEstimator(UR5E.base, x0, P0, extrinsics=Extrinsics(CAM, MARKER))
    for o in obs:
        a.update(o.q, o.pose, o.R)
        b.update(o.q, o.pose, o.R)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


@pytest.mark.parametrize('text, expected', [('', None), ('0', None), ('0 0', None),
                                            ('0.02 2', (0.02, np.radians(2.0))),
                                            ('0.005, 5', (0.005, np.radians(5.0)))])
def test_parse_std(text, expected):
    assert parse_std(text, 'camera_prior') == (pytest.approx(expected) if expected else None)


@pytest.mark.parametrize('text', ['0.02', 'a b', '0.02 -2', '0.02 2 3'])
def test_parse_std_names_the_bad_value(text):
    with pytest.raises(ValueError, match='camera_prior.*' + re.escape(repr(text))):
        parse_std(text, 'camera_prior')


def test_static_transform_is_the_pose():
    tf = static_transform(CAM, 'base', 'left_camera_optical_frame')
    quat = [tf['qx'], tf['qy'], tf['qz'], tf['qw']]
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), CAM[:3, :3], atol=1e-12)
    np.testing.assert_allclose([tf['x'], tf['y'], tf['z']], CAM[:3, 3])
    assert tf['arguments'].endswith('--frame-id base --child-frame-id left_camera_optical_frame')


def test_corrections_are_identity_at_zero():
    e, f = corrections(CAM, MARKER, np.zeros(6), np.zeros(6))
    np.testing.assert_allclose(e, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(f, np.eye(4), atol=1e-12)


def _cost(P, extrinsics=None, criterion='a_optimal'):  # noqa: N803
    box = uniform_configs(UR5E.calibration_box, 64, 0)
    return AcquisitionCost(UR5E.base, UR5E.dh, P, PoseDependentNoise(), CAM, UR5E.markers, criterion=criterion,
                           box_configs=box, extrinsics=extrinsics)


@pytest.mark.parametrize('criterion', ['a_optimal', 'v_optimal'])
def test_acquisition_with_a_known_camera_is_the_table_alone_and_a_free_one_gains_less(criterion):
    """The selector scores only the table: a camera whose pose is known (tiny prior) leaves the
    gain as without extrinsics; a free camera takes part of each observation's information."""
    P_dh = sampling.initial_covariance(6, 0.004, np.radians(2.0))  # noqa: N806
    qs = uniform_configs(UR5E.calibration_box, 20, 1)
    plain = _cost(P_dh, criterion=criterion).terms_batch(qs)[0]
    camera_only = Extrinsics(CAM, MARKER, camera_std=(0.02, np.radians(2.0)))
    known = _cost(scipy.linalg.block_diag(P_dh, 1e-14 * np.eye(6)), camera_only, criterion).terms_batch(qs)[0]
    np.testing.assert_allclose(known, plain, rtol=1e-6)
    free_p = scipy.linalg.block_diag(P_dh, np.diag(camera_only.prior_std() ** 2))
    free = _cost(free_p, camera_only, criterion).terms_batch(qs)[0]
    assert np.all(free < plain) and np.median(free / plain) < 0.9
    with pytest.raises(ValueError, match=r'\(30, 30\).*6 extrinsic corrections'):
        _cost(P_dh, camera_only, criterion)
