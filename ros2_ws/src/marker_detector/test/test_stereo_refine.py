"""One hand pose from both eyes' marker corners (synthetic projections; no rendering)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body_schema import load_robot
from body_schema.markers import marker_corners
from body_schema.noise import PoseDependentNoise, stereo_covariance
from body_schema.robot import MarkerPlacement
from marker_detector.detection import (DetectedMarker, DetectorConfig, FrameResult, HandPoseEstimator, MarkerPose, StereoView,
                                       fuse_estimates, refine_stereo, solve_marker_pose)
from marker_detector.stereo import EyeResult, combine


@pytest.fixture(scope='module')
def icub():
    return load_robot('icub_right_arm')


def _scene(model, seed: int = 0):
    """A hand in front of the eyes, each marker facing the left eye seen by both eyes."""
    rng = np.random.default_rng(seed)
    eyes = {e: model.camera_pose(e) for e in ('left', 'right')}
    k = model.camera.K
    mid = 0.5 * (eyes['left'][:3, 3] + eyes['right'][:3, 3])
    for _ in range(200):
        hand = np.eye(4)
        hand[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        hand[:3, 3] = mid + eyes['left'][:3, :3] @ np.r_[rng.uniform(-0.03, 0.03, 2), 0.3]
        seen = {}
        for e, cam in eyes.items():
            cam_T_root = np.linalg.inv(cam)
            ms = []
            for m in model.markers:
                cam_T_m = cam_T_root @ hand @ m.hand_T_marker
                if cam_T_m[2, 2] > -0.5:          # must face the camera (its normal towards it)
                    continue
                pc = (cam_T_m @ np.c_[marker_corners(model.marker_side_length), np.ones(4)].T)[:3]
                uv = ((k @ pc)[:2] / pc[2]).T
                if np.all((uv > 5) & (uv < [model.camera.width - 5, model.camera.height - 5])):
                    ms.append((m.marker_id, uv))
            seen[e] = ms
        if seen['left'] and seen['right']:
            return hand, eyes, seen
    raise AssertionError('no hand pose seen by both eyes')


def _views(model, eyes, seen, noise: float = 0.0, seed: int = 1, shift: float = 0.0):
    rng = np.random.default_rng(seed)
    out = {}
    for e, ms in seen.items():
        poses = []
        for mid, uv in ms:
            uv = uv + rng.normal(0.0, noise, uv.shape) + (shift if e == 'right' else 0.0)
            poses.append(solve_marker_pose(DetectedMarker(mid, uv), model.marker_side_length, model.camera.K, None, True))
        out[e] = poses
    return out


def test_exact_corners_of_two_eyes_give_the_exact_pose_from_a_far_start(icub):
    hand, eyes, seen = _scene(icub)
    views = _views(icub, eyes, seen)
    start = hand.copy()
    start[:3, 3] += [0.004, -0.003, 0.01]
    start[:3, :3] = Rotation.from_rotvec([0.05, -0.03, 0.04]).as_matrix() @ hand[:3, :3]
    placements = {m.marker_id: m for m in icub.markers}
    pose, rms = refine_stereo(start, [StereoView(eyes[e], icub.camera.K, None, views[e]) for e in eyes],
                              placements, icub.marker_side_length)
    assert rms < 1e-6
    np.testing.assert_allclose(pose, hand, atol=1e-8)


def test_the_baseline_measures_the_depth_one_eye_guesses(icub):
    """Over noisy corners, the stereo estimate's position error is well below either eye's."""
    est = HandPoseEstimator(icub, PoseDependentNoise(), DetectorConfig())
    errs = {'left': [], 'stereo': []}
    for seed in range(30):
        hand, eyes, seen = _scene(icub, seed)
        views = _views(icub, eyes, seen, noise=0.3, seed=seed)
        results = []
        for e in ('left', 'right'):
            ok = [p for p in views[e] if p.ok]
            results.append((FrameResult(markers=ok, hand=est.combine(ok, icub.camera.K, None, eyes[e]),
                                        k=icub.camera.K), eyes[e]))
        if any(r.hand is None for r, _ in results):
            continue
        errs['left'].append(np.linalg.norm(results[0][0].hand.pose[:3, 3] - hand[:3, 3]))
        errs['stereo'].append(np.linalg.norm(est.stereo(results).pose[:3, 3] - hand[:3, 3]))
    assert len(errs['left']) >= 15
    assert np.median(errs['stereo']) < 0.5 * np.median(errs['left'])


def test_the_stereo_covariance_is_the_fused_one_scaled_by_the_law_ratios():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(2, 6, 6))
    covs = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(6)
    fused = np.linalg.inv(np.linalg.inv(covs[0]) + np.linalg.inv(covs[1]))
    np.testing.assert_allclose(stereo_covariance(covs, PoseDependentNoise(stereo_pos=1.0, stereo_rot=1.0)), fused,
                               rtol=1e-10)
    law = PoseDependentNoise(stereo_pos=0.25, stereo_rot=4.0)
    s = np.r_[0.5, 0.5, 0.5, 2.0, 2.0, 2.0]
    np.testing.assert_allclose(stereo_covariance(covs, law), fused * s[:, None] * s[None, :], rtol=1e-10)
    # Batched the same as one by one.
    batch = np.stack([covs, covs[::-1]])
    np.testing.assert_allclose(stereo_covariance(batch, law)[1], stereo_covariance(covs[::-1], law), rtol=1e-10)
    with pytest.raises(ValueError, match='shape'):
        stereo_covariance(covs[:1], law)
    with pytest.raises(ValueError, match='stereo_rot'):
        PoseDependentNoise(stereo_rot=0.0)


def test_the_detector_publishes_the_stereo_pose_and_keeps_the_fused_one_when_the_eyes_disagree(icub):
    law = PoseDependentNoise(stereo_pos=0.1, stereo_rot=1.5)
    est = HandPoseEstimator(icub, law, DetectorConfig())
    hand, eyes, seen = _scene(icub, 4)

    def entry(shift):
        views = _views(icub, eyes, seen, shift=shift)
        items = {}
        for e in ('left', 'right'):
            ok = [p for p in views[e] if p.ok]
            r = FrameResult(markers=ok, hand=est.combine(ok, icub.camera.K, None, eyes[e]), k=icub.camera.K)
            items[e] = EyeResult(e, f'{e}-header', r, eyes[e], 0.0)
        return items

    items = entry(0.0)
    _, _, out = combine(items, estimator=est)
    np.testing.assert_allclose(out.pose, hand, atol=1e-7)
    hands = [i.result.hand for i in items.values()]
    np.testing.assert_allclose(out.covariance, stereo_covariance(np.stack([h.covariance for h in hands]), law))
    fused = fuse_estimates(hands)
    assert np.isclose(out.pos_var, 0.1 * fused.pos_var) and np.isclose(out.rot_var, 1.5 * fused.rot_var)
    # Without the estimator (or a camera matrix), the eyes' poses fused as independent.
    np.testing.assert_allclose(combine(items)[2].pose, fused.pose)
    no_k = {e: replace(i, result=replace(i.result, k=None)) for e, i in items.items()}
    np.testing.assert_allclose(combine(no_k, estimator=est)[2].pose, fused.pose)
    # The right eye's corners 4 px off: no pose fits both images within the gate; fused kept.
    items = entry(4.0)
    _, _, out = combine(items, estimator=est)
    np.testing.assert_allclose(out.pose, fuse_estimates([i.result.hand for i in items.values()]).pose)
    with pytest.raises(ValueError, match='two'):
        est.stereo([(items['left'].result, eyes['left'])])


def test_a_failed_refinement_says_so():
    placements = {}
    with pytest.raises(ValueError, match='no marker corners'):
        refine_stereo(np.eye(4), [StereoView(np.eye(4), np.eye(3), None, [])], placements, 0.03)
    # A marker behind the camera: the solution is refused (infinite RMS), the start returned.
    placements = {1: MarkerPlacement('m1', 1, np.eye(4))}
    mp = MarkerPose(1, np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]), np.eye(4), None,
                    0.1, 1.0, 30.0, 0.3, 20.0)
    start = np.eye(4)
    start[2, 3] = -0.3
    k = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    pose, rms = refine_stereo(start, [StereoView(np.eye(4), k, None, [mp])], placements, 0.03)
    assert rms == float('inf') and np.array_equal(pose, start)
