"""Accuracy study of the detector against ground truth in the simulator (pure; no rclpy).

For uniformly drawn configurations of the robot description's calibration box, the simulator's
PyBullet world (:class:`icub_sim_bridge.world.SimWorld`, built with the nominal DH table, so the
true hand pose is the description's forward kinematics) renders the eye images; the detector
estimates the hand pose and the study measures

* detection rate (over all configurations, and over those where a marker faces the camera
  inside the image), median and 95th-percentile hand position [mm] and orientation [deg] errors,
* the error as a function of marker distance ``r`` and viewing angle ``phi``,
* the time of detection plus pose per frame,
* single eye vs stereo fusion, and the fusion modes when two markers are accepted in one image,
* a sweep of the ambiguity gate,

and fits the noise model (paper eq. 13, one law for position and one for orientation) to the
squared errors by maximum likelihood. Frames are rendered once and re-evaluated under every
setting, since gating and fusion work on the stored ungated marker poses.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize, nnls

from body_schema.map_estimator import pose_residuals
from body_schema.markers import marker_corners
from body_schema.noise import ConstantNoise, NoiseModel, PoseDependentNoise, view_geometry
from body_schema.robot import ArmModel

from marker_detector.detection import DetectorConfig, FrameResult, HandPoseEstimator, MarkerPose, gate_marker

__all__ = ['FLIP_DEG', 'Frame', 'FrameScores', 'NoiseFit', 'collect', 'draw_scores', 'evaluate', 'eye_result',
           'fit_noise', 'summarize', 'time_frames', 'binned']


@dataclass
class Frame:
    """One rendered image and what the detector found in it (ungated marker poses).

    ``truth_view`` maps marker id to ``(r [m], phi [deg], in_image)`` from the true geometry.
    """

    config: int
    eye: str
    size: tuple[int, int]
    k: NDArray[np.float64]
    root_T_cam: NDArray[np.float64]
    truth: NDArray[np.float64]
    poses: list[MarkerPose]
    truth_view: dict[int, tuple[float, float, bool]]
    seconds: float
    gray: NDArray[np.uint8] | None = None


@dataclass
class FrameScores:
    """Per-frame results of one evaluation (arrays of length N frames).

    ``r``/``phi`` are the true distance and viewing angle of the marker the estimate relies on
    most (the one with the smallest predicted variance); NaN on failure.
    """

    success: NDArray[np.bool_]
    in_view: NDArray[np.bool_]
    pos_err: NDArray[np.float64]          # [m]
    rot_err: NDArray[np.float64]          # [rad]
    pos_vec: NDArray[np.float64]          # (N, 3) [m]
    rot_vec: NDArray[np.float64]          # (N, 3) [rad], root frame
    r: NDArray[np.float64]
    phi: NDArray[np.float64]
    n_markers: NDArray[np.int64]
    statuses: dict[str, int] = field(default_factory=dict)
    #: (N, 3) line of sight from the camera to the marker the estimate relies on most, root frame
    #: (None where not recorded, e.g. drawn errors).
    los: NDArray[np.float64] | None = None


def _truth_view(frame_root_T_cam: NDArray[np.float64], truth: NDArray[np.float64], model: ArmModel,
                k: NDArray[np.float64], size: tuple[int, int]) -> dict[int, tuple[float, float, bool]]:
    out = {}
    cam_T_root = np.linalg.inv(frame_root_T_cam)
    corners = np.c_[marker_corners(model.marker_side_length), np.ones(4)].T
    for m in model.markers:
        cam_T_m = cam_T_root @ truth @ m.hand_T_marker
        r, phi = view_geometry(np.eye(4), cam_T_m)
        pc = (cam_T_m @ corners)[:3]
        inside = bool(np.all(pc[2] > 0.01))
        if inside:
            uv = (k @ pc)[:2] / pc[2]
            inside = bool(np.all((uv[0] >= 0) & (uv[0] <= size[0] - 1) & (uv[1] >= 0) & (uv[1] <= size[1] - 1)))
        out[m.marker_id] = (float(r), float(phi), inside and float(phi) < 80.0)
    return out


def collect(model: ArmModel, world: Any, configs: NDArray[np.float64],
            views: Sequence[tuple[str, tuple[int, int]]], noise_std: float = 0.0, seed: int = 0,
            config: DetectorConfig | None = None, keep_images: int = 0) -> list[Frame]:
    """Render every configuration in every view and run detection plus pose on it.

    Parameters
    ----------
    model : ArmModel
    world : icub_sim_bridge.world.SimWorld
        Built from ``model`` with its nominal DH table.
    configs : ndarray, shape (N, L)
    views : sequence of (eye, (width, height))
    noise_std : float
        Additive Gaussian pixel noise [grey levels] (seeded), on top of the renderer's image.
    config : DetectorConfig, optional
        Used for the timed run (the study re-gates afterwards).
    keep_images : int
        Keep the grey image of the first ``keep_images`` configurations (for :func:`time_frames`).

    Returns
    -------
    list of Frame, configuration-major.
    """
    est = HandPoseEstimator(model, PoseDependentNoise.for_robot(model), config or DetectorConfig())
    rng = np.random.default_rng(seed)
    frames = []
    cams = {(eye, size): (model.camera.scaled(*size), model.camera_pose(eye)) for eye, size in views}
    for i, q in enumerate(configs):
        world.set_joint_positions(q)
        truth = model.forward_kinematics(q)
        for eye, size in views:
            intr, root_T_cam = cams[(eye, size)]
            rgb = world.render(root_T_cam, intr)
            if noise_std > 0:
                noisy = rgb.astype(np.float32) + rng.normal(0.0, noise_std, rgb.shape).astype(np.float32)
                rgb = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
            t0 = time.perf_counter()
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            res = est.process(gray, intr.K, None, root_T_cam)
            dt = time.perf_counter() - t0
            poses = [p if p.status == 'invalid' else replace(p, status='ok')
                     for p in res.markers + res.rejected]
            frames.append(Frame(i, eye, size, intr.K, root_T_cam, truth, poses,
                                _truth_view(root_T_cam, truth, model, intr.K, size), dt,
                                gray if i < keep_images else None))
    return frames


def time_frames(frames: Sequence[Frame], estimator: HandPoseEstimator, repeats: int = 3) -> NDArray[np.float64]:
    """Seconds of grey conversion plus :meth:`HandPoseEstimator.process` per kept image.

    Each image is processed ``repeats`` times and the fastest run kept, so that another process
    pre-empting this one does not count as detector time.
    """
    out = []
    for f in frames:
        if f.gray is None:
            continue
        rgb = np.ascontiguousarray(np.repeat(f.gray[..., None], 3, axis=2))
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            estimator.process(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), f.k, None, f.root_T_cam)
            best = min(best, time.perf_counter() - t0)
        out.append(best)
    return np.array(out)


def eye_result(frame: Frame, estimator: HandPoseEstimator) -> tuple[FrameResult, NDArray[np.float64]]:
    """A stored frame gated and combined by ``estimator``, as the detector node holds one eye's
    result of a stamp (accepted markers, hand or None, camera matrix), with the eye's camera pose:
    one element of :meth:`HandPoseEstimator.stereo`'s ``views``."""
    gated = [gate_marker(p, estimator.config) for p in frame.poses]
    hand = estimator.combine(gated, frame.k, None, frame.root_T_cam)
    return FrameResult(markers=[p for p in gated if p.ok], hand=hand, k=frame.k), frame.root_T_cam


