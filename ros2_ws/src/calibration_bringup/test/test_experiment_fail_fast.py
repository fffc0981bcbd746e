"""The driver stops when runs keep failing on one node for one environmental cause: a local Ray
runtime whose tasks are handed an ament index that does not exist (as a node would be whose
workspace lies elsewhere), with the node check skipped (as for a node that joined after it), so
the real runs fail at their recorder's first message definition."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from calibration_bringup import cluster
from calibration_bringup import experiment as ex

pytest.importorskip('ray')

# Domains 200..213 (see test_experiment_run.py), offset from the others.
DOMAIN_BASE = 200 + 2 * ((os.getpid() + 1) % 7)


@pytest.mark.slow
def test_three_runs_failing_for_a_missing_ament_index_stop_the_rest(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    if not ex.recorder_available():
        pytest.skip('the recorder is what reads the ament index')
    monkeypatch.setattr(cluster, 'run_environment', lambda: {'AMENT_PREFIX_PATH': str(tmp_path / 'elsewhere')})
    monkeypatch.setattr(cluster, 'check_nodes', lambda record, options, timeout=0.0: ([], []))
    code = ex.main(['--methods', 'R', '--repetitions', '6', '--iterations', '1', '--jobs', '2', '--no-figures',
                    '--domain-base', str(DOMAIN_BASE), '--output', str(tmp_path / 'out')])
    err = capsys.readouterr().err
    assert code == 1, err
    assert '3 runs failed for the same cause on one node; stopped' in err
    named = [line for line in err.splitlines() if line.startswith('  node ')]
    assert len(named) == 1, err
    assert "DefinitionNotFoundError: package 'rosgraph_msgs' is not in the ament index" in named[0], err
    assert 'a node the driver cannot name' not in named[0]      # the runs said where they ran
    runs = tmp_path / 'out' / 'runs' / 'R'
    assert len(list(runs.glob('rep*.log'))) == 3, err          # the rest never ran or were cancelled
    assert not list(runs.glob('rep*.csv'))
