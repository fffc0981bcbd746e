"""Re-run a study's recorded runs with another noise law: the same observations, re-weighted (paired).

The law an observation is weighted with decides how much the estimate trusts it. This command
takes every run of a ``tools.seed_study`` directory, re-runs its bag through the estimator
twice with the run's own settings (``run.env`` and the packaged ``estimator.yaml``): once with
the covariances the detector recorded, once with each observation's covariance replaced by the
given law's at its hand pose (``evaluate --noise-law``; the block's ``covariance`` and
``loss_scale``, where set, are the estimator's), and prints both, seed by seed, with the paired
comparison. The selector chose the poses with the recorded law, so this measures the estimator's
weighting alone, not what a selector using the new law would pick.

Usage (from the repository root)::

    python -m tools.noise_replay results/panda-al --noise-law LAW.yaml [--output FILE.md]

``LAW.yaml`` holds a ``noise_model:`` block, as ``tools.fit_noise`` prints it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.stats import wilcoxon

from calibration_interfaces.parameters import read_params_file
from tools.seed_study import read_run_env

__all__ = ['run_settings', 'replay', 'report', 'main']

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'ros2_ws' / 'src' / 'calibration_bringup' / 'config'


def run_settings(run: Path):  # -> dh_estimator.evaluate.EvaluationSettings
    """The offline re-run's settings of one launcher run: the packaged estimator parameters with
    what ``run.env`` says of the robot, the noise model, the estimator and the extrinsic priors."""
    from dh_estimator.evaluate import EvaluationSettings

    env = read_run_env(run)
    values = dict(read_params_file(CONFIG / 'estimator.yaml', 'dh_estimator'))
    values.update(robot=env['robot'], noise_model=env.get('noise', 'pose_dependent'),
                  estimator=env.get('estimator', 'map'))
    for key, prior in (('camera_error', 'camera_prior'), ('marker_error', 'marker_prior')):
        if env.get(key):
            values[prior] = env[key]
    return EvaluationSettings.from_parameters(values)


def replay(study: Path, law: tuple[tuple[tuple[str, float], ...], str, float]) -> list[dict[str, float]]:
    """One row per run of ``study`` (``seed_<S>/calibration.mcap``): final errors, information
    limit and NEES with the recorded covariances and with the law of a ``noise_model:`` block
    (:func:`dh_estimator.evaluate.read_noise_block`; its estimator keys, ``covariance`` and
    ``loss_scale``, where set: :func:`dh_estimator.evaluate.with_noise_law`)."""
    from dh_estimator.evaluate import evaluate_bag, with_noise_law

    rows = []
    runs = sorted((p for p in study.glob('seed_*') if (p / 'calibration.mcap').is_file()),
                  key=lambda p: int(p.name.split('_')[1]))
    if not runs:
        raise FileNotFoundError(f'{study}: no seed_<S>/calibration.mcap')
    for run in runs:
        settings = run_settings(run)
        row: dict[str, float] = {'seed': int(run.name.split('_')[1])}
        for name, s in (('recorded', settings), ('law', with_noise_law(settings, law))):
            ev = evaluate_bag(run / 'calibration.mcap', s)
            last = ev.rows[-1]
            band = ev.nees_band or (np.nan, np.nan)
            row.update({f'{name}_mm': last.position_mm, f'{name}_deg': last.orientation_deg,
                        f'{name}_limit_mm': last.expected_position_mm, f'{name}_nees': ev.nees_identifiable,
                        f'{name}_in_band': float(band[0] <= ev.nees_identifiable <= band[1])})
        rows.append(row)
        print(f"seed {row['seed']}: {row['recorded_mm']:.3f} -> {row['law_mm']:.3f} mm", file=sys.stderr)
    return rows


def _stats(v: np.ndarray) -> str:
    return f'{np.mean(v):.3f} / {np.median(v):.3f} / {np.min(v):.3f}-{np.max(v):.3f}'


def report(rows: Sequence[dict[str, float]], title: str) -> str:
    """Markdown: the per-seed table and the paired comparison."""
    lines = [f'# {title}', '',
             '| seed | recorded law [mm / deg] | NEES (in band) | new law [mm / deg] | NEES (in band) | '
             'information limit, recorded / new [mm] |', '|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['seed']} | {r['recorded_mm']:.2f} / {r['recorded_deg']:.3f} | {r['recorded_nees']:.1f} "
                     f"({'yes' if r['recorded_in_band'] else 'no'}) | **{r['law_mm']:.2f} / {r['law_deg']:.3f}** | "
                     f"{r['law_nees']:.1f} ({'yes' if r['law_in_band'] else 'no'}) | "
                     f"{r['recorded_limit_mm']:.2f} / {r['law_limit_mm']:.2f} |")
    a = np.array([[r['recorded_mm'], r['law_mm'], r['recorded_deg'], r['law_deg']] for r in rows])
    n = len(rows)
    lines += ['', f'Over {n} runs (mean / median / range):', '',
              f'- position [mm]: recorded {_stats(a[:, 0])}, new law {_stats(a[:, 1])}; ratio of the means '
              f'{np.mean(a[:, 1]) / np.mean(a[:, 0]):.2f}, lower in {int(np.sum(a[:, 1] < a[:, 0]))} of {n}',
              f'- orientation [deg]: recorded {_stats(a[:, 2])}, new law {_stats(a[:, 3])}; ratio of the means '
              f'{np.mean(a[:, 3]) / np.mean(a[:, 2]):.2f}, lower in {int(np.sum(a[:, 3] < a[:, 2]))} of {n}',
              f"- NEES in its 95% band: recorded {int(sum(r['recorded_in_band'] for r in rows))} of {n}, "
              f"new law {int(sum(r['law_in_band'] for r in rows))} of {n}"]
    if n >= 5:
        lines.append(f'- paired Wilcoxon signed-rank test, position: p = {wilcoxon(a[:, 0], a[:, 1]).pvalue:.2g}; '
                     f'orientation: p = {wilcoxon(a[:, 2], a[:, 3]).pvalue:.2g}')
    return '\n'.join(lines) + '\n'


def main(argv: Sequence[str] | None = None) -> int:
    from dh_estimator.evaluate import read_noise_block

    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('study', type=Path, help='a tools.seed_study output directory')
    ap.add_argument('--noise-law', type=Path, required=True, help="a YAML with a 'noise_model:' block")
    ap.add_argument('--output', type=Path, help='also write the report here')
    args = ap.parse_args(list(argv) if argv is not None else None)
    try:
        rows = replay(args.study, read_noise_block(args.noise_law))
    except (FileNotFoundError, ValueError) as exc:
        print(f'noise_replay: {exc}', file=sys.stderr)
        return 2
    text = report(rows, f'{args.study.name}: recorded covariances against {args.noise_law.name}')
    print(text)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
