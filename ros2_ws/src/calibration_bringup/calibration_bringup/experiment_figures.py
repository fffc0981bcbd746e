"""Figures and summary table of the experiment, from its CSV (re-plot without re-running).

Usage::

    python -m calibration_bringup.experiment_figures [results/experiment-ours]

Reads ``<dir>/metrics.csv`` (written by :mod:`calibration_bringup.experiment`; if it is missing,
the per-run CSVs under ``<dir>/runs`` are read instead) and writes:

* ``figures/error_vs_iteration.png``: average position and orientation error vs iteration, mean
  with standard-deviation bars over repetitions, for R, AL, UCSAL and CCSAL (pose-dependent noise);
* ``figures/error_vs_movement.png``: the same errors vs the mean accumulated joint movement;
* ``figures/discarded.png``: discarded samples (failed attempts) per run, every method;
* ``figures/cn_vs_pose_dependent.png``: AL, UCSAL, CCSAL with the pose-dependent noise model vs
  the constant one (CN);
* ``summary.md``: final errors (mean +- std), total movement, movement relative to AL (with the
  same noise model), discarded samples, paired comparisons, the paper's four claims tested on
  these runs (:func:`paper_claims`), and the per-iteration time breakdown.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .run_check import observations_used

__all__ = ['MethodRuns', 'load_metrics', 'paired_finals', 'paired_difference', 'paired_ratio_interval',
           'interval_text', 'Claim', 'paper_claims', 'claims_markdown', 'summary_markdown', 'plot_all', 'render', 'main']

#: Plot order and style: the paper's four methods, then the CN variants.
ORDER = ('R', 'AL', 'UCSAL', 'CCSAL', 'AL-CN', 'UCSAL-CN', 'CCSAL-CN')
POSE_DEPENDENT = ('R', 'AL', 'UCSAL', 'CCSAL')
COLORS = {'R': 'tab:gray', 'AL': 'tab:blue', 'UCSAL': 'tab:orange', 'CCSAL': 'tab:green'}
#: Numeric columns kept per method as (runs, iterations + 1) arrays.
NUMERIC = ('position_mm', 'orientation_deg', 'movement_deg', 'discarded', 'selection_s', 'move_sim_s',
           'sim_s', 'render_s', 'detect_s', 'estimator_s', 'selector_s', 'recorder_s', 'cpu_s', 'wall_s')
#: Columns without which there is nothing to report.
REQUIRED = ('position_mm', 'orientation_deg', 'movement_deg', 'discarded')
#: Per-iteration time breakdown of the summary: column -> heading.
TIMES = {'selection_s': 'selection [s]', 'move_sim_s': 'move, sim [s]', 'render_s': 'render [s]',
         'sim_s': 'sim node [s]', 'detect_s': 'detection [s]', 'estimator_s': 'update [s]',
         'recorder_s': 'recording [s]', 'cpu_s': 'CPU [s]', 'wall_s': 'wall [s]'}


def _base(method: str) -> str:
    return method.removesuffix('-CN')


def _color(method: str) -> str:
    return COLORS.get(_base(method), 'black')


@dataclass
class MethodRuns:
    """All runs of one method: each numeric column as an array (runs, iterations + 1), NaN-padded,
    plus ``rejected``: the running count of observations the estimator's gate refused, and (from
    :func:`load_metrics`) ``used``: the running count of those that reached the estimate.
    ``seeds``: each run's repetition seed (``seed_base + repetition``), when the CSV has them."""

    method: str
    repetitions: NDArray[np.int64]
    columns: dict[str, NDArray[np.float64]]
    seeds: NDArray[np.int64] | None = None

    @property
    def n_runs(self) -> int:
        return int(self.repetitions.size)

    @property
    def iterations(self) -> int:
        return self.columns['position_mm'].shape[1] - 1

    def final(self, column: str) -> NDArray[np.float64]:
        """The last value of ``column`` of every run, shape (runs,)."""
        a = self.columns[column]
        last = np.array([np.flatnonzero(np.isfinite(r))[-1] if np.isfinite(r).any() else 0 for r in a])
        return a[np.arange(a.shape[0]), last]

    def per_iteration(self, column: str) -> NDArray[np.float64]:
        """Values of ``column`` over every iteration >= 1 of every run (flattened, NaN dropped)."""
        v = self.columns[column][:, 1:].ravel()
        return v[np.isfinite(v)]


