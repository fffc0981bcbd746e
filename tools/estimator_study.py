"""Estimator study: online MAP vs the EKF vs a batch solve of the same observations.

The ROS-free loop of :mod:`active_selector.study` (render the left eye, detect, update, select
with the current selector), ``--seeds`` seeded runs of ``--iterations`` per estimator. Each run
has its own real robot (nominal table perturbed by 4 mm / 2 deg, seed 1000 + s) and initial guess
(the paper's widths, seed s). After each run the observations the online estimator used are
solved in one batch (prior + all of them, plain least squares, from the initial guess): the
"information limit" of that run's data. Reported per estimator: final position / orientation
error (mean, median, std, min, max), the ratio to the batch solution, NEES of the final estimate
(28 parameters) with its 95% chi-square band, outliers flagged. Each run's observations are saved
(``observations_<estimator>_<seed>.npz``: q, pose, R, true_dh, x0) for offline comparisons.

    python -m tools.estimator_study --seeds 20 --iterations 50 --output results/estimator_study
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from active_selector.planner import PlannerSettings
from body_schema.acquisition import SelectorConfig
from tools.selector_study import initial_guess, run_seed, true_table
from body_schema import load_robot, sampling
from body_schema.ekf import nees
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import PoseDependentNoise


def batch_solution(model, x0: np.ndarray, observations: list) -> np.ndarray:
    """Batch MAP of prior + observations (plain least squares), shape (4 L,)."""
    est = MapEstimator(model.base, x0, sampling.initial_covariance(model.n_joints), MapSettings(loss='linear'))
    if observations:
        qs, zs, rs = (np.array(a) for a in zip(*observations))
        est.solve_batch(qs, zs, rs)
    return est.x


def summarise(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {'mean': float(a.mean()), 'median': float(np.median(a)), 'std': float(a.std()),
            'min': float(a.min()), 'max': float(a.max())}


def replay(directory: Path, variants: dict[str, MapSettings]) -> str:
    """Re-run MAP settings online over saved observations (the same data for every variant)."""
    model = load_robot()
    files = sorted(directory.glob('observations_*.npz'))
    if not files:
        raise SystemExit(f'no observations_*.npz in {directory}')
    lines = [f'{len(files)} saved runs of {directory}, re-estimated online with each setting', '',
             '| MAP setting | position [mm] mean / median / std (max) | orientation [deg] mean / median | NEES mean | '
             'outliers / run |', '|---|---|---|---|---|']
    for name, settings in variants.items():
        pos, rot, ne, out = [], [], [], []
        for f in files:
            d = np.load(f)
            est = MapEstimator(model.base, d['x0'], sampling.initial_covariance(model.n_joints), settings,
                               limits=model.limits)
            for q, z, r in zip(d['q'], d['pose'], d['R']):
                est.update(q, z, r)
            e = PoseErrorEvaluator(model.base, d['true_dh'], model.calibration_box)(est.x)
            pos.append(e.position_mm)
            rot.append(e.orientation_deg)
            ne.append(nees(d['true_dh'].ravel(), est.x, est.P))
            out.append(est.n_outliers)
        p, o = summarise(pos), summarise(rot)
        lines.append(f"| {name} | {p['mean']:.2f} / {p['median']:.2f} / {p['std']:.2f} ({p['max']:.2f}) "
                     f"| {o['mean']:.2f} / {o['median']:.2f} | {np.mean(ne):.1f} | {np.mean(out):.1f} |")
        print(lines[-1], flush=True)
    return '\n'.join(lines) + '\n'


#: Robust losses compared by ``--replay`` (name -> settings).
LOSS_VARIANTS = {f'{loss}, scale {scale:g}': MapSettings(loss=loss, loss_scale=scale)
                 for loss, scale in (('linear', 1.0), ('huber', 3.0), ('huber', 2.0), ('soft_l1', 2.0),
                                     ('cauchy', 2.0), ('cauchy', 3.0), ('cauchy', 4.0), ('arctan', 3.0))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, default=20)
    ap.add_argument('--first-seed', type=int, default=0)
    ap.add_argument('--iterations', type=int, default=50)
    ap.add_argument('--estimators', default='map,ekf', help='comma-separated: map, ekf')
    ap.add_argument('--ekf-iterations', type=int, default=5, help="EKF linearisations (the node's default 5)")
    ap.add_argument('--strategy', default='al')
    ap.add_argument('--output', type=Path, default=Path('results/estimator_study'))
    ap.add_argument('--replay', type=Path, default=None,
                    help='compare robust losses on the observations saved in this directory instead')
    args = ap.parse_args(argv)
    if args.replay is not None:
        text = replay(args.replay, LOSS_VARIANTS)
        (args.replay / 'losses.md').write_text(text)
        print(text)
        return 0

    model = load_robot()
    noise = PoseDependentNoise()
    args.output.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        true_dh, x0 = true_table(model, seed), initial_guess(model, seed)
        evaluator = PoseErrorEvaluator(model.base, true_dh, model.calibration_box)
        for kind in args.estimators.split(','):
            settings = PlannerSettings(selector=SelectorConfig(strategy=args.strategy))
            r = run_seed(model, noise, settings, seed, args.iterations, args.ekf_iterations, estimator=kind)
            est = r.estimator
            if r.observations:
                qs, zs, rs = (np.array(a) for a in zip(*r.observations))
                np.savez(args.output / f'observations_{kind}_{seed:03d}.npz', q=qs, pose=zs, R=rs,
                         true_dh=true_dh, x0=x0)
            xb = batch_solution(model, x0, r.observations)
            eb = evaluator(xb)
            row = {'seed': seed, 'estimator': kind, 'position_mm': r.position_mm[-1],
                   'orientation_deg': r.orientation_deg[-1], 'batch_position_mm': eb.position_mm,
                   'batch_orientation_deg': eb.orientation_deg, 'updates': len(r.observations),
                   'discarded': r.discarded, 'nees': nees(true_dh.ravel(), est.x, est.P),
                   'outliers': est.counters['outliers'], 'seconds': r.seconds,
                   'movement_deg': r.movement_deg[-1]}
            runs.append(row)
            print(json.dumps(row), flush=True)
    (args.output / 'runs.json').write_text(json.dumps(runs, indent=1))
    lines = [f'{args.seeds} seeds x {args.iterations} iterations, strategy {args.strategy}', '',
             '| estimator | position [mm] mean / median / std (min-max) | orientation [deg] mean / median / std '
             '| batch position [mm] mean / median | online / batch (mean) | NEES mean (95% band) | outliers / run |',
             '|---|---|---|---|---|---|---|']
    for kind in args.estimators.split(','):
        rs = [r for r in runs if r['estimator'] == kind]
        p, o, b = (summarise([r[k] for r in rs]) for k in ('position_mm', 'orientation_deg', 'batch_position_mm'))
        n = len(rs)
        lo, hi = chi2.ppf(0.025, 28 * n) / n, chi2.ppf(0.975, 28 * n) / n
        lines.append(f"| {kind} | {p['mean']:.2f} / {p['median']:.2f} / {p['std']:.2f} ({p['min']:.2f}-{p['max']:.2f}) "
                     f"| {o['mean']:.2f} / {o['median']:.2f} / {o['std']:.2f} | {b['mean']:.2f} / {b['median']:.2f} "
                     f"| {p['mean'] / b['mean']:.2f} | {np.mean([r['nees'] for r in rs]):.1f} ({lo:.1f}-{hi:.1f}) "
                     f"| {np.mean([r['outliers'] for r in rs]):.1f} |")
    text = '\n'.join(lines) + '\n'
    (args.output / 'summary.md').write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
