"""Noise models: the paper's law, the position/orientation split, and marker choice."""
import numpy as np
import pytest

import body_schema
from body_schema.noise import ConstantNoise, PoseDependentNoise, noise_model, view_geometry


def test_paper_law_exactly():
    m = PoseDependentNoise.paper(a=2e-3, b=1e-6)
    r, phi = np.array([0.2, 0.5]), np.array([45.0, 0.0])
    R = m.covariance(r, phi)
    assert R.shape == (2, 6, 6)
    np.testing.assert_allclose(np.diag(R[0]), 2e-3 * 0.04)
    np.testing.assert_allclose(np.diag(R[1]), 2e-3 * 0.25 + 1e-6 * 45 ** 2)
    assert np.count_nonzero(R[1] - np.diag(np.diag(R[1]))) == 0


def test_noise_grows_with_distance_and_away_from_45_deg():
    # The fitted defaults: both grow with distance; orientation also away from 45 deg (the
    # fit found no angle dependence for position once planar flips are gated: b_pos = 0).
    m = PoseDependentNoise()
    vp_near, vo_near = m.variances(0.2, 45.0)
    vp_far, vo_far = m.variances(0.6, 45.0)
    vp_frontal, vo_frontal = m.variances(0.2, 0.0)
    assert vp_far > vp_near and vo_far > vo_near
    assert vp_frontal >= vp_near and vo_frontal > vo_near
    custom = PoseDependentNoise(b_pos=1e-8)
    assert custom.variances(0.2, 0.0)[0] > custom.variances(0.2, 45.0)[0]


def test_view_geometry():
    cam = np.eye(4)
    marker = np.eye(4)
    marker[:3, 3] = [0, 0, 0.5]
    marker[:3, :3] = np.diag([1.0, -1.0, -1.0])          # facing the camera head-on
    r, phi = view_geometry(cam, marker)
    assert r == pytest.approx(0.5) and phi == pytest.approx(0.0, abs=1e-9)
    marker[:3, :3] = np.eye(3)                            # facing away
    assert view_geometry(cam, marker)[1] == pytest.approx(180.0)


def test_hand_covariance_uses_the_marker_facing_the_camera():
    arm = body_schema.load_robot()
    m = PoseDependentNoise()
    hand = np.eye(4)
    hand[:3, 3] = [0.0, 0.0, 0.4]
    cam = np.eye(4)
    palm, back = arm.markers[0].hand_T_marker, arm.markers[1].hand_T_marker
    r, phi = view_geometry(cam, np.stack([hand @ palm, hand @ back]))
    facing = int(np.argmin(phi))
    assert phi[facing] < 90 < phi[1 - facing]             # palm and back face opposite ways
    expected = m.covariance(r[facing], phi[facing])
    np.testing.assert_allclose(m.hand_covariance(cam, hand, arm.markers), expected)
    batch = m.hand_covariance(cam, np.stack([hand, hand]), arm.markers)
    assert batch.shape == (2, 6, 6)


def test_constant_noise_and_factory():
    cn = noise_model('constant', sigma_pos=0.01, sigma_rot=0.05)
    assert isinstance(cn, ConstantNoise)
    np.testing.assert_allclose(np.diag(cn.covariance(0.3, 10.0)), [1e-4] * 3 + [0.0025] * 3)
    with pytest.raises(ValueError, match='unknown noise model'):
        noise_model('gaussian')
    with pytest.raises(ValueError, match='a_pos'):
        PoseDependentNoise(a_pos=-1.0)
    with pytest.raises(ValueError, match='sigma_rot'):
        ConstantNoise(sigma_rot=float('nan'))
