"""From the paper's system to ours, one change at a time: what each change buys, measured.

Usage::

    python -m calibration_bringup.ablation                      # R and AL, 50 repetitions x 50 iterations
    python -m calibration_bringup.ablation --repetitions 4 --iterations 20 --output /tmp/ablation
    make experiment-ablation

Row 0 is the paper's system (:data:`calibration_bringup.systems.PAPER`); row ``k`` adds the
``k``-th change of :data:`calibration_bringup.systems.ABLATION` to row ``k - 1``; the last row is
ours (the parameter files). Every row runs the same methods on the same repetitions (same real
robots, initial guesses and selector seeds), so each change is measured paired against the row
before it. Each row is an experiment (:mod:`calibration_bringup.experiment`, on one Ray runtime):
row 0 writes into ``results/experiment-paper`` and the last into ``results/experiment-ours``,
where ``make experiment-paper`` and ``make experiment`` write, so runs either made are shared
(their settings hashes match) and skipped; the rows between go to ``<output>/<NN>-<name>``.
Interrupted, the same command resumes; with ``--table-only`` it runs nothing and re-makes the
table and figure from the runs already finished (those of the requested repetitions).

The table (``<output>/ablation.md``, and ``ablation.png``) gives per row the final position and
orientation errors (mean, median), movement and discarded attempts of each method, and for AL
the paired change against the previous row (median difference, how often lower, Wilcoxon p), or
"same final errors" where the change does not touch the method's results (R never meets the selector).
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, TextIO

import numpy as np

from .experiment import METHODS, ExperimentConfig, plan_runs, ray_runtime, run_experiment
from .experiment_figures import ORDER, MethodRuns, load_metrics, paired_difference
from .systems import ABLATION, ablation_overrides

__all__ = ['Row', 'rows', 'table_markdown', 'plot', 'main']


@dataclass(frozen=True)
class Row:
    """One row of the ablation: a system and where its runs live."""

    index: int
    name: str
    change: str
    config: ExperimentConfig


def rows(repetitions: int = 50, iterations: int = 50, methods: Sequence[str] = ('R', 'AL'), jobs: int = 2,
         output: Path = Path('results/ablation'), seed_base: int = 0, record: bool = False,
         paper_output: Path = Path('results/experiment-paper'),
         ours_output: Path = Path('results/experiment-ours')) -> list[Row]:
    """The ablation's rows (experiments), from the paper's system to ours."""
    # Rows 0 and last share the directories of make experiment-paper / make experiment: their
    # combined metrics.csv, summary and figures (all seven methods) stay theirs.
    common = dict(repetitions=repetitions, iterations=iterations, methods=tuple(methods), jobs=jobs,
                  seed_base=seed_base, record=record, figures=False, combine=False)
    out = [Row(0, 'paper', "the paper's system", ExperimentConfig(system='paper', output=paper_output, **common))]
    last = len(ABLATION)
    for k, step in enumerate(ABLATION, start=1):
        if k == last:
            config = ExperimentConfig(system='ours', output=ours_output, **common)
        else:
            config = ExperimentConfig(system='ours', overrides=ablation_overrides(k),
                                      output=Path(output) / f'{k:02d}-{step.name}', **common)
        out.append(Row(k, step.name, step.change, config))
    return out


def _cell(m: MethodRuns, column: str, digits: int) -> str:
    v = m.final(column)
    return f'{np.nanmean(v):.{digits}f} ({np.nanmedian(v):.{digits}f})'


def _identical(a: MethodRuns, b: MethodRuns) -> bool:
    """Whether two rows' runs of a method end with the same errors on every shared repetition."""
    fa = dict(zip(a.repetitions.tolist(), zip(a.final('position_mm'), a.final('orientation_deg'))))
    fb = dict(zip(b.repetitions.tolist(), zip(b.final('position_mm'), b.final('orientation_deg'))))
    shared = fa.keys() & fb.keys()
    return bool(shared) and all(np.allclose(fa[r], fb[r], rtol=0.0, atol=1e-9, equal_nan=True) for r in shared)


def table_markdown(results: Sequence[tuple[Row, dict[str, MethodRuns]]], command: str) -> str:
    """The ablation table: one line per row and method, AL's paired change against the row before."""
    methods = sorted({m for _, data in results for m in data}, key=ORDER.index)
    lines = ['# Ablation: from the paper\'s system to ours, one change at a time', '',
             f'`{command}`. Each row adds one change to the row above (row 0: the paper\'s system, '
             'docs/paper_fidelity.md; the last row: ours). Same repetitions in every row (same real robots, '
             'initial guesses and selector seeds). Errors after the last iteration over 1000 configurations '
             'of the calibration box: mean (median) over the repetitions; movement: accumulated L1 joint '
             'movement; discarded: attempts that saw no marker. "vs above": the paired change of the final '
             'position error against the row above (median of the differences, repetitions where it is '
             'lower, two-sided Wilcoxon signed-rank p).', '',
             '| # | change | method | position mm | orientation deg | movement deg | discarded | vs above (position) |',
             '|---|---|---|---|---|---|---|---|']
    previous: dict[str, MethodRuns] = {}
    for row, data in results:
        for method in methods:
            if method not in data:
                continue
            m = data[method]
            versus = '-'
            if method in previous:
                n, d, lower, p = paired_difference(m, previous[method], 'position_mm')
                if n and _identical(m, previous[method]):
                    versus = 'same final errors'      # e.g. a selector change, which R never meets
                else:
                    versus = f'{d:+.2f} mm, {lower}/{n}, p = {p:.2g}' if n else '-'
            lines.append(f'| {row.index} | {row.change} | {method} | {_cell(m, "position_mm", 2)} | '
                         f'{_cell(m, "orientation_deg", 2)} | {np.nanmean(m.final("movement_deg")):.0f} | '
                         f'{np.nanmean(m.final("discarded")):.1f} | {versus} |')
        previous = data
    return '\n'.join(lines) + '\n'


