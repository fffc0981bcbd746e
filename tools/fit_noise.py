"""Fit a robot description's observation-noise law to its own camera and marker, in the simulator.

The pose-dependent law (:class:`body_schema.noise.PoseDependentNoise`, paper eq. 13) depends only
on the camera-to-marker distance and viewing angle, so its coefficients belong to one camera
(resolution, focal length) and one marker size: the defaults were fitted on the iCub's 320x240
eyes and 3 cm markers and are about ten times too pessimistic (in standard deviation) for a
1280x1024 camera watching an 8 cm marker at 1.7 m. This command renders uniform configurations of
the description's calibration box with its cameras at their native resolution, runs the detector
on them, measures the hand-pose error against the true forward kinematics and fits the law by
maximum likelihood (:func:`tools.detector_accuracy.fit_noise`). It prints the ``noise_model:``
block to paste into the description's YAML, which the detector and the selector then use
(``pdn_*`` parameters left negative), and how well each law describes the errors.

Usage (from the repository root)::

    python -m tools.fit_noise --robot ur5e --n 300 --seed 1 [--pixel-noise 0.0] [--depth] [--loss-scale] [--out FILE]

``--pixel-noise`` should be what the simulator node adds (its ``pixel_noise_std``, 0 by default);
on a real camera fit to the simulator with the noise your images show, or keep the defaults and
check the NEES the estimator reports.

A robot with two eyes also gets the law's stereo ratios (:func:`stereo_ratios`): on the
configurations both eyes see the hand, the error of the detector's stereo estimate (both images'
corners in one refinement) over the eyes' fused variances, which the detector and the selector
then scale the fused covariance by (:func:`body_schema.noise.stereo_covariance`).

The law is the errors' variance; heavy-tailed errors are typically much smaller than it says.
The report gives their typical size in the law's standard deviations (:func:`typical_spread`),
and ``--loss-scale`` adds the MAP estimator's ``loss_scale`` for it to the block
(:func:`loss_scale_for`), so that the robust loss departs from the square at 3 typical errors.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from body_schema.map_estimator import LOSS_SCALE_RANGE, MapSettings, pose_residuals
from body_schema.noise import ConstantNoise, NoiseModel, PoseDependentNoise, stereo_covariance
from body_schema.robot import NOISE_LAW_KEYS, ArmModel, load_robot
from body_schema.sampling import uniform_configs

from marker_detector.detection import DetectorConfig, HandPoseEstimator, fuse_estimates
from tools.detector_accuracy import (FLIP_DEG, Frame, FrameScores, NoiseFit, collect, evaluate, eye_result, fit_noise,
                                     position_chi2, summarize)

__all__ = ['views_of', 'law_yaml', 'calibration_of', 'tails', 'typical_spread', 'loss_scale_for', 'shape', 'stereo_ratios',
           'main']

CHI2_3_95 = 7.814727903251178                   # chi-square(3) 95 % quantile


def views_of(model: ArmModel) -> list[tuple[str, tuple[int, int]]]:
    """Every camera of the description (eyes and fixed cameras) at its native resolution."""
    if model.camera is None:
        raise ValueError(f'robot {model.name!r} has no camera intrinsics to render with')
    size = (model.camera.width, model.camera.height)
    names = sorted(model.fixed_cameras) + (sorted(model.eyes.links) if model.eyes is not None else [])
    if not names:
        raise ValueError(f'robot {model.name!r} has no camera (neither eyes nor fixed_cameras)')
    return [(name, size) for name in names]


def law_yaml(law: PoseDependentNoise, comment: str, covariance: str = '', loss_scale: float = 0.0,
             stereo: bool = False) -> str:
    """The ``noise_model:`` block of a robot description for ``law`` (3 significant digits), with the
    estimator's ``covariance`` and ``loss_scale`` where given, and the stereo ratios with ``stereo``
    (a robot with two eyes)."""
    skip = {'stereo_pos', 'stereo_rot'} if not stereo else set()
    if law.depth_ratio == 1.0:
        skip.add('depth_ratio')            # the isotropic law
    body = ', '.join([f'{k}: {getattr(law, k):.3g}' for k in NOISE_LAW_KEYS if k not in skip]
                     + ([f'covariance: {covariance}'] if covariance else [])
                     + ([f'loss_scale: {loss_scale:.2g}'] if loss_scale > 0 else []))
    return f'# {comment}\nnoise_model: {{{body}}}\n'


def _normalised(model: NoiseModel, out: FrameScores) -> tuple[np.ndarray, np.ndarray]:
    """Squared position and orientation errors over ``model``'s variances, flips excluded."""
    ok = out.success & np.isfinite(out.r) & (np.degrees(out.rot_err) <= FLIP_DEG)
    vp, vo = (np.broadcast_to(v, out.r[ok].shape) for v in model.variances(out.r[ok], out.phi[ok]))
    return position_chi2(model, out, ok, vp), out.rot_err[ok] ** 2 / vo