def evaluate(frames: Sequence[Frame], estimator: HandPoseEstimator, fusion: str | None = None) -> FrameScores:
    """Gate and fuse stored frames with ``estimator``'s settings; compare with the truth."""
    n = len(frames)
    out = FrameScores(np.zeros(n, bool), np.zeros(n, bool), np.full(n, np.nan), np.full(n, np.nan),
                  np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full(n, np.nan),
                  np.full(n, np.nan), np.zeros(n, np.int64))
    statuses: dict[str, int] = {}
    out.los = np.full((n, 3), np.nan)
    for i, f in enumerate(frames):
        out.in_view[i] = any(v[2] for v in f.truth_view.values())
        gated = [gate_marker(p, estimator.config) for p in f.poses]
        for p in gated:
            statuses[p.status] = statuses.get(p.status, 0) + 1
        hand = estimator.combine(gated, f.k, None, f.root_T_cam, fusion)
        if hand is None:
            continue
        out.success[i] = True
        out.n_markers[i] = sum(p.ok for p in gated)
        err = pose_residuals(hand.pose[None], f.truth[None])[0]      # estimate minus truth, root frame
        out.pos_vec[i], out.rot_vec[i] = err[:3], err[3:]
        out.pos_err[i] = np.linalg.norm(out.pos_vec[i])
        out.rot_err[i] = np.linalg.norm(out.rot_vec[i])
        # The marker the estimate relies on most: smallest predicted variance among those used.
        used = [p for p in gated if p.ok and p.marker_id in hand.marker_ids]
        best = min(used, key=lambda p: float(estimator.quality.variances(p.r, p.phi_deg)[0]))
        out.r[i], out.phi[i] = f.truth_view[best.marker_id][:2]
        out.los[i] = (f.truth @ estimator.placements[best.marker_id].hand_T_marker)[:3, 3] - f.root_T_cam[:3, 3]
    out.statuses = statuses
    return out


