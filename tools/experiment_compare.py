"""Compare two experiments method by method on their shared seeds (paired).

Two ``make experiment`` output directories meet the same real robots and initial guesses in the
runs with the same seed, so their final errors pair up by seed (by repetition for CSVs without a
``seed`` column); runs of another seed base share none, and are refused. For every method both
ran, this prints, over the shared seeds, each experiment's mean and median final position and
orientation error, discarded attempts and movement, the ratio of the means (second over first)
with its 95% paired bootstrap interval
(:func:`~calibration_bringup.experiment_figures.paired_ratio_interval`), and the paired test of
:func:`calibration_bringup.experiment_figures.paired_difference` (median difference, how often the
second is lower, two-sided Wilcoxon p). A closing note says whether the two were made on the same
numeric environment, where their ``config.json`` recorded it.

Usage (from the repository root)::

    python -m tools.experiment_compare results/one-eye results/experiment-ours --names "one eye" "both eyes"
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from calibration_bringup.experiment import read_environments
from calibration_bringup.experiment_figures import (MethodRuns, interval_text, load_metrics, paired_difference,
                                                   paired_finals, paired_ratio_interval)
from calibration_interfaces.provenance import environment_note

#: (CSV column, label, digits) compared.
FIGURES = (('position_mm', 'position [mm]', 3), ('orientation_deg', 'orientation [deg]', 3),
           ('discarded', 'discarded', 1), ('movement_deg', 'movement [deg]', 0))


def compare(first: dict[str, MethodRuns], second: dict[str, MethodRuns], names: Sequence[str]) -> list[str]:
    """Markdown table rows comparing the methods both experiments ran.

    Raises
    ------
    ValueError
        If no method is in both, or a method both ran shares no seed (another seed base): nothing
        to pair, which an empty table would hide.
    """
    a, b = names
    methods = [m for m in first if m in second]
    if not methods:
        raise ValueError(f'no method in both experiments: {list(first)} and {list(second)}')
    for method in methods:
        if not paired_finals(first[method], second[method], 'position_mm')[0].size:
            raise ValueError(f'{method}: no seed in both experiments (another --seed-base?)')
    lines = [f'| method | figure | {a}: mean (median) | {b}: mean (median) | {b} / {a} | 95% interval | pairs | '
             f'median difference ({b} - {a}) | {b} lower | p |', '|---|---|---|---|---|---|---|---|---|---|']
    for method in methods:
        for column, label, digits in FIGURES:
            # Over the shared seeds, as the interval and the test: an experiment of 50 repetitions
            # against one of its first 20 compares those 20 (each mean over its own runs did not).
            fa, fb = paired_finals(first[method], second[method], column)
            # Second minus first: negative favours the second.
            n, median, second_lower, p = paired_difference(second[method], first[method], column)
            interval = interval_text(*paired_ratio_interval(fa, fb))
            lines.append(f'| {method} | {label} | {np.mean(fa):.{digits}f} ({np.median(fa):.{digits}f}) | '
                         f'{np.mean(fb):.{digits}f} ({np.median(fb):.{digits}f}) | {np.mean(fb) / np.mean(fa):.2f} | '
                         f'{interval} | {n} | {median:+.{digits}f} | {second_lower} | {p:.2g} |')
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.experiment_compare', description=__doc__.split('\n\n')[0])
    ap.add_argument('first', type=Path, help='the baseline experiment directory (its metrics.csv)')
    ap.add_argument('second', type=Path, help='the experiment compared with it')
    ap.add_argument('--names', nargs=2, default=None, help='labels of the two [their directory names]')
    args = ap.parse_args(argv)
    try:
        first, second = (load_metrics(d / 'metrics.csv') for d in (args.first, args.second))
        names = args.names or [args.first.name, args.second.name]
        lines = compare(first, second, names)
        note = environment_note({n: read_environments(d) for n, d in zip(names, (args.first, args.second))})
    except (OSError, ValueError) as exc:
        print(f'experiment_compare: {exc}', file=sys.stderr)
        return 2
    print('\n'.join(lines + (['', note] if note else [])))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