def _float(text: str) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return float('nan')


def load_metrics(path: Path | Sequence[Path]) -> dict[str, MethodRuns]:
    """Per-method runs from ``metrics.csv`` or from a list of per-run CSVs.

    Raises
    ------
    ValueError
        If a CSV lacks a column of :data:`REQUIRED` (time columns may be missing) or holds no rows.
    """
    paths = [Path(path)] if isinstance(path, (str, Path)) else [Path(p) for p in path]
    runs: dict[tuple[str, int], dict[int, dict[str, str]]] = {}
    for p in paths:
        with p.open(newline='') as f:
            reader = csv.DictReader(f)
            missing = {'method', 'repetition', 'iteration', *REQUIRED} - set(reader.fieldnames or ())
            if missing:
                raise ValueError(f'{p}: missing columns {sorted(missing)}')
            for row in reader:
                runs.setdefault((row['method'], int(row['repetition'])), {})[int(row['iteration'])] = row
    if not runs:
        raise ValueError(f'no rows in {", ".join(map(str, paths))}')
    out: dict[str, MethodRuns] = {}
    methods = sorted({m for m, _ in runs}, key=lambda m: (ORDER.index(m) if m in ORDER else len(ORDER), m))
    for m in methods:
        reps = sorted(r for mm, r in runs if mm == m)
        n = max(max(runs[(m, r)]) for r in reps) + 1
        cols = {c: np.full((len(reps), n), np.nan) for c in (*NUMERIC, 'rejected', 'used')}
        for i, r in enumerate(reps):
            for it, row in runs[(m, r)].items():
                for c in NUMERIC:
                    cols[c][i, it] = _float(row.get(c, ''))     # time columns may be absent: NaN
                cols['rejected'][i, it] = row.get('outcome') == 'rejected'
                cols['used'][i, it] = observations_used([row.get('outcome', '')])
            # Observations refused by the estimator's gate, and used, so far (NaN stays NaN past a run's end).
            cols['rejected'][i] = np.cumsum(cols['rejected'][i])
            cols['used'][i] = np.cumsum(cols['used'][i])
        seeds = [runs[(m, r)][min(runs[(m, r)])].get('seed', '') for r in reps]
        out[m] = MethodRuns(m, np.array(reps), cols,
                            np.array(seeds, dtype=np.int64) if all(str(x).strip() for x in seeds) else None)
    return out


# ------------------------------------------------------------------------------------------
# Table

def _pm(values: NDArray[np.float64], digits: int) -> str:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return '-'
    return f'{v.mean():.{digits}f} +- {v.std():.{digits}f}' if v.size > 1 else f'{v.mean():.{digits}f}'


def _relative_to_al(data: dict[str, MethodRuns], name: str, column: str) -> str:
    """Mean final ``column`` of ``name`` over AL's with the same noise model (AL-CN for the CN
    methods), two decimals; ``'-'`` for AL itself, without AL, or when AL's mean is not positive."""
    ref = 'AL-CN' if name.endswith('-CN') else 'AL'
    if ref not in data or name == ref:
        return '-'
    base = np.nanmean(data[ref].final(column))
    return f'{np.nanmean(data[name].final(column)) / base:.2f}' if base > 0 else '-'


