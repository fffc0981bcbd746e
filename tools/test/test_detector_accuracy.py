"""The study's noise fit recovers a known law; evaluation compares with the truth correctly."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema import load_robot
from body_schema.noise import PoseDependentNoise
from tools.detector_accuracy import Frame, FrameScores, _fit_law, draw_scores, evaluate, fit_noise, summarize
from marker_detector.detection import DetectedMarker, HandPoseEstimator, solve_marker_pose


def _draw(law: PoseDependentNoise, n: int, seed: int) -> FrameScores:
    return draw_scores(law, n, seed)


def test_fit_recovers_known_law() -> None:
    truth = PoseDependentNoise(a_pos=4e-4, b_pos=2e-8, a_rot=2e-2, b_rot=5e-7, floor_pos=2e-6, floor_rot=1e-5)
    fit = fit_noise(_draw(truth, 4000, 0))
    for name in ('a_pos', 'b_pos', 'a_rot', 'b_rot'):
        assert getattr(fit.pdn, name) == pytest.approx(getattr(truth, name), rel=0.25), name
    # The pose-dependent law explains the data better than a constant one, and is calibrated.
    assert fit.nll_pdn < fit.nll_cn
    assert fit.coverage_pdn[0] == pytest.approx(0.95, abs=0.02)
    assert fit.coverage_pdn[1] == pytest.approx(0.95, abs=0.02)
    # CN is the root-mean-square per-axis error.
    out = _draw(truth, 4000, 0)
    assert fit.cn.sigma_pos == pytest.approx(np.sqrt(np.mean(out.pos_err ** 2) / 3))


def test_fit_zero_coefficient_is_zero() -> None:
    rng = np.random.default_rng(1)
    r, phi = rng.uniform(0.15, 0.5, 3000), rng.uniform(0, 85, 3000)
    v = 3e-4 * r ** 2                                     # no angle dependence, no floor
    sq = (rng.normal(size=(3000, 3)) ** 2).sum(1) * v
    coef, _ = _fit_law(sq, r, phi, min_floor=1e-8)
    assert coef[0] == pytest.approx(3e-4, rel=0.1)
    assert coef[1] * 45 ** 2 < 0.15 * 3e-4 * 0.3 ** 2     # small against the distance term
    assert coef[2] >= 1e-8 and coef[2] < 0.05 * 3e-4 * 0.3 ** 2


def test_evaluate_measures_against_truth() -> None:
    """A frame whose marker pose is exact gives zero error; a shifted truth gives that shift."""
    import cv2
    from body_schema.markers import marker_corners
    from marker_detector.synthetic import look_at_pose

    model = load_robot('icub_right_arm')
    k = model.camera.K
    cam_T_m = look_at_pose(0.25, 40.0)
    proj, _ = cv2.projectPoints(marker_corners(model.marker_side_length),
                                cv2.Rodrigues(cam_T_m[:3, :3])[0], cam_T_m[:3, 3], k, np.zeros(5))
    pose = solve_marker_pose(DetectedMarker(0, proj.reshape(4, 2)), model.marker_side_length, k)
    root_T_cam = model.camera_pose('left')
    truth = root_T_cam @ cam_T_m @ np.linalg.inv(model.markers[0].hand_T_marker)
    shifted = truth.copy()
    shifted[:3, 3] += [0.003, 0.0, -0.004]
    frames = [Frame(0, 'left', (320, 240), k, root_T_cam, t, [pose], {0: (0.25, 40.0, True)}, 1e-3)
              for t in (truth, shifted)]
    out = evaluate(frames, HandPoseEstimator(model, PoseDependentNoise()))
    assert out.success.all() and out.n_markers.tolist() == [1, 1]
    assert out.pos_err[0] < 1e-6 and out.pos_err[1] == pytest.approx(0.005, abs=1e-6)
    assert out.r.tolist() == [0.25, 0.25]
    s = summarize(out, frames)
    assert s['success'] == 1.0 and s['time_med_ms'] == pytest.approx(1.0)