def calibration_of(model: NoiseModel, out: FrameScores) -> dict[str, float]:
    """How well ``model`` describes the measured errors (flips excluded).

    Returns the mean normalised squared error per block (``E[e^T R^-1 e] / 3``: 1 for a
    calibrated law, below 1 for a pessimistic one) and the fraction inside the 95 % chi-square(3)
    ellipsoid (0.95 for a calibrated law).
    """
    zp, zo = _normalised(model, out)
    return {'ratio_pos': float(np.mean(zp) / 3), 'ratio_rot': float(np.mean(zo) / 3),
            'cover_pos': float(np.mean(zp <= CHI2_3_95)), 'cover_rot': float(np.mean(zo <= CHI2_3_95))}


def tails(model: NoiseModel, out: FrameScores) -> dict[str, float]:
    """How heavy the errors' tails are, beyond what a Gaussian ``model`` allows (flips excluded).

    Fits a 6-D Student t to the errors whitened by ``model`` (``d^2 = e_p^2 / s_p^2 + e_o^2 /
    s_o^2``) by maximum likelihood: ``dof`` (large: Gaussian; near 1: Cauchy-like) and ``scale``
    (the t's scale matrix as a fraction of the model's covariance), and counts the errors beyond
    the chi-square(6) 99.99 % bound the estimator's change test uses (``beyond_9999``: 1e-4 if
    Gaussian).
    """
    from scipy.optimize import minimize
    from scipy.special import gammaln
    from scipy.stats import chi2

    zp, zo = _normalised(model, out)
    d2 = zp + zo

    def nll(theta: np.ndarray) -> float:
        s, nu = np.exp(theta)
        return -float(np.mean(gammaln((nu + 6) / 2) - gammaln(nu / 2) - 3 * np.log(nu * np.pi * s)
                              - (nu + 6) / 2 * np.log1p(d2 / (s * nu))))

    best = minimize(nll, [0.0, np.log(5.0)], method='Nelder-Mead')
    scale, dof = np.exp(best.x)
    return {'dof': float(dof), 'scale': float(scale), 'beyond_9999': float(np.mean(d2 > chi2.ppf(0.9999, 6)))}


#: Student-t degrees of freedom of the whitened errors below which the printed block asks the
#: estimator for the leverage-corrected spread (``covariance: sandwich_hc3``).
HEAVY_TAILS_DOF = 5.0

#: How far the errors' typical size may be from the law's before the printed block sets the
#: estimator's ``loss_scale`` (a ratio of standard deviations, either way).
SPREAD_TOLERANCE = 0.1


def typical_spread(model: NoiseModel, out: FrameScores) -> float:
    """The errors' typical size in ``model``'s standard deviations: ``sqrt(median d^2 / median
    chi2(6))``, ``d^2`` the squared error whitened by the law (flips excluded); 1 where the law
    is right. A law fitted to the errors' variance (maximum likelihood of a Gaussian) takes the
    heavy tails' size: the typical error is then a fraction of it.
    """
    from scipy.stats import chi2

    zp, zo = _normalised(model, out)
    return float(np.sqrt(np.median(zp + zo) / chi2.median(6)))


def loss_scale_for(spread: float) -> float:
    """The estimator's ``loss_scale`` for errors of typical size ``spread`` (law standard
    deviations): its default number of typical errors (``MapSettings.loss_scale``, 3), in the
    law's units, so that the robust loss departs from the square at the same place relative to
    the errors as with a right law; 0 (the estimator's default) within :data:`SPREAD_TOLERANCE`
    of 1.
    """
    if not np.isfinite(spread) or spread <= 0:
        raise ValueError(f'spread must be finite and > 0, got {spread}')
    if abs(spread - 1.0) <= SPREAD_TOLERANCE:
        return 0.0
    return float(np.clip(MapSettings.loss_scale * spread, *LOSS_SCALE_RANGE))


