"""run_check: a finished run with many timeouts or an offline re-run that disagrees is unhealthy."""
from __future__ import annotations

import csv
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest

from calibration_bringup.run_check import CheckSettings, check_rows, check_run
from dh_estimator.evaluate import IterationRow


def _rows(outcomes: list[str], offline_mm: float = 4.7, online_mm: float = 4.7,
          offline_deg: float = 2.0, online_deg: float = 2.0) -> list[dict[str, str]]:
    """metrics.csv rows as the report writes them: the initial guess, then one per iteration."""
    rows = []
    for i, outcome in enumerate(['initial', *outcomes]):
        last = i == len(outcomes)
        row = IterationRow(iteration=i, outcome=outcome, detected=True, movement_deg=10.0 * i, discarded=0,
                           position_mm=offline_mm if last else 50.0, orientation_deg=offline_deg if last else 9.0,
                           online_position_mm=online_mm if last else 50.0,
                           online_orientation_deg=online_deg if last else 9.0, offline_updates=i,
                           selection_s=0.1, sim_time=float(i))
        rows.append({f.name: str(getattr(row, f.name)) for f in fields(IterationRow)})
    return rows


def test_a_healthy_run_has_no_problem() -> None:
    assert check_rows(_rows(['accepted'] * 9 + ['timeout'])) == []        # 10 % timeouts: within 20 %


def test_a_stalled_estimator_is_reported() -> None:
    """One future-stamped joint state used to stall the estimator: most iterations 'timeout'."""
    (problem,) = check_rows(_rows(['accepted'] * 2 + ['timeout'] * 3))
    assert '3 of 5 iterations ended "timeout"' in problem
    assert check_rows(_rows(['accepted'] * 2 + ['timeout'] * 3), CheckSettings(max_timeouts=0.6)) == []


def test_an_offline_rerun_that_disagrees_is_reported() -> None:
    """The issue's case: offline re-run 28.3 mm, online 4.7 mm, and the run exited 0."""
    (problem,) = check_rows(_rows(['accepted'] * 5, offline_mm=28.3, online_mm=4.7))
    assert '28.30 mm' in problem and '4.70 mm' in problem
    (problem,) = check_rows(_rows(['accepted'] * 5, offline_deg=2.2, online_deg=2.0))   # orientation alone
    assert check_rows(_rows(['accepted'] * 5, offline_mm=4.9, online_mm=4.7)) == []     # within 0.5 mm
    assert check_rows(_rows(['accepted'] * 5, offline_mm=4.9, online_mm=4.7), CheckSettings(max_disagreement_mm=0.1))
    assert check_rows(_rows(['accepted'] * 5, offline_mm=28.3), CheckSettings(check_agreement=False)) == []


def test_bad_thresholds_and_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match='1.5'):
        CheckSettings(max_timeouts=1.5)
    with pytest.raises(ValueError, match='no iteration row'):
        check_rows(_rows([])[:1])
    with pytest.raises(FileNotFoundError):
        check_run(tmp_path)


def test_the_command_exits_1_and_says_why(tmp_path: Path) -> None:
    rows = _rows(['accepted'] * 5, offline_mm=28.3)
    with (tmp_path / 'metrics.csv').open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    cmd = [sys.executable, '-m', 'calibration_bringup.run_check', str(tmp_path)]
    bad = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and 'UNHEALTHY RUN' in bad.stderr and '28.30 mm' in bad.stderr, bad.stderr
    ok = subprocess.run([*cmd, '--max-disagreement', '30'], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
