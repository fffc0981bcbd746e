"""Compare seed studies seed by seed: does one setting end better than another on the same seeds?

Each study is a :mod:`tools.seed_study` output directory (its ``seed_<S>/summary.json``) or a
committed ``summary.md`` of one (rounded as printed: 2 decimals in mm, 3 in deg). The first study
is the baseline; every other is paired with it on the seeds both have, so that each seed's real
robot, camera and marker errors and initial guess are shared (the selections are not: a run
parts from its pair at the first attempt that differs). Per figure (final position and
orientation error, the information limit, and the realised error over that limit): each study's
mean, median and range, the ratio of the means to the baseline's with its 95% interval (a
percentile bootstrap over the common seeds, resampled in pairs), in how many seeds the study was
lower, and the two-sided Wilcoxon signed-rank p of the paired differences (scipy). Where the runs
recorded their numeric environment, a closing note says whether the studies were made on the same
one (on another, runs of the same seed do not repeat one another step by step).

Usage (from the repository root)::

    python -m tools.study_compare docs/results/safety/ur5e-summary.md results/ur5e-nocheck \\
        --names "with the check" "without" --output comparison.md
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.stats import wilcoxon

from calibration_bringup.experiment_figures import interval_text, paired_ratio_interval
from calibration_interfaces.provenance import distinct_environments, environment_note
from tools.seed_study import read_records, read_summary

__all__ = ['Study', 'load_study', 'FIGURES', 'compare', 'main']


@dataclass(frozen=True)
class Study:
    """One seed study: its name and each seed's (partial) ``summary.json`` record."""

    name: str
    records: dict[int, dict[str, Any]]


def load_study(path: Path, name: str | None = None) -> Study:
    """A study from its output directory (``seed_<S>/summary.json``) or a ``summary.md``; or from
    several, joined by ``+`` (``a/summary.md+results/more-seeds``: one study run in parts, e.g.
    its last seeds in another session), none of which may hold a seed another holds.

    Raises
    ------
    FileNotFoundError
        If ``path`` (or a part) does not exist.
    ValueError
        If a directory holds no ``seed_<S>/summary.json``, a file no seed row, or two parts the same
        seed (the message names the path).
    """
    path = Path(path)
    if not path.exists() and '+' in str(path):
        records: dict[int, dict[str, Any]] = {}
        for part in str(path).split('+'):
            more = load_study(Path(part)).records
            if common := sorted(set(records) & set(more)):
                raise ValueError(f'study {path}: seeds {common} are in {part} and in an earlier part')
            records.update(more)
        return Study(name or str(path), records)
    if not path.exists():
        raise FileNotFoundError(f'study {path}: no such file or directory')
    if path.is_dir():
        records = read_records(path)
        if not records:
            raise ValueError(f'study {path}: no seed_<S>/summary.json in it (a tools.seed_study output directory?)')
    else:
        try:
            records = read_summary(path.read_text())
        except ValueError as exc:
            raise ValueError(f'study {path}: {exc}') from None
    return Study(name or str(path), records)


def _ratio(record: dict[str, Any], key: str) -> float:
    return record['final'][key] / record['information_limit'][key]


#: (label, format, the figure from one seed's record); lower is better for each.
FIGURES: tuple[tuple[str, str, Callable[[dict[str, Any]], float]], ...] = (
    ('final position error [mm]', '.3f', lambda r: r['final']['position_mm']),
    ('final orientation error [deg]', '.4f', lambda r: r['final']['orientation_deg']),
    ('information limit, position [mm]', '.3f', lambda r: r['information_limit']['position_mm']),
    ('information limit, orientation [deg]', '.4f', lambda r: r['information_limit']['orientation_deg']),
    ('final / limit, position', '.2f', lambda r: _ratio(r, 'position_mm')),
    ('final / limit, orientation', '.2f', lambda r: _ratio(r, 'orientation_deg')),
)


def _spread(v: np.ndarray, fmt: str) -> str:
    return f'{v.mean():{fmt}} / {np.median(v):{fmt}} / {v.min():{fmt}}-{v.max():{fmt}}'


def _wilcoxon_p(a: np.ndarray, b: np.ndarray) -> float:
    d = a - b
    if not np.any(d):
        return 1.0                         # identical on every seed: no evidence of a difference
    return float(wilcoxon(a, b).pvalue)


def compare(studies: Sequence[Study]) -> str:
    """The Markdown comparison of ``studies[1:]`` with ``studies[0]`` on their common seeds.

    Raises
    ------
    ValueError
        If fewer than two studies are given, or one shares no seed with the baseline.
    """
    if len(studies) < 2:
        raise ValueError(f'compare needs a baseline and at least one other study, got {len(studies)}')
    base = studies[0]
    lines = [f'Baseline: {base.name} ({len(base.records)} seeds). Each figure: mean / median / range over '
             'the seeds both studies have; x: ratio of the means, with its 95% interval (percentile bootstrap '
             'over the seeds, resampled in pairs); lower: seeds where the study is lower than the baseline; '
             'p: two-sided Wilcoxon signed-rank test of the paired differences.', '']
    for other in studies[1:]:
        seeds = sorted(set(base.records) & set(other.records))
        if not seeds:
            raise ValueError(f'study {other.name!r} shares no seed with the baseline {base.name!r}')
        lines += [f'**{other.name}** against {base.name}: {len(seeds)} common seeds '
                  f'({seeds[0]}-{seeds[-1]}' + (')' if len(seeds) == seeds[-1] - seeds[0] + 1 else ', not all)'),
                  '', f'| figure | {base.name} | {other.name} | x | 95% interval | lower | p |',
                  '|---|---|---|---|---|---|---|']
        for label, fmt, get in FIGURES:
            a = np.array([get(base.records[s]) for s in seeds])
            b = np.array([get(other.records[s]) for s in seeds])
            interval = interval_text(*paired_ratio_interval(a, b))
            lines.append(f'| {label} | {_spread(a, fmt)} | {_spread(b, fmt)} | {b.mean() / a.mean():.3f} | '
                         f'{interval} | {int(np.sum(b < a))} of {len(seeds)} | {_wilcoxon_p(b, a):.2g} |')
        lines.append('')
    note = environment_note({s.name: distinct_environments(r.get('environment') for r in s.records.values())
                             for s in studies})
    if note:
        lines += [note, '']
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.study_compare', description=__doc__.split('\n\n')[0])
    ap.add_argument('studies', nargs='+', type=Path,
                    help='the baseline first: seed_study directories or summary.md files (parts of one study joined by +)')
    ap.add_argument('--names', nargs='+', help='a short name per study (default: the paths)')
    ap.add_argument('--output', type=Path, help='also write the comparison here')
    args = ap.parse_args(argv)
    if args.names and len(args.names) != len(args.studies):
        ap.error(f'--names: {len(args.names)} names for {len(args.studies)} studies')
    names = args.names or [None] * len(args.studies)
    try:
        text = compare([load_study(p, n) for p, n in zip(args.studies, names)])
    except (OSError, ValueError) as exc:
        print(f'study_compare: {exc}', file=sys.stderr)
        return 2
    print(text)
    if args.output:
        args.output.write_text(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