def shape(model: NoiseModel, out: FrameScores, cameras: np.ndarray) -> dict[str, object]:
    """How the errors spread along the camera's axes (x right, y down, z the optical axis), over ``model``.

    The law gives one variance per block, the same along every axis; a monocular marker pose is
    far less precise in depth than across the image. Each error is rotated into its own camera's
    frame and divided by the law's standard deviation; the spread per axis is robust (1.4826 x
    the median absolute value), so the heavy tails do not swamp it.

    Parameters
    ----------
    cameras : ndarray, shape (N, 3, 3)
        Root-frame rotation of the camera that took each frame of ``out``.

    Returns
    -------
    dict with ``position`` and ``rotation`` (3 robust spreads each, 1 where the law is right
    along that axis) and ``ratio`` (largest over smallest spread within a block, the larger block).
    """
    ok = out.success & np.isfinite(out.r) & (np.degrees(out.rot_err) <= FLIP_DEG)
    vp, vo = (np.broadcast_to(v, out.r[ok].shape) for v in model.variances(out.r[ok], out.phi[ok]))
    c = np.asarray(cameras, dtype=float)[ok]
    spread = {}
    for name, vec, var in (('position', out.pos_vec[ok], vp), ('rotation', out.rot_vec[ok], vo)):
        local = np.einsum('nji,nj->ni', c, vec) / np.sqrt(var)[:, None]
        spread[name] = tuple(float(v) for v in 1.4826 * np.median(np.abs(local), axis=0))
    ratio = max(max(v) / min(v) for v in spread.values())
    return {**spread, 'ratio': float(ratio)}


def stereo_ratios(frames: Sequence[Frame], law: PoseDependentNoise, model: ArmModel,
                  config: DetectorConfig | None = None) -> dict[str, float]:
    """The law's stereo variance ratios, fitted where both eyes found the hand.

    For every configuration whose two eye frames each give a hand estimate under ``law``, the
    detector's stereo estimate (:meth:`HandPoseEstimator.stereo`) is compared with the truth; each
    ratio is the error's variance over the eyes' fused covariance (variance-matched, as
    the law itself is: the mean squared error whitened by the fused covariance, per axis; planar
    flips, over :data:`FLIP_DEG`, left out).

    Parameters
    ----------
    frames : sequence of Frame
        From :func:`tools.detector_accuracy.collect` with the views ``left`` and ``right``.

    Returns
    -------
    dict with ``stereo_pos``, ``stereo_rot`` (NaN without a pair), ``n`` pairs used, ``fallbacks``
    (pairs whose refinement was refused and the fused poses kept), and the stereo and the left
    eye's median position and orientation errors [mm, deg] over the same pairs.
    """
    est = HandPoseEstimator(model, law, config or DetectorConfig())
    unit = replace(law, stereo_pos=1.0, stereo_rot=1.0)
    by_config: dict[int, dict[str, Frame]] = {}
    for f in frames:
        by_config.setdefault(f.config, {})[f.eye] = f
    ratios_p, ratios_o, errs, left = [], [], [], []
    fallbacks = 0
    for pair in by_config.values():
        if set(pair) != {'left', 'right'}:
            continue
        views = [eye_result(pair[eye], est) for eye in ('left', 'right')]
        if any(r.hand is None for r, _ in views):
            continue
        truth = pair['left'].truth
        fused = fuse_estimates([r.hand for r, _ in views])
        hand = est.stereo(views)
        fallbacks += bool(np.array_equal(hand.pose, fused.pose))
        e_p, e_o = np.split(pose_residuals(hand.pose[None], truth[None])[0], 2)
        if np.degrees(np.linalg.norm(e_o)) > FLIP_DEG:
            continue
        # Whitened by the eyes' fused covariance (ratios 1), whose blocks the ratios then scale.
        c = stereo_covariance(np.stack([r.hand.covariance for r, _ in views]), unit)
        ratios_p.append(e_p @ np.linalg.solve(c[:3, :3], e_p) / 3)
        ratios_o.append(e_o @ np.linalg.solve(c[3:, 3:], e_o) / 3)
        l_p, l_o = np.split(pose_residuals(views[0][0].hand.pose[None], truth[None])[0], 2)
        errs.append((1e3 * np.linalg.norm(e_p), np.degrees(np.linalg.norm(e_o))))
        left.append((1e3 * np.linalg.norm(l_p), np.degrees(np.linalg.norm(l_o))))
    if not ratios_p:
        return {'stereo_pos': float('nan'), 'stereo_rot': float('nan'), 'n': 0, 'fallbacks': fallbacks}
    e, lo = np.median(errs, axis=0), np.median(left, axis=0)
    return {'stereo_pos': float(np.mean(ratios_p)), 'stereo_rot': float(np.mean(ratios_o)), 'n': len(ratios_p),
            'fallbacks': int(fallbacks), 'pos_med_mm': float(e[0]), 'rot_med_deg': float(e[1]),
            'left_pos_med_mm': float(lo[0]), 'left_rot_med_deg': float(lo[1])}


