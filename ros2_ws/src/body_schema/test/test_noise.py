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


def test_a_depth_ratio_stretches_the_position_along_the_line_of_sight():
    from body_schema import load_robot
    from body_schema.noise import line_of_sight_covariance

    np.testing.assert_array_equal(line_of_sight_covariance(1e-6, 1e-5, [0.3, 0.1, 2.0], 1.0),
                                  np.diag([1e-6] * 3 + [1e-5] * 3))
    cov = line_of_sight_covariance(np.array([1e-6, 4e-6]), np.array([1e-5, 1e-5]), [[0, 0, 2.0], [1.0, 0, 0]], 3.0)
    np.testing.assert_allclose(np.diag(cov[0])[:3], [1e-6, 1e-6, 9e-6])
    np.testing.assert_allclose(np.diag(cov[1])[:3], [36e-6, 4e-6, 4e-6])
    # The predicted covariance of a hand pose: along its marker's line of sight from the camera.
    ur = load_robot('ur5e')
    deep = PoseDependentNoise.for_robot(ur, depth_ratio=4.0)
    cam = ur.camera_pose('left')
    hands = ur.forward_kinematics(np.mean(ur.calibration_box, axis=1)[None].repeat(3, 0) + [[0.0], [0.1], [0.2]])
    covs = deep.hand_covariance(cam, hands, ur.markers)
    for hand, c in zip(hands, covs):
        los = (hand @ ur.markers[0].hand_T_marker)[:3, 3] - cam[:3, 3]
        values, vectors = np.linalg.eigh(c[:3, :3])
        assert values[2] == pytest.approx(16.0 * values[0]) and values[1] == pytest.approx(values[0])
        assert abs(vectors[:, 2] @ los) / np.linalg.norm(los) == pytest.approx(1.0)
    np.testing.assert_allclose(deep.hand_covariance(cam, hands[0], ur.markers), covs[0])
    np.testing.assert_array_equal(PoseDependentNoise.for_robot(ur).hand_covariance(cam, hands, ur.markers)[:, 3:, 3:],
                                  covs[:, 3:, 3:])
    with pytest.raises(ValueError, match='depth_ratio must be finite and > 0, got 0.0'):
        PoseDependentNoise(depth_ratio=0.0)


def test_innovation_check_counts_past_the_warm_up_against_the_chi_square_bound():
    from scipy.stats import chi2

    from body_schema.noise import innovation_check

    nis = chi2.rvs(6, size=20000, random_state=np.random.default_rng(2))
    c = innovation_check(np.concatenate([[1e6] * 5, nis]), skip=5, probability=0.99)
    assert c.count == 20000 and abs(c.median - chi2.median(6)) < 0.15
    assert abs(c.beyond - 200) < 45 and c.expected_beyond == pytest.approx(200)
    assert c.bound == pytest.approx(16.81, abs=0.01)
    assert 'beyond the 99.00% bound in' in c.text() and 'of 20000 (200.000 expected' in c.text()
    assert innovation_check([3.0, 4.0], skip=2) is None
    for kw, words in (({'skip': -1}, 'skip must be >= 0, got -1'), ({'probability': 1.0}, 'in \\(0, 1\\), got 1.0')):
        with pytest.raises(ValueError, match=words):
            innovation_check([1.0], **kw)


def test_innovation_check_p_values_match_their_distributions():
    """The tail p-value is the Poisson chance of as many exceedances; the median's is an upper
    bound of the chance of as high a median, checked by simulation."""
    from scipy.stats import chi2

    from body_schema.noise import InnovationCheck

    bound = float(chi2.ppf(0.9999, 6))
    assert InnovationCheck(40, 5.3, 0, 0.9999, bound).tail_p_value() == 1.0
    # one exceedance where 0.004 are expected: 1 - exp(-0.004)
    assert InnovationCheck(40, 5.3, 1, 0.9999, bound).tail_p_value() == pytest.approx(1 - np.exp(-0.004), rel=1e-9)
    rng = np.random.default_rng(3)
    medians = np.median(chi2.rvs(6, size=(20000, 40), random_state=rng), axis=1)
    for m in (6.0, 7.0, 8.0):
        simulated = np.mean(medians >= m)
        p = InnovationCheck(40, m, 0, 0.9999, bound).high_median_p_value()
        assert simulated <= p < 3 * simulated + 1e-3, (m, simulated, p)
    with pytest.raises(ValueError, match='alpha must be in \\(0, 1\\), got 2'):
        InnovationCheck(40, 5.3, 0, 0.9999, bound).cautions(alpha=2)
