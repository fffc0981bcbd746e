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


# --- the geometric visibility prior -------------------------------------------------------------

from body_schema.occlusion import VisibilityPrior  # noqa: E402
from body_schema.robot import CameraIntrinsics  # noqa: E402

CAM = CameraIntrinsics(320, 240, 250.0, 250.0, 159.5, 119.5)


def _marker_at(x, y, z, facing=True):
    """A marker at (x, y, z) in the camera frame (= root frame here), facing the camera or away."""
    m = np.eye(4)
    m[:3, 3] = [x, y, z]
    if facing:                      # z out of the face, pointing back at the camera
        m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    return m


@pytest.fixture
def prior():
    return VisibilityPrior(CAM)


def test_visibility_high_in_view_low_outside_behind_and_facing_away(prior):
    cam = np.eye(4)
    centre = prior.probability(cam, _marker_at(0.0, 0.0, 0.3)[None])
    assert centre == pytest.approx(prior.ceiling, abs=1e-3)
    outside = prior.probability(cam, _marker_at(0.3, 0.0, 0.3)[None])          # u = 160 + 250 = 410 > 320
    away = prior.probability(cam, _marker_at(0.0, 0.0, 0.3, facing=False)[None])
    behind = prior.probability(cam, _marker_at(0.0, 0.0, -0.3)[None])
    for p in (outside, away, behind):
        assert p == pytest.approx(prior.floor, abs=1e-3)
    # Any of several markers suffices; a batch of hands evaluates each.
    two = np.stack([_marker_at(0.0, 0.0, 0.3, facing=False), _marker_at(0.0, 0.0, 0.3)])
    batch = prior.probability(cam, np.stack([two, two[:1].repeat(2, 0)]))
    np.testing.assert_allclose(batch, [centre, away], atol=1e-12)


def test_visibility_falls_smoothly_across_the_image_edge(prior):
    cam = np.eye(4)
    xs = np.linspace(0.0, 0.3, 31)
    p = prior.probability(cam, np.stack([_marker_at(x, 0.0, 0.3) for x in xs])[:, None])
    assert np.all(np.diff(p) <= 1e-12) and p[0] > 0.85 and p[-1] < 0.05
    # Half-way where the margin is exactly met: u = W - margin W.
    x_half = (CAM.width * (1 - prior.margin) - CAM.cx) * 0.3 / CAM.fx
    mid = prior.probability(cam, _marker_at(x_half, 0.0, 0.3)[None])
    assert mid == pytest.approx(prior.floor + 0.5 * (prior.ceiling - prior.floor), abs=1e-6)


def test_an_uncertain_estimate_softens_the_prediction(prior):
    cam = np.eye(4)
    outside = _marker_at(0.2, 0.0, 0.3)[None]                                 # about 10 px out of view
    sure = prior.probability(cam, outside)
    unsure = prior.probability(cam, outside, position_std=0.05)
    assert sure < 0.05 < 0.2 < unsure < 0.5
    turned = _marker_at(0.0, 0.0, 0.3)
    turned[:3, :3] = turned[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(1.4), -np.sin(1.4)],
                                                [0, np.sin(1.4), np.cos(1.4)]])   # phi = 80 deg
    assert prior.probability(cam, turned[None]) < prior.probability(cam, turned[None], orientation_std_deg=30.0)


def test_a_near_marker_must_lie_further_inside_with_marker_widths():
    """``margin_marker_widths``: the margin grows with the marker's projected width, so the half-way
    point moves in by that many widths (a near marker's corners leave the image first)."""
    cam, side, z, k = np.eye(4), 0.03, 0.2, 0.5
    sized = VisibilityPrior(CAM, margin=0.02, marker_side=side, margin_marker_widths=k)
    # Where the marker's distance from the border is the margin plus k head-on widths (fx side / r).
    from scipy.optimize import brentq

    x_half = brentq(lambda x: (CAM.width - (CAM.fx * x / z + CAM.cx)) - 0.02 * CAM.width
                    - k * CAM.fx * side / np.hypot(x, z), 0.0, 0.15)
    mid = sized.probability(cam, _marker_at(x_half, 0.0, z)[None])
    assert mid == pytest.approx(sized.floor + 0.5 * (sized.ceiling - sized.floor), abs=1e-6)
    # Without the widths, the same marker lies well inside the margin; far away the two agree.
    assert VisibilityPrior(CAM, margin=0.02, marker_side=side).probability(cam, _marker_at(x_half, 0.0, z)[None]) \
        > sized.ceiling - 0.01
    far = _marker_at(0.8, 0.0, 2.0)[None]
    assert sized.probability(cam, far) == pytest.approx(
        VisibilityPrior(CAM, margin=0.02, marker_side=side).probability(cam, far), abs=0.02)
    with pytest.raises(ValueError, match='margin_marker_widths needs marker_side'):
        VisibilityPrior(CAM, margin_marker_widths=0.5)
    with pytest.raises(ValueError, match='margin_marker_widths must be finite and >= 0, got -1'):
        VisibilityPrior(CAM, marker_side=side, margin_marker_widths=-1.0)