# --------------------------------------------------------------------------------------------
# Noise-model fit


@dataclass(frozen=True)
class NoiseFit:
    """Fitted noise laws and how well they describe the errors.

    ``pdn`` holds the pose-dependent model, ``cn`` the constant one; ``nll_*`` are the mean
    negative log-likelihoods per sample (position and orientation blocks added; lower is
    better); ``coverage_*`` the fraction of samples inside the 95 % chi-square(3) ellipsoid
    for each block (0.95 for a calibrated model).
    """

    pdn: PoseDependentNoise
    cn: ConstantNoise
    n: int
    nll_pdn: float
    nll_cn: float
    coverage_pdn: tuple[float, float]
    coverage_cn: tuple[float, float]


#: Smallest floors the fit may use: (0.1 mm)^2 and (0.03 deg)^2, far below any measured noise,
#: so ``R`` stays positive definite even where the data put the floor at zero.
MIN_FLOOR_POS = 1e-8
MIN_FLOOR_ROT = float(np.radians(0.03) ** 2)


def _fit_law(sq: NDArray[np.float64], r: NDArray[np.float64], phi: NDArray[np.float64],
             min_floor: float, dof: int = 3) -> tuple[NDArray[np.float64], float]:
    """ML fit of ``v = a r^2 + b (phi-45)^2 + floor`` to squared error norms ``sq ~ v chi2(dof)``.

    Returns the coefficients (a, b, floor), with ``floor >= min_floor`` and a term set to exactly
    zero when it contributes less than 0.1 % of the median variance, and the mean negative
    log-likelihood per sample.
    """
    design = np.c_[r ** 2, (phi - 45.0) ** 2, np.ones_like(r)]
    # Start from non-negative least squares on sq / dof (unbiased for v but dominated by the
    # largest errors), then maximise the Gaussian likelihood, which weights each sample by 1/v.
    x0, _ = nnls(design, sq / dof)
    typical = max(float(np.median(sq / dof)), min_floor)
    scale = np.maximum(np.median(design, axis=0), 1e-12)
    x0 = np.maximum(x0, 1e-3 * typical / scale)

    def variance(logx: NDArray[np.float64]) -> NDArray[np.float64]:
        return design @ np.exp(logx) + min_floor

    def nll(logx: NDArray[np.float64]) -> float:
        v = variance(logx)
        return float(np.mean(0.5 * dof * np.log(v) + 0.5 * sq / v))

    lo = np.log(1e-9 * typical / scale)
    hi = np.log(1e3 * typical / scale)
    best = minimize(nll, np.clip(np.log(x0), lo, hi), method='L-BFGS-B', bounds=list(zip(lo, hi)))
    coef = np.exp(best.x)
    coef[coef * scale < 1e-3 * np.median(variance(best.x))] = 0.0      # negligible terms
    coef[2] += min_floor
    v = design[:, :2] @ coef[:2] + coef[2]
    return coef, float(np.mean(0.5 * dof * np.log(v) + 0.5 * sq / v))