def plot(results: Sequence[tuple[Row, dict[str, MethodRuns]]], path: Path) -> Path:
    """Final position and orientation error (mean, with the median as a dot) per row and method, log scale."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from .experiment_figures import _color

    methods = sorted({m for _, data in results for m in data}, key=ORDER.index)
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    x = np.arange(len(results))
    width = 0.8 / max(len(methods), 1)
    for ax, column, label in zip(axes, ('position_mm', 'orientation_deg'), ('position error [mm]',
                                                                            'orientation error [deg]')):
        for i, method in enumerate(methods):
            means = [np.nanmean(d[method].final(column)) if method in d else np.nan for _, d in results]
            medians = [np.nanmedian(d[method].final(column)) if method in d else np.nan for _, d in results]
            pos = x + (i - (len(methods) - 1) / 2) * width
            ax.bar(pos, means, width, color=_color(method), label=method)
            ax.plot(pos, medians, 'k.', markersize=4)
        ax.set_yscale('log')
        ax.set_ylabel(label)
        ax.grid(True, axis='y', which='both', alpha=0.3)
    axes[0].legend()
    axes[1].set_xticks(x, [f'{r.index} {r.name}' for r, _ in results], rotation=35, ha='right')
    fig.suptitle("From the paper's system (0) to ours: bars mean, dots median")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='ablation', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--repetitions', type=int, default=50, help='repetitions per row [50]')
    p.add_argument('--iterations', type=int, default=50, help='iterations per run [50]')
    p.add_argument('--methods', nargs='+', default=['R', 'AL'], choices=list(METHODS), metavar='METHOD',
                   help='methods every row runs [R AL]')
    p.add_argument('--jobs', type=int, default=2, help='runs in flight [2]')
    p.add_argument('--output', type=Path, default=Path('results/ablation'),
                   help='where the rows between the paper and ours go, and the table [results/ablation]')
    p.add_argument('--paper-output', type=Path, default=Path('results/experiment-paper'),
                   help="row 0's experiment (shared with make experiment-paper) [results/experiment-paper]")
    p.add_argument('--ours-output', type=Path, default=Path('results/experiment-ours'),
                   help="the last row's experiment (shared with make experiment) [results/experiment-ours]")
    p.add_argument('--seed-base', type=int, default=0, help='repetition r has seed seed_base + r [0]')
    p.add_argument('--table-only', action='store_true',
                   help='run nothing: make the table and figure from the runs already finished')
    return p


def main(argv: Sequence[str] | None = None, stream: TextIO = sys.stderr) -> int:
    """Console entry point ``ablation``."""
    from tqdm import tqdm

    args = build_parser().parse_args(argv)
    try:
        table = rows(args.repetitions, args.iterations, args.methods, args.jobs, args.output, args.seed_base,
                     paper_output=args.paper_output, ours_output=args.ours_output)
    except ValueError as exc:
        print(f'ablation: {exc}', file=stream)
        return 2
    t0 = time.monotonic()
    failed = 0
    with ray_runtime(None, args.jobs) if not args.table_only else contextlib.nullcontext():
        for row in table if not args.table_only else ():
            stream.write(f'ablation: row {row.index}/{len(table) - 1} ({row.name}: {row.change}) -> '
                         f'{row.config.output}\n')
            try:
                failed += len(run_experiment(row.config, stream=stream).failures)
            except ValueError as exc:       # finished runs there made with other settings
                print(f'ablation: {exc}', file=stream)
                return 2
    results = []
    for row in table:
        done = [p for p in (spec.path(row.config.output, '.csv') for spec in plan_runs(row.config)) if p.exists()]
        if done:
            results.append((row, load_metrics(done)))
    if not results:
        print(f'ablation: no finished runs under {args.output}', file=stream)
        return 1
    command = 'python -m calibration_bringup.ablation' + ''.join(
        f' {a}' for a in (argv if argv is not None else sys.argv[1:]) if a != '--table-only')
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'ablation.md').write_text(table_markdown(results, command.strip()))
    plot(results, out / 'ablation.png')
    stream.write(f'ablation: {out / "ablation.md"}, {out / "ablation.png"}; finished in '
                 f'{tqdm.format_interval(time.monotonic() - t0)}'
                 f'{f", {failed} run(s) failed (rerun to retry them)" if failed else ""}\n')
    return 1 if failed else 0


if __name__ == '__main__':
    from calibration_bringup.ablation import main as _main

    sys.exit(_main())