@pytest.mark.parametrize('field, value', [('max_view_angle_deg', 0.0), ('margin_softness', -1.0),
                                          ('margin', float('nan')), ('floor', 0.0), ('ceiling', 1.0)])
def test_bad_visibility_settings_name_the_value(field, value):
    with pytest.raises(ValueError, match=field if field not in ('floor', 'ceiling') else 'floor < ceiling'):
        VisibilityPrior(CAM, **{field: value})


def test_prior_mean_replaces_the_flat_one_with_the_same_strength():
    m = OcclusionModel(BOX, length_scale=0.1, a0=1.0, b0=2.0)
    t = np.array([0.0, 1.0, 0.0])
    assert m.mean(t, prior=0.8) == pytest.approx(0.8)
    np.testing.assert_allclose(m.mean(np.stack([t, t]), prior=np.array([0.2, 0.9])), [0.2, 0.9])
    m.add(t, False)
    # One failure at t against a prior of strength a0 + b0 = 3.
    assert m.mean(t, prior=0.8) == pytest.approx(3 * 0.8 / (3 + 1))
    assert m.mean(t) == pytest.approx(1.0 / 4.0)



def _attempted(q, seen):
    m = OcclusionModel(BOX, length_scale=0.1, a0=1.0, b0=2.0)
    for theta, ok in zip(q, seen):
        m.add(theta, ok)
    return m


def test_attempts_are_kept_in_order_beside_the_merged_counts():
    m = OcclusionModel(BOX)
    t1, t2 = np.array([0.0, 1.0, 0.0]), np.array([0.5, 0.5, 0.1])
    for theta, ok in ((t1, True), (t2, False), (t1, False)):
        m.add(theta, ok)
    q, seen = m.attempts
    np.testing.assert_array_equal(q, [t1, t2, t1])
    np.testing.assert_array_equal(seen, [True, False, False])
    assert m.n_configs == 2


def test_geometric_evidence_trusts_predictions_that_come_true():
    rng = np.random.default_rng(3)
    q = BOX[:, 0] + rng.random((40, 3)) * (BOX[:, 1] - BOX[:, 0])
    p = rng.uniform(0.02, 0.9, 40)
    seen = rng.random(40) < p                              # outcomes drawn from the prediction
    assert _attempted(q, seen).geometric_evidence(p) > 0.95
    assert _attempted(q, ~seen).geometric_evidence(p) < 0.01        # the opposite outcomes
    assert _attempted(q[:0], seen[:0]).geometric_evidence(p[:0]) == pytest.approx(0.5)
    # Repeated failures where geometry expects the hand: two far-apart misses outweigh even odds.
    far = _attempted(BOX.T, [False, False])
    assert far.geometric_evidence([0.9, 0.9]) < 0.2
    # The same misses next to each other: the kernel predicts the second, so it costs geometry less.
    near = _attempted(np.stack([BOX[:, 0], BOX[:, 0] + 1e-3]), [False, False])
    assert near.geometric_evidence([0.9, 0.9]) > far.geometric_evidence([0.9, 0.9])
    with pytest.raises(ValueError, match=r'\(0, 1\).*1\.0'):
        _attempted(q[:1], [True]).geometric_evidence([1.0])
    with pytest.raises(ValueError, match=r'one entry per recorded attempt \(2\), got 1'):
        _attempted(q[:2], [True, True]).geometric_evidence([0.5])
