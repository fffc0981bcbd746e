"""Experiment runner end to end: two methods x one repetition x three iterations on the real graph,
as two tasks of a local Ray runtime; then a restart skips the finished runs and redoes a missing one."""
from __future__ import annotations

import io
import json
import os
import socket
from dataclasses import asdict, replace
from pathlib import Path

import pytest

from calibration_bringup import experiment as ex

ITERATIONS = 3
# Domains 200..213: clear of the in-process fixture (1..100), the transport tests and benchmark
# (101..199) and the experiment's own default (215..232).
DOMAIN_BASE = 200 + 2 * (os.getpid() % 7)


@pytest.mark.slow
def test_two_methods_run_resume_and_report(tmp_path: Path) -> None:
    config = ex.ExperimentConfig(repetitions=1, iterations=ITERATIONS, methods=('AL-CN', 'R'), jobs=2,
                                 output=tmp_path, seed_base=3, domain_base=DOMAIN_BASE)
    log = io.StringIO()
    outcome = ex.run_experiment(config, stream=log)
    assert outcome.failures == [], log.getvalue()
    assert {r.spec.method for r in outcome.results} == set(config.methods)
    assert {r.domain_id for r in outcome.results} <= set(ex.domain_ids(config))
    # The numeric environment the runs computed in, as the Ray worker saw it (threads as Ray sets them).
    (env,) = ex.read_environments(tmp_path)
    assert env['numpy'] and 'openblas' in env['blas'] and env == outcome.environments[socket.gethostname()]

    runs = {m: ex.read_rows(tmp_path / 'runs' / m / 'rep00.csv') for m in config.methods}
    for method, rows in runs.items():
        assert [int(r['iteration']) for r in rows] == list(range(ITERATIONS + 1)), method
        assert {r['seed'] for r in rows} == {'3'} and {r['method'] for r in rows} == {method}
        seeds = ex.derive_seeds(3)
        assert {(r['robot_seed'], r['guess_seed'], r['selector_seed']) for r in rows} == \
            {(str(seeds.robot), str(seeds.guess), str(seeds.selector))}
        assert {r['settings_hash'] for r in rows} == {ex.settings_hash(ex.run_settings(config, method))}
        # The driver wrote the log the task returned.
        assert 'ROS_DOMAIN_ID' in (tmp_path / 'runs' / method / 'rep00.log').read_text()
        assert rows[0]['outcome'] == 'initial'
        assert {r['outcome'] for r in rows[1:]} <= {'accepted', 'outlier', 'rejected', 'failed'}, rows
        movement = [float(r['movement_deg']) for r in rows]
        assert movement == sorted(movement) and movement[-1] > 0
        assert all(float(r['wall_s']) > 0 for r in rows[1:])
        discarded = [int(r['discarded']) for r in rows]
        assert discarded[-1] == sum(r['detected'] == 'False' for r in rows[1:])
    # Fair comparison: the same true robot and initial guess, hence the same initial error.
    assert runs['AL-CN'][0]['position_mm'] == runs['R'][0]['position_mm']
    assert float(runs['R'][0]['position_mm']) > 10.0
    # The estimate moves at the accepted updates (the table is scored when the iteration's record
    # arrives, after its update); failed and rejected attempts leave it alone. An observation
    # flagged as an outlier is kept but pulls with a bounded weight: it may or may not move it.
    for method, rows in runs.items():
        moved = [rows[i]['position_mm'] != rows[i - 1]['position_mm'] for i in range(1, len(rows))]
        for m, r in zip(moved, rows[1:]):
            if r['outcome'] in ('accepted', 'failed', 'rejected'):
                assert m == (r['outcome'] == 'accepted'), (method, rows)
    # At least one observation kept (with the iCub's own noise law the first ones can be flagged as
    # outliers from a far initial guess: docs/selector.md, "One detection from both images").
    assert sum(r['outcome'] in ('accepted', 'outlier') for rows in runs.values() for r in rows) >= 1, runs

    combined = ex.read_rows(tmp_path / 'metrics.csv')
    assert len(combined) == 2 * (ITERATIONS + 1)
    assert (tmp_path / 'summary.md').read_text().count('| AL-CN |') == 3   # accuracy, medians and time tables
    assert (tmp_path / 'figures' / 'discarded.png').stat().st_size > 1000
    assert 'AL-CN rep 0 (seed 3): done' in log.getvalue()
    assert json.loads((tmp_path / 'config.json').read_text())['seeds'][0] == \
        {'repetition': 0, 'seed': 3, **asdict(ex.derive_seeds(3))}

    if ex.recorder_available():
        from mcap.reader import make_reader

        with (tmp_path / 'runs' / 'R' / 'rep00.mcap').open('rb') as f:
            summary = make_reader(f).get_summary()
        counts = {c.topic: summary.statistics.channel_message_counts.get(i, 0)
                  for i, c in summary.channels.items()}
        assert counts['/calibration/progress'] == ITERATIONS
        assert counts['/joint_states'] > 0
        assert not any(t.endswith('image_raw') for t in counts)

    # Restart: nothing to do; the finished CSVs are left alone.
    stamps = {m: (tmp_path / 'runs' / m / 'rep00.csv').stat().st_mtime_ns for m in config.methods}
    log = io.StringIO()
    assert ex.run_experiment(config, stream=log).results == []
    assert '2 already finished, 0 to run' in log.getvalue()
    assert stamps == {m: (tmp_path / 'runs' / m / 'rep00.csv').stat().st_mtime_ns for m in config.methods}

    # A run whose CSV is missing (killed before its end) is redone, and only that one.
    (tmp_path / 'runs' / 'R' / 'rep00.csv').unlink()
    log = io.StringIO()
    assert [r.spec.method for r in ex.run_experiment(replace(config, jobs=1), stream=log).results] == ['R']
    assert '1 already finished, 1 to run' in log.getvalue()
    assert (tmp_path / 'runs' / 'AL-CN' / 'rep00.csv').stat().st_mtime_ns == stamps['AL-CN']
    rerun = ex.read_rows(tmp_path / 'runs' / 'R' / 'rep00.csv')
    assert [r['position_mm'] for r in rerun][:1] == [runs['R'][0]['position_mm']]


@pytest.mark.slow
def test_a_task_with_a_shared_output_writes_its_log_there_and_returns_no_bytes(tmp_path: Path) -> None:
    spec = ex.RunSpec('R', 4, 9, 1)
    result = ex.execute_run(spec, DOMAIN_BASE + 1, ex.GraphSettings(), 'ours', record=False,
                            shared_root=str(tmp_path))
    assert result.error is None and [r['iteration'] for r in result.rows] == [0, 1]
    assert (result.log, result.mcap, result.node_id) == (None, None, '')    # outside Ray: no node
    log = spec.path(tmp_path, '.log').read_text()
    assert f'ROS_DOMAIN_ID {DOMAIN_BASE + 1}' in log and 'icub_sim' in log
    # The CSV (the "finished" mark) is the driver's to write, never the task's.
    assert not spec.path(tmp_path, '.csv').exists()
