"""The ablation runner: rows from the paper's system to ours, shared runs, the table."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from calibration_bringup import ablation
from calibration_bringup import experiment as ex
from calibration_bringup import experiment_figures as figs
from calibration_bringup.systems import ABLATION, PAPER, ablation_overrides


def test_rows_walk_from_the_papers_directory_to_ours(tmp_path: Path) -> None:
    rows = ablation.rows(3, 5, ('R', 'AL'), 2, tmp_path / 'abl', paper_output=tmp_path / 'paper',
                         ours_output=tmp_path / 'ours')
    assert len(rows) == len(ABLATION) + 1
    first, *middle, last = rows
    assert (first.config.system, first.config.output, dict(first.config.overrides)) == ('paper', tmp_path / 'paper', {})
    assert (last.config.system, last.config.output, dict(last.config.overrides)) == ('ours', tmp_path / 'ours', {})
    for row in middle:
        assert row.config.overrides == ablation_overrides(row.index)
        assert row.config.output == tmp_path / 'abl' / f'{row.index:02d}-{ABLATION[row.index - 1].name}'
    # Rows 0 and last are the very runs of make experiment-paper / make experiment (same settings
    # hash), and none of the rows replaces those experiments' combined files.
    assert ex.settings_hash(ex.run_settings(first.config, 'AL')) == \
        ex.settings_hash(ex.run_settings(ex.ExperimentConfig(system='ours', overrides=PAPER, iterations=5), 'AL'))
    assert not any(r.config.combine or r.config.figures for r in rows)


def _runs(name: str, position: list[float]) -> figs.MethodRuns:
    n = len(position)
    cols = {c: np.zeros((n, 2)) for c in (*figs.NUMERIC, 'rejected')}
    cols['position_mm'][:, 1] = position
    cols['orientation_deg'][:, 1] = 1.0
    cols['movement_deg'][:, 1] = 100.0
    return figs.MethodRuns(name, np.arange(n), cols)


def test_the_table_pairs_each_row_with_the_one_above(tmp_path: Path) -> None:
    rows = ablation.rows(3, 5, ('R', 'AL'), 2, tmp_path)[:2]
    results = [(rows[0], {'AL': _runs('AL', [10.0, 20.0, 30.0]), 'R': _runs('R', [5.0, 5.0, 5.0])}),
               (rows[1], {'AL': _runs('AL', [9.0, 18.0, 27.0]), 'R': _runs('R', [5.0, 5.0, 5.0])})]
    text = ablation.table_markdown(results, 'python -m calibration_bringup.ablation')
    lines = [line for line in text.splitlines() if line.startswith('| 1 |')]
    assert lines[0].startswith(f'| 1 | {ABLATION[0].change} | R | 5.00 (5.00) |') and lines[0].endswith('| same final errors |')
    assert '-2.00 mm, 3/3, p = ' in lines[1]                           # AL: paired against row 0
    assert '| 0 | the paper\'s system | AL | 20.00 (20.00) |' in text
    assert ablation.plot(results, tmp_path / 'a.png').stat().st_size > 1000


def test_a_dry_run_of_every_row(tmp_path: Path) -> None:
    """One repetition of two iterations of R per row, on the real graph; then the same command resumes."""
    argv = ['--repetitions', '1', '--iterations', '2', '--methods', 'R', '--output', str(tmp_path / 'abl'),
            '--paper-output', str(tmp_path / 'paper'), '--ours-output', str(tmp_path / 'ours')]
    log = io.StringIO()
    assert ablation.main(argv, stream=log) == 0, log.getvalue()
    text = (tmp_path / 'abl' / 'ablation.md').read_text()
    assert all(f'| {k} | ' in text for k in range(len(ABLATION) + 1))
    assert not (tmp_path / 'paper' / 'metrics.csv').exists()        # shared directories keep their own files
    assert (tmp_path / 'paper' / 'runs' / 'R' / 'rep00.csv').exists()
    again = io.StringIO()
    assert ablation.main(argv, stream=again) == 0
    assert again.getvalue().count('1 already finished, 0 to run') == len(ABLATION) + 1
    # --table-only runs nothing (no experiment output) and writes the same table, command without the flag.
    (tmp_path / 'abl' / 'ablation.md').unlink()
    table_only = io.StringIO()
    assert ablation.main([*argv, '--table-only'], stream=table_only) == 0
    assert 'experiment:' not in table_only.getvalue() and (tmp_path / 'abl' / 'ablation.md').read_text() == text
    assert ablation.main([*argv[:6], '--output', str(tmp_path / 'empty'), '--paper-output', str(tmp_path / 'e1'),
                          '--ours-output', str(tmp_path / 'e2'), '--table-only'], stream=io.StringIO()) == 1