def paired_finals(first: MethodRuns, second: MethodRuns, column: str
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Final ``column`` of two methods over the runs both made on the same seeds (the same real
    robot and initial guess; the repetitions where either lacks seeds), in seed order: (P,) each."""
    use_seeds = first.seeds is not None and second.seeds is not None
    fa = dict(zip((first.seeds if use_seeds else first.repetitions).tolist(), first.final(column)))
    fb = dict(zip((second.seeds if use_seeds else second.repetitions).tolist(), second.final(column)))
    shared = sorted(fa.keys() & fb.keys())
    return np.array([fa[r] for r in shared], dtype=float), np.array([fb[r] for r in shared], dtype=float)


def paired_difference(first: MethodRuns, second: MethodRuns, column: str) -> tuple[int, float, int, float]:
    """Paired final values of two methods over their shared repetitions.

    Returns
    -------
    pairs : int
    median_difference : float
        Median of ``first - second``.
    first_lower : int
        Pairs where ``first`` is lower.
    p_value : float
        Two-sided Wilcoxon signed-rank test (NaN with fewer than two non-zero differences).
    """
    from scipy.stats import wilcoxon

    a, b = paired_finals(first, second, column)
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    if d.size == 0:
        return 0, float('nan'), 0, float('nan')
    p = float(wilcoxon(d).pvalue) if np.count_nonzero(d) >= 2 else float('nan')
    return int(d.size), float(np.median(d)), int(np.sum(d < 0)), p


def paired_ratio_interval(a: ArrayLike, b: ArrayLike, confidence: float = 0.95, resamples: int = 10_000,
                          seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of ``mean(b) / mean(a)`` over pairs ``(a_i, b_i)`` resampled
    together (a repetition's, or a seed's, two runs meet the same robot and initial guess).

    Parameters
    ----------
    a, b : array_like, shape (N,)
        Paired values; pairs with a non-finite value are dropped.

    Returns
    -------
    low, high : float
        NaN with fewer than two pairs or ``mean(a) = 0``; both the ratio when every pair has the
        same one (scipy's bootstrap refuses a degenerate sample); ``high`` may be inf when some
        ``a`` are 0 (a resample of only those has no ratio).
    """
    from scipy.stats import bootstrap

    pairs = np.column_stack([np.asarray(a, dtype=float), np.asarray(b, dtype=float)])
    pairs = pairs[np.all(np.isfinite(pairs), axis=1)]
    if len(pairs) < 2 or pairs[:, 0].mean() == 0:
        return float('nan'), float('nan')
    with np.errstate(divide='ignore', invalid='ignore'):
        ratios = pairs[:, 1] / pairs[:, 0]
        if np.all(np.isfinite(ratios)) and np.ptp(ratios) == 0:
            r = float(pairs[:, 1].mean() / pairs[:, 0].mean())
            return r, r
        res = bootstrap((pairs[:, 0], pairs[:, 1]), lambda x, y, axis=-1: y.mean(axis) / x.mean(axis),
                        paired=True, confidence_level=confidence, n_resamples=resamples, method='percentile',
                        rng=seed)
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def interval_text(low: float, high: float) -> str:
    """A ratio's interval as the comparison tables print it: ``'0.94-1.16'``, ``'-'`` when there is none."""
    return '-' if np.isnan(low) else f'{low:.2f}-{high:.2f}'


#: Significance level of the paired tests behind the claims.
ALPHA = 0.05


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims tested on an experiment's runs.

    Attributes
    ----------
    claim : str
    verdict : str
        ``'yes'``, ``'partly'`` (some of its parts hold), ``'no'``, or ``'-'`` (methods missing).
    evidence : str
        The figures behind the verdict.
    """

    claim: str
    verdict: str
    evidence: str


def _verdict(parts: Sequence[bool]) -> str:
    return '-' if not parts else 'yes' if all(parts) else 'partly' if any(parts) else 'no'


def _better(first: MethodRuns, second: MethodRuns, column: str) -> tuple[bool, str]:
    """Whether ``first`` ends lower than ``second`` (paired: median difference < 0, Wilcoxon p < ALPHA)."""
    n, d, lower, p = paired_difference(first, second, column)
    return (n > 0 and d < 0 and p < ALPHA), f'{d:+.3g}, {lower}/{n} lower, p = {p:.2g}'


def paper_claims(data: dict[str, MethodRuns]) -> list[Claim]:
    """The paper's four qualitative claims (issue #28's operational form), tested on ``data``.

    1. AL's mean final position error within 1.25x R's, and AL better than R in orientation
       (paired, p < :data:`ALPHA`).
    2. UCSAL and CCSAL at <= 0.6x AL's mean movement with <= 1.25x its mean final position and
       orientation errors.
    3. The pose-dependent noise model better than CN for AL, UCSAL and CCSAL, in position and in
       orientation (paired, p < :data:`ALPHA`).
    4. AL, UCSAL and CCSAL discard fewer attempts than R (paired, p < :data:`ALPHA`).
    """
    def mean(name: str, column: str) -> float:
        return float(np.nanmean(data[name].final(column)))

    out: list[Claim] = []
    parts: list[bool] = []
    evidence = []
    if {'AL', 'R'} <= set(data):
        ratio = mean('AL', 'position_mm') / mean('R', 'position_mm')
        ok, text = _better(data['AL'], data['R'], 'orientation_deg')
        parts, evidence = [ratio <= 1.25, ok], [f'position AL / R = {ratio:.2f}', f'orientation AL - R: {text}']
    out.append(Claim('AL within 1.25x of R in position and better than R in orientation', _verdict(parts),
                     '; '.join(evidence)))
    parts, evidence = [], []
    for name in ('UCSAL', 'CCSAL'):
        if {name, 'AL'} <= set(data):
            mv, pe, oe = (mean(name, c) / mean('AL', c) for c in ('movement_deg', 'position_mm', 'orientation_deg'))
            parts.append(mv <= 0.6 and pe <= 1.25 and oe <= 1.25)
            evidence.append(f'{name}: movement {mv:.2f}x, position {pe:.2f}x, orientation {oe:.2f}x')
    out.append(Claim("UCSAL and CCSAL at <= 0.6x AL's movement with <= 1.25x its error", _verdict(parts),
                     '; '.join(evidence)))
    parts, evidence = [], []
    for name in ('AL', 'UCSAL', 'CCSAL'):
        if {name, f'{name}-CN'} <= set(data):
            for column, unit in (('position_mm', 'mm'), ('orientation_deg', 'deg')):
                ok, text = _better(data[name], data[f'{name}-CN'], column)
                parts.append(ok)
                evidence.append(f'{name} - {name}-CN {unit}: {text}')
    out.append(Claim('the pose-dependent noise model beats constant noise (CN)', _verdict(parts),
                     '; '.join(evidence)))
    parts, evidence = [], []
    for name in ('AL', 'UCSAL', 'CCSAL'):
        if {name, 'R'} <= set(data):
            ok, text = _better(data[name], data['R'], 'discarded')
            parts.append(ok)
            evidence.append(f'{name} {mean(name, "discarded"):.1f} vs R {mean("R", "discarded"):.1f} ({text})')
    out.append(Claim('the active methods discard fewer attempts than R', _verdict(parts), '; '.join(evidence)))
    return out


def claims_markdown(data: dict[str, MethodRuns]) -> list[str]:
    """The claims as a Markdown section (lines)."""
    lines = ['', "## The paper's claims", '',
             f'Tested on these runs (paired tests: median difference, repetitions where the first is lower, '
             f'two-sided Wilcoxon signed-rank p; significant at p < {ALPHA}). "partly": some of the claim\'s '
             'parts hold.', '', '| claim | holds | evidence |', '|---|---|---|']
    lines += [f'| {c.claim} | {c.verdict} | {c.evidence or "-"} |' for c in paper_claims(data)]
    return lines


def summary_markdown(data: dict[str, MethodRuns], system: str | None = None) -> str:
    """The summary tables (Markdown): accuracy and movement, then time per iteration; ``system``
    (the runner's ``--system``), if known, in the heading."""
    n_runs = {m.n_runs for m in data.values()}
    its = {m.iterations for m in data.values()}
    lines = [f'# Experiment summary{f" (system: {system})" if system else ""}', '',
             f'{", ".join(data)}; {"/".join(map(str, sorted(n_runs)))} repetitions, '
             f'{"/".join(map(str, sorted(its)))} iterations per run. Mean +- standard deviation over '
             'repetitions of the values after the last iteration; errors averaged over 1000 '
             'configurations of the calibration box; "discarded": failed detections; "rejected": '
             'detections the estimator\'s outlier gate refused.', '',
             '| method | runs | position [mm] | orientation [deg] | initial position [mm] | movement [deg] '
             '| movement / AL | discarded | rejected by the gate |',
             '|---|---|---|---|---|---|---|---|---|']
    for name, m in data.items():
        lines.append(f'| {name} | {m.n_runs} | {_pm(m.final("position_mm"), 2)} | '
                     f'{_pm(m.final("orientation_deg"), 2)} | {_pm(m.columns["position_mm"][:, 0], 1)} | '
                     f'{_pm(m.final("movement_deg"), 0)} | {_relative_to_al(data, name, "movement_deg")} | '
                     f'{_pm(m.final("discarded"), 1)} | {_pm(m.final("rejected"), 1)} |')
    unused = [f'{name} rep {rep}' for name, m in data.items() if 'used' in m.columns
              for rep, used in zip(m.repetitions.tolist(), m.final('used')) if used == 0]
    if unused:
        # Results, kept in the statistics above; the reader should know why they sit at the initial error.
        lines += ['', f'No observation reached the estimate in {len(unused)} run(s), whose final error is '
                      f'the initial guess\'s: {", ".join(unused)}.']
    lines += ['', '| method | position [mm] median | orientation [deg] median | error / AL (mean position) |',
              '|---|---|---|---|']
    for name, m in data.items():
        lines.append(f'| {name} | {np.nanmedian(m.final("position_mm")):.2f} | '
                     f'{np.nanmedian(m.final("orientation_deg")):.2f} | '
                     f'{_relative_to_al(data, name, "position_mm")} |')
    pairs = [(a, b) for a, b in (('AL', 'R'), ('AL', 'AL-CN'), ('UCSAL', 'UCSAL-CN'), ('CCSAL', 'CCSAL-CN'))
             if a in data and b in data]
    if pairs:
        lines += ['', '## Paired comparisons', '',
                  'Final errors of two methods over the repetitions both ran (same real robot and initial '
                  'guess): median of the paired differences (first minus second; negative favours the first), '
                  'how often the first is lower, and the two-sided Wilcoxon signed-rank p-value.', '',
                  '| first vs second | pairs | position: median diff [mm], first lower, p | '
                  'orientation: median diff [deg], first lower, p |', '|---|---|---|---|']
        for a, b in pairs:
            cells = [paired_difference(data[a], data[b], c) for c in ('position_mm', 'orientation_deg')]
            n = cells[0][0]
            lines.append(f'| {a} vs {b} | {n} | ' + ' | '.join(
                f'{d:+.3f}, {k}/{n}, p = {pv:.2g}' if n else '-' for n, d, k, pv in cells) + ' |')
    if 'AL' in data:
        al = data['AL']
        p, o = np.nanmean(al.final('position_mm')), np.nanmean(al.final('orientation_deg'))
        lines += ['', f'AL after {al.iterations} iterations: {p:.2f} mm (target <= 5 mm: '
                      f'{"met" if p <= 5 else "not met"}), {o:.2f} deg (target <= 2 deg: '
                      f'{"met" if o <= 2 else "not met"}).']
    lines += claims_markdown(data)
    lines += ['', '## Time per iteration', '',
              'Means over every iteration of every run. Wall seconds except the simulated move; '
              '"sim node" is the simulator\'s callbacks (physics, rendering, publishing), "detection" '
              'the detector\'s, "update" the estimator\'s, "CPU" the CPU time of the run\'s process '
              '(below the wall time when the machine is shared), "other" the wall time outside every '
              'node callback (executor, middleware, the probe).', '',
              '| method | ' + ' | '.join(TIMES.values()) + ' | other [s] |',
              '|---|' + '---|' * (len(TIMES) + 1)]
    for name, m in data.items():
        means = {c: float(np.mean(m.per_iteration(c))) if m.per_iteration(c).size else float('nan') for c in TIMES}
        callbacks = sum(float(np.mean(m.per_iteration(c))) for c in
                        ('sim_s', 'detect_s', 'estimator_s', 'selector_s', 'recorder_s') if m.per_iteration(c).size)
        other = means['wall_s'] - callbacks
        lines.append(f'| {name} | ' + ' | '.join(f'{means[c]:.3f}' for c in TIMES) + f' | {other:.3f} |')
    return '\n'.join(lines) + '\n'


# ------------------------------------------------------------------------------------------
# Figures

def _mean_std(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)     # all-NaN columns of shorter runs
        return np.nanmean(a, axis=0), np.nanstd(a, axis=0)


def _ticks(iterations: int, groups: int) -> list[int]:
    """Iterations at which grouped bars are drawn: 0 and every ``iterations / groups`` (paper:
    0, 12, 24, 36, 48 of 50)."""
    step = max(1, int(iterations / groups))
    return list(range(0, iterations + 1, step))


def _grouped_bars(ax: Any, data: dict[str, MethodRuns], methods: Sequence[str], column: str,
                  iterations: Sequence[int]) -> None:
    """Bars of the mean over repetitions at ``iterations``, one per method, std bars upward (the
    paper's style: on a log axis a downward bar would leave the plot)."""
    width = 0.8 / len(methods)
    x = np.arange(len(iterations), dtype=float)
    for k, m in enumerate(methods):
        a = data[m].columns[column]
        cols = [i for i in iterations if i < a.shape[1]]
        mean, std = _mean_std(a[:, cols])
        bars = ax.bar(x[:len(cols)] + (k - (len(methods) - 1) / 2) * width, mean, width,
                      yerr=[np.zeros_like(std), std], capsize=2, label=m, color=_color(m),
                      error_kw={'elinewidth': 0.8})
        if m.endswith('-CN'):
            for b in bars:
                b.set_hatch('//')
                b.set_edgecolor('white')
    ax.set_xticks(x, [str(i) for i in iterations])


_ERRORS = (('position_mm', 'average position error [mm]'), ('orientation_deg', 'average orientation error [deg]'))


def _log_y(ax: Any) -> None:
    """Log y axis with plain numbers (2, 5, 10, 20, not 2 x 10^0)."""
    from matplotlib.ticker import FuncFormatter, LogFormatter

    ax.set_yscale('log')
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:g}'))
    ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(1.5, 0.5)))