def _gauss_nll(sq: NDArray[np.float64], v: NDArray[np.float64], dof: int = 3) -> float:
    return float(np.mean(0.5 * dof * np.log(2 * np.pi * v) + 0.5 * sq / v))


#: Orientation error beyond which an estimate is a planar flip (a gross outlier), not noise [deg].
FLIP_DEG = 30.0


def depth_split(outcome: FrameScores, ok: NDArray[np.bool_]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Squared position errors across the line of sight (2 axes) and along it (1), frames ``ok``."""
    if outcome.los is None:
        raise ValueError('these scores have no line of sight (FrameScores.los): rendered frames are needed')
    unit = outcome.los[ok] / np.linalg.norm(outcome.los[ok], axis=1, keepdims=True)
    along = np.einsum('ni,ni->n', outcome.pos_vec[ok], unit) ** 2
    return np.maximum(outcome.pos_err[ok] ** 2 - along, 0.0), along


def position_chi2(model: NoiseModel, outcome: FrameScores, ok: NDArray[np.bool_],
                  vp: NDArray[np.float64]) -> NDArray[np.float64]:
    """``e^T R_p^-1 e`` of the frames ``ok`` (chi-square(3) for a calibrated law), ``vp`` the law's
    variance across the line of sight; along it ``depth_ratio^2`` times that."""
    if model.depth_ratio == 1.0:
        return outcome.pos_err[ok] ** 2 / vp
    across, along = depth_split(outcome, ok)
    return across / vp + along / (model.depth_ratio ** 2 * vp)


def fit_noise(outcome: FrameScores, exclude_flips: bool = True, depth: bool = False) -> NoiseFit:
    """Fit the pose-dependent and constant models to the successful frames of ``outcome``.

    With ``exclude_flips`` the gross outliers (orientation error above :data:`FLIP_DEG`: the
    wrong IPPE solution got through the ambiguity gate) are left out: a Gaussian covariance
    cannot describe them, and one 150-degree flip would otherwise set the orientation law's
    scale for every observation. Their rate is reported separately.

    With ``depth`` the position law is fitted to the errors across the line of sight (2 dof) and
    its ``depth_ratio`` to those along it, by maximum likelihood: ``k^2 = mean(e_along^2 / v)``.
    """
    ok = outcome.success & np.isfinite(outcome.r)
    if exclude_flips:
        ok &= np.degrees(outcome.rot_err) <= FLIP_DEG
    r, phi = outcome.r[ok], outcome.phi[ok]
    sq_p = outcome.pos_err[ok] ** 2
    sq_o = outcome.rot_err[ok] ** 2
    across, along = depth_split(outcome, ok) if depth else (sq_p, None)
    (ap, bp, fp), _ = _fit_law(across, r, phi, MIN_FLOOR_POS, dof=2 if depth else 3)
    (ao, bo, fo), _ = _fit_law(sq_o, r, phi, MIN_FLOOR_ROT)
    pdn = PoseDependentNoise(ap, bp, ao, bo, fp, fo)
    if depth:
        pdn = replace(pdn, depth_ratio=float(np.sqrt(np.mean(along / pdn.variances(r, phi)[0]))))
    cn = ConstantNoise(float(np.sqrt(np.mean(sq_p) / 3)), float(np.sqrt(np.mean(sq_o) / 3)))
    chi95 = 7.814727903251178                       # chi-square(3) 95 % quantile

    def score(model: NoiseModel) -> tuple[float, tuple[float, float]]:
        vp, vo = (np.broadcast_to(v, r.shape) for v in model.variances(r, phi))
        zp = position_chi2(model, outcome, ok, vp)
        # Gaussian NLL of the position block: 3 log(2 pi v) + log(k^2) over 2, plus zp over 2.
        nll_p = float(np.mean(0.5 * 3 * np.log(2 * np.pi * vp) + np.log(model.depth_ratio) + 0.5 * zp))
        return (nll_p + _gauss_nll(sq_o, vo),
                (float(np.mean(zp <= chi95)), float(np.mean(sq_o / vo <= chi95))))

    nll_pdn, cov_pdn = score(pdn)
    nll_cn, cov_cn = score(cn)
    return NoiseFit(pdn, cn, int(ok.sum()), nll_pdn, nll_cn, cov_pdn, cov_cn)


def draw_scores(law: NoiseModel, n: int, seed: int, r_range: tuple[float, float] = (0.15, 0.5)) -> FrameScores:
    """``n`` successful frames whose errors are drawn from ``law`` (a known truth for the fits),
    at distances uniform in ``r_range`` [m] and viewing angles uniform in 0-85 deg, each seen along
    a random line of sight (the law's ``depth_ratio`` stretches the position error along it)."""
    rng = np.random.default_rng(seed)
    r, phi = rng.uniform(*r_range, n), rng.uniform(0, 85, n)
    vp, vo = (np.broadcast_to(v, r.shape) for v in law.variances(r, phi))
    los = rng.normal(size=(n, 3))
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    pv = rng.normal(size=(n, 3)) * np.sqrt(vp)[:, None]
    pv += (law.depth_ratio - 1.0) * np.einsum('ni,ni->n', pv, los)[:, None] * los
    ov = rng.normal(size=(n, 3)) * np.sqrt(vo)[:, None]
    ones = np.ones(n, bool)
    return FrameScores(ones, ones, np.linalg.norm(pv, axis=1), np.linalg.norm(ov, axis=1), pv, ov, r, phi,
                       np.ones(n, np.int64), los=los)


# --------------------------------------------------------------------------------------------
# Summaries


def summarize(outcome: FrameScores, frames: Sequence[Frame] | None = None) -> dict[str, float]:
    """Headline figures: rates, median/p95 errors [mm, deg], time per frame [ms]."""
    s = outcome.success
    pe, re = outcome.pos_err[s] * 1e3, np.degrees(outcome.rot_err[s])
    q = lambda a, p: float(np.percentile(a, p)) if a.size else float('nan')  # noqa: E731
    out = {
        'frames': float(len(s)),
        'flips': float(np.sum(re > FLIP_DEG)),
        'success': float(s.mean()) if len(s) else float('nan'),
        'success_in_view': float(s[outcome.in_view].mean()) if outcome.in_view.any() else float('nan'),
        'in_view': float(outcome.in_view.mean()) if len(s) else float('nan'),
        'pos_med_mm': q(pe, 50), 'pos_p95_mm': q(pe, 95),
        'rot_med_deg': q(re, 50), 'rot_p95_deg': q(re, 95),
    }
    if frames is not None:
        t = np.array([f.seconds for f in frames]) * 1e3
        out.update(time_med_ms=q(t, 50), time_p95_ms=q(t, 95))
    return out


def binned(outcome: FrameScores, key: str, edges: Sequence[float]) -> list[tuple[str, int, float, float]]:
    """Median position [mm] and orientation [deg] errors per bin of ``r`` [m] or ``phi`` [deg]."""
    vals = getattr(outcome, key)
    s = outcome.success & np.isfinite(vals)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = s & (vals >= lo) & (vals < hi)
        label = f'{lo:g}-{hi:g}'
        if m.sum() == 0:
            rows.append((label, 0, float('nan'), float('nan')))
        else:
            rows.append((label, int(m.sum()), float(np.median(outcome.pos_err[m]) * 1e3),
                         float(np.degrees(np.median(outcome.rot_err[m])))))
    return rows


def main(argv: Sequence[str] | None = None) -> str:
    """``python -m tools.detector_accuracy``: the study's command line is :mod:`tools.detector_bench`'s."""
    from tools.detector_bench import main as bench_main

    return bench_main(argv)


if __name__ == '__main__':
    import sys

    print(main(sys.argv[1:]))
