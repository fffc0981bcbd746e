"""Figures and summary table from synthetic experiment CSVs with known statistics."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from calibration_bringup import experiment as ex
from calibration_bringup import experiment_figures as figs

ITERATIONS = 5
REPS = 3
#: Final position error of repetition r: base + r (so mean base + 1, population std sqrt(2/3)).
BASE_ERROR = {'R': 20.0, 'AL': 4.0, 'UCSAL': 8.0, 'CCSAL': 6.0, 'AL-CN': 5.0, 'UCSAL-CN': 9.0, 'CCSAL-CN': 7.0}
#: Movement per iteration [deg].
STEP = {'R': 300.0, 'AL': 200.0, 'UCSAL': 80.0, 'CCSAL': 100.0, 'AL-CN': 100.0, 'UCSAL-CN': 50.0,
        'CCSAL-CN': 25.0}


def _rows(method: str, rep: int) -> list[dict]:
    rows = []
    for it in range(ITERATIONS + 1):
        final = BASE_ERROR[method] + rep
        rows.append({'method': method, 'repetition': rep, 'seed': rep, 'iteration': it,
                     'outcome': 'initial' if it == 0 else ('rejected' if (it, rep) == (2, 2) else 'accepted'),
                     'detected': it > 0,
                     'position_mm': 100.0 if it == 0 else final + (ITERATIONS - it),
                     'orientation_deg': 30.0 if it == 0 else final / 10,
                     'movement_deg': STEP[method] * it, 'discarded': min(it, rep),
                     'selection_s': 0.0 if it == 0 else 0.1, 'move_sim_s': 1.0 * (it > 0),
                     'sim_s': 0.05 * (it > 0), 'render_s': 0.04 * (it > 0), 'detect_s': 0.01 * (it > 0),
                     'estimator_s': 0.002 * (it > 0), 'selector_s': 0.12 * (it > 0), 'recorder_s': 0.0,
                     'cpu_s': 0.25 * (it > 0), 'wall_s': 0.3 * (it > 0)})
    return rows


@pytest.fixture
def experiment_dir(tmp_path: Path) -> Path:
    runs = ex.plan_runs(ex.ExperimentConfig(repetitions=REPS, iterations=ITERATIONS))
    for spec in runs:
        ex.write_rows(spec.path(tmp_path, '.csv'), _rows(spec.method, spec.repetition))
    ex.combine_runs(tmp_path, runs, tmp_path / 'metrics.csv')
    return tmp_path


def _table_row(summary: str, method: str) -> list[str]:
    line = next(line for line in summary.splitlines() if line.startswith(f'| {method} | {REPS} |'))
    return [c.strip() for c in line.strip('|').split('|')]


def test_summary_reports_final_statistics(experiment_dir: Path) -> None:
    outputs = figs.render(experiment_dir)
    summary = (experiment_dir / 'summary.md').read_text()
    std = np.std([0.0, 1.0, 2.0])
    for method, base in BASE_ERROR.items():
        cells = _table_row(summary, method)
        assert cells[2] == f'{base + 1:.2f} +- {std:.2f}', cells          # final position
        assert cells[3] == f'{(base + 1) / 10:.2f} +- {std / 10:.2f}'     # final orientation
        assert cells[4] == '100.0 +- 0.0'                                 # initial position
        assert cells[5] == f'{STEP[method] * ITERATIONS:.0f} +- 0'        # total movement
        assert cells[7] == f'{1.0:.1f} +- {std:.1f}'                      # discarded: min(5, rep)
        assert cells[8] == f'{1 / 3:.1f} +- {np.std([0, 0, 1]):.1f}'      # rejected: once in rep 2
    # Movement relative to AL with the same noise model.
    assert _table_row(summary, 'UCSAL')[6] == '0.40' and _table_row(summary, 'CCSAL')[6] == '0.50'
    assert _table_row(summary, 'UCSAL-CN')[6] == '0.50' and _table_row(summary, 'CCSAL-CN')[6] == '0.25'
    assert _table_row(summary, 'AL')[6] == '-'
    assert 'AL after 5 iterations: 5.00 mm (target <= 5 mm: met), 0.50 deg' in summary
    # Paired over the three shared repetitions, one row per compared pair.
    for pair in ('AL vs R', 'AL vs AL-CN', 'UCSAL vs UCSAL-CN', 'CCSAL vs CCSAL-CN'):
        assert re.search(rf'^\| {pair} \| 3 \| [-+]\d', summary, re.M), pair
    timing = next(line for line in summary.splitlines() if line.startswith('| AL | 0.100'))
    assert re.search(r'\| 0\.250 \| 0\.300 \| 0\.118 \|$', timing), timing   # CPU, wall, other = 0.3 - 0.182

    names = {p.name for p in outputs}
    assert names == {'error_vs_iteration.png', 'error_vs_movement.png', 'discarded.png',
                     'cn_vs_pose_dependent.png', 'summary.md'}
    for p in outputs:
        if p.suffix == '.png':
            assert p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and p.stat().st_size > 5000


def test_a_run_that_used_no_observation_is_named_in_the_summary(tmp_path: Path) -> None:
    runs = ex.plan_runs(ex.ExperimentConfig(repetitions=REPS, iterations=ITERATIONS, methods=('R', 'AL')))
    for spec in runs:
        rows = _rows(spec.method, spec.repetition)
        if (spec.method, spec.repetition) == ('AL', 1):
            rows = [{**r, 'outcome': 'failed'} if r['iteration'] else r for r in rows]
        if (spec.method, spec.repetition) == ('R', 2):                # one outlier is an observation used
            rows = [{**r, 'outcome': 'outlier' if r['iteration'] == 3 else 'failed'} if r['iteration'] else r
                    for r in rows]
        ex.write_rows(spec.path(tmp_path, '.csv'), rows)
    ex.combine_runs(tmp_path, runs, tmp_path / 'metrics.csv')
    data = figs.load_metrics(tmp_path / 'metrics.csv')
    assert data['AL'].final('used').tolist() == [5, 0, 4]   # rep 2: one rejected by the gate
    assert data['R'].final('used').tolist() == [5, 5, 1]
    assert "No observation reached the estimate in 1 run(s), whose final error is the initial guess's: " \
           'AL rep 1.' in figs.summary_markdown(data)
    figs.render(tmp_path)
    assert 'the initial guess\'s: AL rep 1.' in (tmp_path / 'summary.md').read_text()
    assert 'No observation' not in figs.summary_markdown({'R': data['R']})     # an outlier was used


def test_replot_from_run_files_when_the_combined_csv_is_missing(experiment_dir: Path) -> None:
    (experiment_dir / 'metrics.csv').unlink()
    assert figs.main([str(experiment_dir)]) == 0
    assert '| CCSAL-CN | 3 |' in (experiment_dir / 'summary.md').read_text()


def test_subset_of_methods_draws_what_it_can(tmp_path: Path) -> None:
    ex.write_rows(tmp_path / 'metrics.csv', _rows('AL', 0) + _rows('AL', 1))
    outputs = figs.render(tmp_path)
    assert {p.name for p in outputs} == {'error_vs_iteration.png', 'error_vs_movement.png',
                                         'discarded.png', 'summary.md'}


def test_shorter_runs_are_padded_not_misaligned(tmp_path: Path) -> None:
    ex.write_rows(tmp_path / 'metrics.csv', _rows('AL', 0) + _rows('AL', 1)[:3])
    data = figs.load_metrics(tmp_path / 'metrics.csv')
    assert data['AL'].columns['position_mm'].shape == (2, ITERATIONS + 1)
    assert np.isnan(data['AL'].columns['position_mm'][1, 3:]).all()
    assert data['AL'].final('position_mm').tolist() == [4.0, 5.0 + ITERATIONS - 2]


def test_time_columns_are_optional(tmp_path: Path) -> None:
    rows = _rows('AL', 0)
    keep = ['method', 'repetition', 'iteration', *figs.REQUIRED]
    (tmp_path / 'metrics.csv').write_text(
        ','.join(keep) + '\n' + ''.join(','.join(str(r[k]) for k in keep) + '\n' for r in rows))
    figs.render(tmp_path)
    timing = next(line for line in (tmp_path / 'summary.md').read_text().splitlines()
                  if line.startswith('| AL | nan'))
    assert timing.count('nan') == len(figs.TIMES) + 1      # and 'other'


def test_bad_inputs_are_named(tmp_path: Path) -> None:
    bad = tmp_path / 'metrics.csv'
    bad.write_text('method,repetition,iteration\nAL,0,0\n')
    with pytest.raises(ValueError, match='position_mm'):
        figs.load_metrics(bad)
    with pytest.raises(FileNotFoundError, match='metrics.csv'):
        figs.render(tmp_path / 'empty')
    assert figs.main([str(tmp_path / 'empty')]) == 2


def _runs(method: str, reps: list[int], final: list[float]) -> figs.MethodRuns:
    pos = np.array([[10.0, f] for f in final])
    return figs.MethodRuns(method, np.array(reps), {'position_mm': pos, 'orientation_deg': pos / 10})


def test_paired_difference_pairs_by_repetition() -> None:
    a = _runs('AL', [0, 1, 2, 3, 4, 5], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    # Same repetitions in another order and one extra: pairs are matched by repetition, not position.
    b = _runs('AL-CN', [5, 4, 3, 2, 1, 0, 9], [6.5, 5.5, 4.5, 3.5, 2.5, 1.5, 0.0])
    n, d, lower, p = figs.paired_difference(a, b, 'position_mm')
    assert (n, lower) == (6, 6) and d == pytest.approx(-0.5)
    assert p == pytest.approx(0.03125)          # exact two-sided signed-rank p for 6 of 6 one way
    n, d, lower, p = figs.paired_difference(a, a, 'position_mm')
    assert (n, d, lower) == (6, 0.0, 0) and np.isnan(p)


def _method(name: str, position: np.ndarray, orientation: np.ndarray, movement: float = 1000.0,
            discarded: np.ndarray | None = None) -> figs.MethodRuns:
    """Runs whose final values are the given arrays (one per repetition)."""
    n = position.size
    cols = {c: np.zeros((n, 2)) for c in (*figs.NUMERIC, 'rejected')}
    cols['position_mm'][:, 1], cols['orientation_deg'][:, 1] = position, orientation
    cols['movement_deg'][:, 1] = movement
    cols['discarded'][:, 1] = discarded if discarded is not None else np.full(n, 10.0)
    return figs.MethodRuns(name, np.arange(n), cols)


def test_the_ratio_interval_is_paired_and_says_when_there_is_none() -> None:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter('error')                      # no division warning on any input below
        assert figs.paired_ratio_interval([1.0, 2.0, 3.0], [2.0, 4.0, 6.0]) == (2.0, 2.0)   # one ratio
        assert np.isnan(figs.paired_ratio_interval([1.0], [2.0])[0])                        # one pair
        assert np.isnan(figs.paired_ratio_interval([0.0, 0.0, 0.0], [1.0, 2.0, 0.0])[0])    # mean(a) = 0
        assert np.isnan(figs.paired_ratio_interval([1.0, np.nan, 3.0], [2.0, 2.0, np.nan])[0])  # one finite pair
        low, high = figs.paired_ratio_interval([1.0, 2.0, 3.0, 0.0], [1.0, 2.0, 3.0, 1.0])
    assert 1.0 <= low < high
    # Seeds 10x apart, pairs 1.5x apart within a few percent: the interval is the pairs', not the seeds'.
    rng = np.random.default_rng(1)
    a = rng.uniform(0.1, 1.0, 30)
    low, high = figs.paired_ratio_interval(a, 1.5 * a * rng.lognormal(0.0, 0.02, 30))
    assert 1.45 < low < 1.5 < high < 1.55


def test_the_papers_claims_are_judged_from_the_runs() -> None:
    rng = np.random.default_rng(3)
    r_pos, r_rot = rng.uniform(10, 20, 20), rng.uniform(3, 5, 20)
    few = rng.uniform(2, 4, 20)
    data = {'R': _method('R', r_pos, r_rot, 5000.0, few + 10),
            'AL': _method('AL', 1.2 * r_pos, r_rot - 1.0, 4000.0, few),
            'UCSAL': _method('UCSAL', 1.2 * r_pos, r_rot - 0.9, 2000.0, few),     # 0.5x movement, 1.0x error
            'CCSAL': _method('CCSAL', 2.0 * r_pos, r_rot - 0.9, 2000.0, few),     # 1.67x error: fails
            'AL-CN': _method('AL-CN', 1.5 * r_pos, r_rot, 4000.0, few)}
    one, two, three, four = figs.paper_claims(data)
    assert one.verdict == 'yes' and 'position AL / R = 1.20' in one.evidence
    assert two.verdict == 'partly' and 'CCSAL: movement 0.50x, position 1.67x' in two.evidence
    assert three.verdict == 'yes' and 'AL - AL-CN mm: ' in three.evidence and 'UCSAL-CN' not in three.evidence
    assert four.verdict == 'yes' and 'p = ' in four.evidence
    # AL far worse than R in position, no better in orientation: the first claim fails outright.
    worse = {**data, 'AL': _method('AL', 3.0 * r_pos, r_rot + 0.5, 4000.0, few + 20)}
    first, *_, last = figs.paper_claims(worse)
    assert first.verdict == 'no' and last.verdict == 'partly'
    # Without the methods a claim needs, it is not judged.
    assert [c.verdict for c in figs.paper_claims({'R': data['R']})] == ['-'] * 4
    text = '\n'.join(figs.claims_markdown(data))
    assert "## The paper's claims" in text and '| AL within 1.25x of R' in text
