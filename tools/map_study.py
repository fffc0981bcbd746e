"""Studies of the online MAP estimator on synthetic observations (noise drawn from the model).

Subcommands (each prints a markdown table and writes JSON under ``--output``):

``consistency``  NEES of the final estimate and mean NIS over ``--seeds`` runs, MAP and EKF.
``adaptation``   a body that changes at observation ``--change-at`` (forearm +10 mm, shoulder
                 yaw offset +3 deg): observations needed to get back within 1.5x the pre-change
                 error, and the price on a body that does not change, per forgetting setting.
``timing``       seconds of one MAP update after 50 and 500 observations.

    python -m tools.map_study consistency --seeds 30
    python -m tools.map_study adaptation --seeds 20
    python -m tools.map_study timing
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from body_schema import ekf, load_robot, sampling
from body_schema.map_estimator import MapEstimator, MapSettings
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import PoseDependentNoise
from body_schema.synthetic import SyntheticRun

from .estimator_study import summarise
from .selector_study import initial_guess, true_table

#: Forgetting settings compared by ``adaptation`` (name -> MapSettings overrides).
FORGETTING = {
    'none': {'change_probability': 0.0},
    'random walk 0.1 mm / 0.03 deg': {'change_probability': 0.0, 'q_length': 1e-8,
                                      'q_angle': float(np.radians(0.03)) ** 2},
    'random walk 0.3 mm / 0.1 deg': {'change_probability': 0.0, 'q_length': 9e-8,
                                     'q_angle': float(np.radians(0.1)) ** 2},
    'window 15, no change detection': {'change_probability': 0.0, 'window': 15},
    'change detection: 2 of 3 NIS beyond p=0.99': {'change_probability': 0.99, 'change_window': 3, 'change_count': 2},
    'change detection: 2 of 3 beyond p=0.999': {'change_probability': 0.999, 'change_window': 3, 'change_count': 2},
    'change detection: 3 of 3 beyond p=0.999': {'change_probability': 0.999, 'change_window': 3, 'change_count': 3},
    'change detection: 2 of 3 beyond p=0.9999 (the former default)': {'change_window': 3, 'change_count': 2},
    'change detection: 3 of 4 beyond p=0.9999 (default)': {},
    'default without the confirmation (change_confirm off)': {'change_confirm': False},
    'default, jump 5 mm / 1.5 deg': {'jump_length': 0.005, 'jump_angle': float(np.radians(1.5))},
    'default, jump 30 mm / 10 deg': {'jump_length': 0.03, 'jump_angle': float(np.radians(10.0))},
    'default + random walk 0.1 mm / 0.03 deg': {'q_length': 1e-8, 'q_angle': float(np.radians(0.03)) ** 2},
}


def changed_table(table: np.ndarray) -> np.ndarray:
    """The body after the change: forearm (wrist prosup d) +10 mm, shoulder yaw offset +3 deg."""
    out = table.copy()
    out[4, 1] += 0.010
    out[2, 3] += np.radians(3.0)
    return out


def summary(a: list[float]) -> str:
    """``mean / median / std`` of ``a``, two decimals."""
    s = summarise(a)
    return f"{s['mean']:.2f} / {s['median']:.2f} / {s['std']:.2f}"


def consistency(model, seeds: int, n_obs: int) -> tuple[dict, str]:
    noise = PoseDependentNoise()
    rows = {'map': [], 'ekf': []}
    for seed in range(seeds):
        true = true_table(model, seed)
        obs = SyntheticRun(model, true, noise, seed)(n_obs)
        x0, p0 = initial_guess(model, seed), sampling.initial_covariance(model.n_joints)
        est = MapEstimator(model.base, x0, p0, limits=model.limits)
        f = ekf.ExtendedKalmanFilter(x0.ravel(), p0)
        hand = ekf.HandPoseModel(model.base, model.n_joints)
        nis_m, nis_e = [], []
        for o in obs:
            nis_m.append(est.update(o.q, o.pose, o.R).nis)
            hand.update(f, o.q, o.pose, o.R)
            nis_e.append(f.nis)
        ev = PoseErrorEvaluator(model.base, true, model.calibration_box)
        rows['map'].append({'nees': ekf.nees(true.ravel(), est.x, est.P), 'nis': float(np.mean(nis_m[10:])),
                            'outliers': est.n_outliers, 'position_mm': ev(est.x).position_mm})
        rows['ekf'].append({'nees': ekf.nees(true.ravel(), f.x, f.P), 'nis': float(np.mean(nis_e[10:])),
                            'outliers': 0, 'position_mm': ev(f.x).position_mm})
    lo, hi = chi2.ppf(0.025, 28 * seeds) / seeds, chi2.ppf(0.975, 28 * seeds) / seeds
    lines = [f'{seeds} seeds x {n_obs} synthetic observations (uniform in the box, pose-dependent noise drawn '
             f'from the model); NEES over 28 parameters, 95% band of the mean {lo:.1f}-{hi:.1f}; NIS after the '
             '10th observation (6 when consistent)', '',
             '| estimator | mean NEES | in band | mean NIS | NIS / 6 | outliers flagged / run | position [mm] mean / median / std |',
             '|---|---|---|---|---|---|---|']
    for kind, rs in rows.items():
        m = float(np.mean([r['nees'] for r in rs]))
        nis = float(np.mean([r['nis'] for r in rs]))
        label = 'MAP' if kind == 'map' else 'EKF (paper, 1 linearisation)'
        lines.append(f"| {label} | {m:.1f} | {'yes' if lo <= m <= hi else 'no'} | {nis:.2f} | {nis / 6:.2f} "
                     f"| {np.mean([r['outliers'] for r in rs]):.2f} | {summary([r['position_mm'] for r in rs])} |")
    return rows, '\n'.join(lines)


def recovery(errors_after: list[float], target: float) -> int | None:
    """Observations after the change until the error is back within ``target`` (and stays)."""
    for k in range(len(errors_after)):
        if all(e <= target for e in errors_after[k:]):
            return k + 1
    return None


def adaptation(model, seeds: int, change_at: int, n_after: int) -> tuple[dict, str]:
    noise = PoseDependentNoise()
    out = {}
    for name, overrides in FORGETTING.items():
        settings = replace(MapSettings(), **overrides)
        recs, pre, price, final_changed, final_static, changes_static = [], [], [], [], [], []
        for seed in range(seeds):
            true = true_table(model, seed)
            new = changed_table(true)
            x0, p0 = initial_guess(model, seed), sampling.initial_covariance(model.n_joints)
            ev_old = PoseErrorEvaluator(model.base, true, model.calibration_box, n=300)
            ev_new = PoseErrorEvaluator(model.base, new, model.calibration_box, n=300)
            # A body that changes ...
            obs = SyntheticRun(model, true, noise, seed, {change_at: new})(change_at + n_after)
            est = MapEstimator(model.base, x0, p0, settings, limits=model.limits)
            after = []
            for k, o in enumerate(obs):
                est.update(o.q, o.pose, o.R)
                if k == change_at - 1:
                    e_pre = ev_old(est.x).position_mm
                if k >= change_at:
                    after.append(ev_new(est.x).position_mm)
            pre.append(e_pre)
            recs.append(recovery(after, 1.5 * e_pre))
            final_changed.append(after[-1])
            # ... and the same run on a body that does not.
            static = MapEstimator(model.base, x0, p0, settings, limits=model.limits)
            for o in SyntheticRun(model, true, noise, seed)(change_at + n_after):
                static.update(o.q, o.pose, o.R)
            final_static.append(ev_old(static.x).position_mm)
            changes_static.append(static.n_changes)
        out[name] = {'settings': asdict(settings), 'pre_change_mm': pre, 'recovery': recs,
                     'final_after_change_mm': final_changed, 'final_static_mm': final_static,
                     'false_changes': changes_static}
        print(name, 'done', flush=True)
    base_static = np.mean(out['none']['final_static_mm'])
    lines = [f'{seeds} seeds; synthetic observations uniform in the box; the body changes at observation '
             f'{change_at} (forearm +10 mm, shoulder yaw offset +3 deg); {n_after} observations after it. '
             'Recovery: observations after the change until the position error is back within 1.5x the '
             'pre-change error for good. Price: final error on a body that does not change, relative to no '
             'forgetting.', '',
             '| forgetting | recovered (runs) | recovery [obs] median (mean) | error after the change, final [mm] '
             'mean / median / std | no-change final [mm] mean | price | false changes / run |',
             '|---|---|---|---|---|---|---|']
    for name, r in out.items():
        rec = [v for v in r['recovery'] if v is not None]
        rec_text = f'{np.median(rec):.0f} ({np.mean(rec):.1f})' if rec else '-'
        fs = float(np.mean(r['final_static_mm']))
        lines.append(f"| {name} | {len(rec)}/{seeds} | {rec_text} | {summary(r['final_after_change_mm'])} "
                     f"| {fs:.3f} | {100 * (fs / base_static - 1):+.1f}% | {np.mean(r['false_changes']):.2f} |")
    return out, '\n'.join(lines)


def timing(model, sizes: tuple[int, ...] = (50, 500), repeats: int = 20) -> tuple[dict, str]:
    """Median / p90 time of one update once ``n`` observations are in (reached online)."""
    noise = PoseDependentNoise()
    true = true_table(model, 0)
    obs = SyntheticRun(model, true, noise, 0)(max(sizes) + repeats)
    out = {}
    lines = ['| MAP update after N observations | median [ms] | p90 [ms] | residual evaluations (median) |',
             '|---|---|---|---|']
    for settings_name, settings in (('default: window 100', MapSettings()), ('all kept: window 0', MapSettings(window=0))):
        est = MapEstimator(model.base, sampling.perturb_dh(model.dh, 0), sampling.initial_covariance(7), settings)
        ts, nf = [], []
        for k, o in enumerate(obs):
            t0 = time.perf_counter()
            u = est.update(o.q, o.pose, o.R)
            ts.append(time.perf_counter() - t0)
            nf.append(u.nfev)
        for n in sizes:
            ms = 1e3 * np.array(ts[n:n + repeats])
            out[f'{settings_name} {n}'] = {'median_ms': float(np.median(ms)), 'p90_ms': float(np.percentile(ms, 90)),
                                           'nfev': float(np.median(nf[n:n + repeats]))}
            lines.append(f'| {n} ({settings_name}) | {np.median(ms):.1f} | {np.percentile(ms, 90):.1f} '
                         f'| {np.median(nf[n:n + repeats]):.0f} |')
    return out, '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('study', choices=['consistency', 'adaptation', 'timing'])
    ap.add_argument('--seeds', type=int, default=30)
    ap.add_argument('--observations', type=int, default=50)
    ap.add_argument('--change-at', type=int, default=25)
    ap.add_argument('--after', type=int, default=50)
    ap.add_argument('--output', type=Path, default=Path('results/map_study'))
    args = ap.parse_args(argv)
    model = load_robot()
    if args.study == 'consistency':
        data, text = consistency(model, args.seeds, args.observations)
    elif args.study == 'adaptation':
        data, text = adaptation(model, args.seeds, args.change_at, args.after)
    else:
        data, text = timing(model)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / f'{args.study}.json').write_text(json.dumps(data, indent=1, default=float))
    (args.output / f'{args.study}.md').write_text(text + '\n')
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