def plot_all(data: dict[str, MethodRuns], out_dir: Path) -> list[Path]:
    """Write the figures (PNG) into ``out_dir``; returns their paths.

    As in the paper: error vs iteration as grouped bars (mean, std upward) on a log axis at
    every quarter of the run; error vs accumulated movement as mean curves; CN vs pose-dependent
    noise as grouped bars at the start, middle and end; discarded samples as bars with std.
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    n_its = max(m.iterations for m in data.values())

    def save(fig: Any, name: str) -> None:
        path = out_dir / name
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)

    def error_bars(methods: Sequence[str], iterations: Sequence[int], name: str) -> None:
        fig, axes = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
        for ax, (col, label) in zip(axes, _ERRORS):
            _grouped_bars(ax, data, methods, col, iterations)
            ax.set(ylabel=label)
            _log_y(ax)
            ax.grid(True, axis='y', which='both', linestyle='--', alpha=0.4)
        axes[-1].set_xlabel('iteration')
        axes[0].legend(ncol=min(len(methods), 4), fontsize='small')
        save(fig, name)

    main = [m for m in POSE_DEPENDENT if m in data]
    if main:
        error_bars(main, _ticks(n_its, 4), 'error_vs_iteration.png')
        fig, axes = plt.subplots(2, 1, figsize=(8, 6.5))
        for m in main:
            mov, _ = _mean_std(data[m].columns['movement_deg'])
            for ax, (col, label) in zip(axes, _ERRORS):
                mean, _ = _mean_std(data[m].columns[col])
                ax.plot(mov, mean, label=m, color=_color(m), marker='.', markersize=4)
        for ax, (_, label) in zip(axes, _ERRORS):
            ax.set(xlabel='accumulated joint movement [deg]', ylabel=label)
            _log_y(ax)
            ax.grid(True, which='both', linestyle='--', alpha=0.4)
        axes[0].legend(fontsize='small')
        save(fig, 'error_vs_movement.png')

    pairs = [b for b in ('AL', 'UCSAL', 'CCSAL') if b in data and f'{b}-CN' in data]
    if pairs:
        error_bars([f'{b}-CN' for b in pairs] + pairs, _ticks(n_its, 2), 'cn_vs_pose_dependent.png')

    names = list(data)
    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(names)), 3.8))
    finals = [data[m].final('discarded') for m in names]
    bars = ax.bar(names, [np.nanmean(v) for v in finals], yerr=[np.nanstd(v) for v in finals], capsize=4,
                  color=[_color(m) for m in names])
    for bar, m in zip(bars, names):
        if m.endswith('-CN'):
            bar.set_hatch('//')
            bar.set_edgecolor('white')
    for i, v in enumerate(finals):
        ax.scatter(np.full(v.size, i) + np.linspace(-0.15, 0.15, v.size), v, s=6, color='black', zorder=3)
    ax.set(ylabel=f'discarded samples in {n_its} iterations', title='failed measurement attempts (mean, std, runs)')
    ax.grid(True, axis='y', linestyle='--', alpha=0.4)
    save(fig, 'discarded.png')
    return written


def render(root: Path, metrics: Path | None = None) -> list[Path]:
    """Figures into ``<root>/figures`` and ``<root>/summary.md`` from the experiment's CSVs.

    Raises
    ------
    FileNotFoundError
        If there is neither ``metrics.csv`` nor any per-run CSV.
    """
    root = Path(root)
    source: Path | list[Path] = metrics or root / 'metrics.csv'
    if not Path(source).exists():
        source = sorted(root.glob('runs/*/rep*.csv'))
        if not source:
            raise FileNotFoundError(f'no {root / "metrics.csv"} and no per-run CSVs under {root / "runs"}')
    data = load_metrics(source)
    config = root / 'config.json'
    system = json.loads(config.read_text()).get('system') if config.exists() else None
    summary = root / 'summary.md'
    summary.write_text(summary_markdown(data, system))
    return plot_all(data, root / 'figures') + [summary]


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='experiment_figures', description=__doc__.split('\n\n')[0])
    p.add_argument('root', nargs='?', type=Path, default=Path('results/experiment-ours'),
                   help='experiment directory [results/experiment-ours]')
    p.add_argument('--metrics', type=Path, default=None, help='CSV to read [<root>/metrics.csv]')
    a = p.parse_args(argv)
    try:
        paths = render(a.root, a.metrics)
    except (FileNotFoundError, ValueError) as exc:
        print(f'experiment_figures: {exc}', file=sys.stderr)
        return 2
    print((a.root / 'summary.md').read_text())
    print('\n'.join(str(x) for x in paths), file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