def _row(name: str, model: NoiseModel, out: FrameScores) -> str:
    c = calibration_of(model, out)
    return (f'| {name} | {c["ratio_pos"]:.3g} | {c["ratio_rot"]:.3g} | {c["cover_pos"]:.2f} | '
            f'{c["cover_rot"]:.2f} |')


def run(robot: str, n: int, seed: int, pixel_noise: float, depth: bool = False,
        with_loss_scale: bool = False) -> tuple[str, NoiseFit]:
    """Render, detect, fit; the Markdown report (with the YAML block) and the fit. With
    ``with_loss_scale`` the block also sets the estimator's ``loss_scale`` (:func:`loss_scale_for`)."""
    from icub_sim_bridge.world import SimWorld

    t0 = time.perf_counter()
    model = load_robot(robot)
    views = views_of(model)
    configs = uniform_configs(model.calibration_box, n, seed)
    with SimWorld(model) as world:
        frames = collect(model, world, configs, views, noise_std=pixel_noise, seed=seed)
    current = PoseDependentNoise.for_robot(model)
    out = evaluate(frames, HandPoseEstimator(model, current, DetectorConfig()))
    fit = fit_noise(out, depth=depth)
    stereo_text, stereo_fitted = '', False
    if {'left', 'right'} <= {name for name, _ in views}:
        st = stereo_ratios(frames, replace(fit.pdn, stereo_pos=1.0, stereo_rot=1.0), model)
        if st['n'] >= 10:
            fit = replace(fit, pdn=replace(fit.pdn, stereo_pos=st['stereo_pos'], stereo_rot=st['stereo_rot']))
            stereo_fitted = True
            stereo_text = (
                'Stereo: on the {n} configurations both eyes see the hand, the detector\'s stereo estimate (both '
                'images\' corners in one refinement; {fb} refused, the fused poses kept) is off by {p:.2f} mm / '
                '{o:.3f} deg (median; the left eye alone {lp:.2f} mm / {lo:.3f} deg): its variance is {sp:.3g} '
                '(position) and {so:.3g} (orientation) of the eyes\' fused ones (`stereo_pos`, `stereo_rot`).'
                .format(n=st['n'], fb=st['fallbacks'], p=st['pos_med_mm'], o=st['rot_med_deg'],
                        lp=st['left_pos_med_mm'], lo=st['left_rot_med_deg'], sp=st['stereo_pos'],
                        so=st['stereo_rot']))
        else:
            stereo_text = f'Stereo: only {st["n"]} configurations with both eyes\' hands; the ratios stay 1.'
    tl = tails(fit.pdn, out)
    sh = shape(fit.pdn, out, np.array([f.root_T_cam[:3, :3] for f in frames]))
    covariance = 'sandwich_hc3' if tl['dof'] < HEAVY_TAILS_DOF else ''
    spread = typical_spread(fit.pdn, out)
    loss_scale = loss_scale_for(spread)
    if loss_scale and with_loss_scale:
        scale_text = ('the block sets the robust loss to depart from the square at {:g} typical errors, '
                      'loss_scale {:.2g} of the law\'s.'.format(loss_scale / spread, loss_scale))
    elif loss_scale:
        scale_text = ('`--loss-scale` adds loss_scale {:.2g} to the block (the robust loss then departs from the '
                      'square at {:g} typical errors rather than at {:g} of the law\'s standard '
                      'deviations).'.format(loss_scale, loss_scale / spread, MapSettings.loss_scale))
    else:
        scale_text = 'the estimator\'s default loss scale.'
    s = summarize(out, frames)
    r_ok = out.r[out.success & np.isfinite(out.r)]
    lines = [f'## Noise law of `{model.name}` ({", ".join(f"{e} {w}x{h}" for e, (w, h) in views)}, '
             f'{model.marker_side_length * 100:g} cm marker)', '',
             f'{n} uniform configurations of the calibration box (seed {seed}), pixel noise {pixel_noise:g} '
             f'grey levels: {len(frames)} images, a hand pose in {100 * s["success"]:.1f} %, '
             f'{int(s["flips"])} planar flips (over {FLIP_DEG:g} deg, left out of the fit), distance '
             f'{r_ok.min():.2f}-{r_ok.max():.2f} m; median / p95 error {s["pos_med_mm"]:.2f} / '
             f'{s["pos_p95_mm"]:.2f} mm, {s["rot_med_deg"]:.3f} / {s["rot_p95_deg"]:.3f} deg.', '',
             '| law | mean squared error / predicted, position (1 = calibrated) | orientation | '
             'inside the 95 % ellipsoid, position (0.95 = calibrated) | orientation |',
             '|---|---|---|---|---|',
             _row('the description\'s law now', current, out),
             _row('the built-in defaults (iCub 320x240, 3 cm)', PoseDependentNoise(), out),
             _row('**fitted here**', fit.pdn, out),
             _row('constant (CN) fitted here', fit.cn, out), '',
             'Tails: a Student t fitted to the errors whitened by the fitted law has {dof:.2g} degrees of freedom '
             '(Gaussian: large) and a scale of {scale:.2g} of the law\'s covariance; {beyond:.1f} % of the errors '
             'lie beyond the chi-square(6) 99.99 % bound (Gaussian: 0.01 %). A variance-matched Gaussian law '
             'then overstates the typical error: the MAP estimator\'s sandwich covariance measures the spread '
             'instead.'.format(dof=tl['dof'], scale=tl['scale'], beyond=100 * tl['beyond_9999']), '',
             'Shape: along the camera\'s x, y and z (optical axis) the errors\' robust spread over the fitted '
             'law\'s is {p} in position and {o} in rotation (1 where the law is right): largest over smallest '
             '{ratio:.1f}, where an isotropic law assumes 1.'.format(
                 p=' / '.join(f'{v:.2f}' for v in sh['position']), o=' / '.join(f'{v:.2f}' for v in sh['rotation']),
                 ratio=sh['ratio']), '',
             ('Tails this heavy (under {:g} degrees of freedom): the block asks the estimator for the '
              'leverage-corrected spread (covariance: sandwich_hc3).'.format(HEAVY_TAILS_DOF) if covariance else
              'Tails near Gaussian: the estimator\'s default covariance.'), '',
             'Typical error: {:.2f} of the law\'s standard deviation (the median whitened error against '
             'chi-square(6)\'s); {}'.format(spread, scale_text), '',
             (f'Line of sight: the position law is fitted across it and `depth_ratio` along it: the error '
              f'along the line of sight is {fit.pdn.depth_ratio:.3g} times that across it.' if depth else
              'An isotropic position law (`--depth` fits one across the line of sight and its `depth_ratio` '
              'along it).'), '',
             *([stereo_text, ''] if stereo_text else []),
             f'Fitted on {fit.n} poses; {time.perf_counter() - t0:.0f} s. Paste into the description:', '',
             '```yaml',
             law_yaml(fit.pdn, f'Fitted by: python -m tools.fit_noise --robot {robot} --n {n} --seed {seed} '
                               f'--pixel-noise {pixel_noise:g}' + (' --depth' if depth else '')
                               + (' --loss-scale' if with_loss_scale else ''), covariance,
                      loss_scale if with_loss_scale else 0.0, stereo=stereo_fitted).rstrip(),
             f'# CN baseline fitted on the same poses: cn_sigma_pos {fit.cn.sigma_pos:.3g} m, '
             f'cn_sigma_rot_deg {np.degrees(fit.cn.sigma_rot):.3g}',
             '```', '']
    return '\n'.join(lines), fit


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', default='ur5e', help='packaged name or YAML path')
    ap.add_argument('--n', type=int, default=300, help='configurations of the calibration box')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--pixel-noise', type=float, default=0.0,
                    help="additive pixel noise [grey levels]; the simulator node's pixel_noise_std")
    ap.add_argument('--depth', action='store_true',
                    help='fit the position law across the line of sight and its depth_ratio along it')
    ap.add_argument('--loss-scale', action='store_true',
                    help="also set the estimator's loss_scale in the block: 3 of the errors' typical size, in the "
                         "law's standard deviations, where that differs from 1 by more than 10%%")
    ap.add_argument('--out', type=Path, help='also write the report here')
    args = ap.parse_args(list(argv) if argv is not None else None)
    if args.n < 20:
        ap.error(f'--n must be at least 20 for a fit of six coefficients, got {args.n}')
    report, _ = run(args.robot, args.n, args.seed, args.pixel_noise, args.depth, args.loss_scale)
    print(report)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)
    return 0


if __name__ == '__main__':
    sys.exit(main())
