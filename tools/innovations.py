"""A noise law's check from recorded runs, without re-running them: each bag's innovations.

Every estimator verdict on ``/body_schema/update_status`` carries the Mahalanobis distance of its
observation's innovation; an update's NIS is its square (chi-square, 6 dof, if the law is right).
This command reads them from each run's ``calibration.mcap`` (seconds per bag, where ``evaluate``
re-runs the estimator for the same figures) and prints, per run and over all, the median NIS
after the warm-up, how many lie beyond the change test's bound
(:func:`body_schema.noise.innovation_check`) and which of the launcher's health-check tests of
the law they fail (``tails``, ``median``: :meth:`body_schema.noise.InnovationCheck.findings`).
A bag whose offline re-run equals the online estimate gives the figures the run's report states.

Usage (from the repository root)::

    python -m tools.innovations results/study-a results/study-b/seed_3 ... [--skip 10] [--probability 0.9999]

A directory with ``seed_<S>/`` subdirectories is read as a ``tools.seed_study`` study.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ['UPDATES', 'recorded_nis', 'runs_of', 'main']

#: The verdicts of an update (MAP: accepted or outlier; EKF: accepted or rejected by its gate).
UPDATES = ('accepted', 'outlier', 'rejected')


def recorded_nis(bag: str | Path) -> list[float]:
    """The NIS of every update recorded in ``bag``, in order (duplicates and failures left out)."""
    from calibration_interfaces.outcome import recorded_statuses

    return [s.mahalanobis ** 2 for s in recorded_statuses(bag) if s.outcome.value in UPDATES]


def runs_of(paths: Sequence[Path]) -> list[Path]:
    """Run directories (holding ``calibration.mcap``) named or held by a study directory, in seed order.

    Raises
    ------
    FileNotFoundError
        Naming a path that is neither a run nor a study.
    """
    runs = []
    for p in paths:
        if (p / 'calibration.mcap').is_file():
            runs.append(p)
            continue
        seeds = sorted((d for d in p.glob('seed_*') if (d / 'calibration.mcap').is_file()),
                       key=lambda d: int(d.name.split('_')[1]))
        if not seeds:
            raise FileNotFoundError(f'{p}: neither a run (no calibration.mcap) nor a study (no seed_<S>/calibration.mcap)')
        runs += seeds
    return runs


def main(argv: Sequence[str] | None = None) -> int:
    from body_schema.map_estimator import MapSettings
    from body_schema.noise import CAUTION_ALPHA, innovation_check

    ap = argparse.ArgumentParser(prog='python -m tools.innovations', description=__doc__.split('\n\n')[0])
    ap.add_argument('paths', type=Path, nargs='+', help='run directories or seed_study directories')
    ap.add_argument('--skip', type=int, default=MapSettings.warmup,
                    help="updates of the warm-up left out (the MAP's warmup)")
    ap.add_argument('--probability', type=float, default=MapSettings.change_probability,
                    help="chi-square probability of the bound (the change test's change_probability)")
    args = ap.parse_args(argv)
    try:
        runs = runs_of(args.paths)
        nis = {r: recorded_nis(r / 'calibration.mcap') for r in runs}
        checks = {r: innovation_check(v, args.skip, args.probability) for r, v in nis.items()}
    except (OSError, ValueError) as exc:
        print(f'innovations: {exc}', file=sys.stderr)
        return 2
    print(f'| run | updates | after the warm-up | median NIS | beyond the {args.probability:.2%} bound '
          f'| against the law (p < {CAUTION_ALPHA:g}) |')
    print('|---|---|---|---|---|---|')
    found = {r: c.findings() for r, c in checks.items() if c is not None}
    for r, c in checks.items():
        print(f'| {r} | {len(nis[r])} | ' + ('0 | n/a | n/a | n/a |' if c is None else
                                             f'{c.count} | {c.median:.1f} | {c.beyond} | '
                                             f'{", ".join(found[r]) or "none"} |'))
    done = [c for c in checks.values() if c is not None]
    if done:
        count, beyond = sum(c.count for c in done), sum(c.beyond for c in done)
        medians = np.array([c.median for c in done])
        print(f'\nOver {len(done)} runs: median NIS per run mean {medians.mean():.1f}, median {np.median(medians):.1f} '
              f'(5.3 if the noise law is right); beyond the bound in {beyond} of {count} '
              f'({beyond / count:.1%}; a right law: {1 - args.probability:.2%}), in {sum(c.beyond > 0 for c in done)} '
              f'of {len(done)} runs; the health check cautions against the law in '
              f'{sum(bool(f) for f in found.values())} of {len(done)} runs')
    return 0


if __name__ == '__main__':
    sys.exit(main())
