"""The kernel-smoothed Beta occlusion model against the paper's formula (eq. finalbeta)."""
import numpy as np
import pytest

from body_schema.occlusion import OcclusionModel

BOX = np.array([[-1.0, 1.0], [0.0, 2.0], [-0.5, 0.5]])


def test_prior_mean_without_data():
    m = OcclusionModel(BOX, length_scale=0.1, a0=2.0, b0=1.0)
    assert m.mean(np.zeros(3)) == pytest.approx(2.0 / 3.0)
    assert m.mean(np.zeros((5, 3))).shape == (5,)


def test_mean_at_visited_point_and_far_away():
    a0, b0, ls = 1.0, 1.0, 0.1
    m = OcclusionModel(BOX, length_scale=ls, a0=a0, b0=b0)
    t1, t2 = np.array([0.0, 1.0, 0.0]), np.array([0.1, 1.0, 0.0])
    m.add(t1, True)
    m.add(t1, True)
    m.add(t2, False)
    assert m.n_configs == 2
    # At t1: K(t1, t1) = 1; K(t1, t2) from the normalised distance 0.1 / 2 = 0.05.
    k12 = np.exp(-0.5 * 0.05 ** 2 / ls ** 2)
    s, u = 2.0 * 1.0, 1.0 * k12
    assert m.mean(t1) == pytest.approx((s + a0) / (s + a0 + u + b0))
    # Far away, the kernels vanish and the prior mean returns.
    far = np.array([1.0, 0.0, 0.5])
    assert m.mean(far) == pytest.approx(a0 / (a0 + b0), abs=1e-6)
    # Batched queries equal single ones.
    q = np.stack([t1, t2, far])
    np.testing.assert_allclose(m.mean(q), [m.mean(t1), m.mean(t2), m.mean(far)])


def test_failures_lower_the_mean_locally():
    m = OcclusionModel(BOX)
    t = np.array([0.5, 0.5, 0.1])
    for _ in range(5):
        m.add(t, False)
    assert m.mean(t) < 0.2
    assert m.mean(t + np.array([0.02, 0.0, 0.0])) < 0.5 < m.mean(np.array([-0.9, 1.9, -0.4])) + 1e-6


def test_bad_inputs():
    with pytest.raises(ValueError, match='length_scale'):
        OcclusionModel(BOX, length_scale=0.0)
    with pytest.raises(ValueError, match='min < max'):
        OcclusionModel(np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match='finite'):
        OcclusionModel(BOX).add([0.0, np.nan, 0.0], True)
