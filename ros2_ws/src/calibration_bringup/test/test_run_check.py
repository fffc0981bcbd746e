"""run_check: a finished run with many timeouts or an offline re-run that disagrees is unhealthy."""
from __future__ import annotations

import csv
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from calibration_bringup.run_check import CheckSettings, check_rows, check_run, dh_difference, noise_law_cautions
from dh_estimator.evaluate import Evaluation, IterationRow, summary_text


def _rows(outcomes: list[str], offline_mm: float = 4.7, online_mm: float = 4.7) -> list[IterationRow]:
    """The report's rows: the initial guess, then one per iteration."""
    return [IterationRow(iteration=i, outcome=outcome, detected=True, movement_deg=10.0 * i, discarded=0,
                         position_mm=offline_mm if i == len(outcomes) else 50.0, orientation_deg=2.0,
                         online_position_mm=online_mm if i == len(outcomes) else 50.0, online_orientation_deg=2.0,
                         offline_updates=i, selection_s=0.1, sim_time=float(i))
            for i, outcome in enumerate(['initial', *outcomes])]


def _csv(rows: list[IterationRow]) -> list[dict[str, str]]:
    return [{f.name: str(getattr(r, f.name)) for f in fields(IterationRow)} for r in rows]


def _report(rows: list[IterationRow], offset: float) -> str:
    """The summary calibration_report prints and writes, for final tables ``offset`` apart."""
    dh = np.zeros((7, 4))
    ev = Evaluation(rows=rows, final_dh=dh + offset, online_final_dh=dh, true_dh=dh,
                    counters={'updates': 5, 'rejected': 0}, strategy='al')
    return summary_text(ev)


def _write_run(directory: Path, rows: list[IterationRow], offset: float) -> None:
    """The run directory calibration_report leaves: ``metrics.csv`` and ``report.md``."""
    with (directory / 'metrics.csv').open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=[x.name for x in fields(IterationRow)])
        w.writeheader()
        w.writerows(_csv(rows))
    (directory / 'report.md').write_text(_report(rows, offset))


def test_a_healthy_run_has_no_problem() -> None:
    rows = _rows(['accepted'] * 9 + ['timeout'])                           # 10 % timeouts: within 20 %
    assert check_rows(_csv(rows), dh_difference(_report(rows, 0.0))) == []


def test_a_stalled_estimator_is_reported() -> None:
    """One future-stamped joint state used to stall the estimator: most iterations 'timeout'."""
    rows = _csv(_rows(['accepted'] * 2 + ['timeout'] * 3))
    (problem,) = check_rows(rows, 0.0)
    assert '3 of 5 iterations ended "timeout"' in problem
    assert check_rows(rows, 0.0, CheckSettings(max_timeouts=0.6)) == []


def test_a_run_that_never_used_an_observation_is_reported() -> None:
    """Issue 31's seed 30 with per-eye occlusion models: 50 attempts, none seen, exit 0 before."""
    rows = _csv(_rows(['failed'] * 48 + ['unreachable', 'rejected']))
    (problem,) = check_rows(rows, 0.0)
    assert 'no observation reached the estimate in 50 iterations' in problem
    assert '48 failed, 1 unreachable, 1 rejected' in problem and 'initial guess' in problem
    # One observation used, even as an outlier under the robust loss, is an estimate that moved.
    for used in ('accepted', 'outlier'):
        assert check_rows(_csv(_rows(['failed'] * 9 + [used])), 0.0) == []


def test_a_run_that_never_saw_the_hand_exits_1(tmp_path: Path) -> None:
    _write_run(tmp_path, _rows(['failed'] * 5), 0.0)
    out = subprocess.run([sys.executable, '-m', 'calibration_bringup.run_check', str(tmp_path)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert 'UNHEALTHY RUN: no observation reached the estimate in 5 iterations (5 failed)' in out.stderr


def test_an_offline_rerun_that_disagrees_is_reported() -> None:
    """The issue's case: offline re-run 28.3 mm, online 4.7 mm, and the run exited 0."""
    rows = _rows(['accepted'] * 5, offline_mm=28.3, online_mm=4.7)
    diff = dh_difference(_report(rows, 0.02))                                # what the report states
    assert diff == pytest.approx(0.02, rel=1e-2)
    (problem,) = check_rows(_csv(rows), diff)
    assert '2.00e-02' in problem and '28.30 mm' in problem and '4.70 mm' in problem
    assert check_rows(_csv(rows), 1e-9) == []                                # a healthy run's agreement
    assert check_rows(_csv(rows), 1e-3, CheckSettings(max_dh_difference=1e-2)) == []
    assert check_rows(_csv(rows), float('nan'))                              # NaN is not agreement
    assert 'does not say' in check_rows(_csv(rows), None)[0]
    assert check_rows(_csv(rows), 0.02, CheckSettings(check_agreement=False)) == []


def test_bad_thresholds_and_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match='1.5'):
        CheckSettings(max_timeouts=1.5)
    with pytest.raises(ValueError, match='no iteration row'):
        check_rows(_csv(_rows([]))[:1], 0.0)
    with pytest.raises(FileNotFoundError):
        check_run(tmp_path)


def test_the_command_exits_1_and_says_why(tmp_path: Path) -> None:
    _write_run(tmp_path, _rows(['accepted'] * 5, offline_mm=28.3), 0.02)
    cmd = [sys.executable, '-m', 'calibration_bringup.run_check', str(tmp_path)]
    bad = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and 'UNHEALTHY RUN' in bad.stderr and '2.00e-02' in bad.stderr, bad.stderr
    ok = subprocess.run([*cmd, '--max-dh-difference', '0.05'], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr


def test_the_summary_record_carries_the_innovation_check_seed_study_adds_up() -> None:
    from body_schema.noise import innovation_check
    from calibration_bringup.report import summary_record

    rows = _rows(['accepted'] * 4)
    dh = np.zeros((7, 4))
    ev = Evaluation(rows=rows, final_dh=dh, online_final_dh=dh, true_dh=dh, counters={'updates': 4, 'rejected': 0},
                    strategy='al', innovations=innovation_check([100.0, 3.0, 40.0, 5.0], skip=1))
    assert summary_record(ev, 't', None)['innovations'] == {
        'count': 3, 'median': 5.0, 'beyond': 1, 'bound': pytest.approx(27.856, abs=1e-3), 'probability': 0.9999}
    assert 'beyond the 99.99% bound in 1 of 3' in summary_text(ev)
    ev.innovations = None
    assert summary_record(ev, 't', None)['innovations'] is None


def _innovations(nis: list[float] | np.ndarray) -> dict:
    """A summary.json record's ``innovations`` entry for these NIS (no warm-up)."""
    from body_schema.noise import innovation_check

    c = innovation_check(nis)
    return {'innovations': {'count': c.count, 'median': c.median, 'beyond': c.beyond, 'bound': c.bound,
                            'probability': c.probability}}


def test_the_noise_law_is_cautioned_against_when_its_innovations_say_so() -> None:
    """Innovations of a right law (chi-square 6) seldom raise a caution; a detector with heavier
    tails than the law (the Panda's: 3 of 39 beyond the 99.99 % bound) or a law that understates
    the typical error (NIS twice too large) does, each with its own sentence; a cautious law alone
    does not."""
    from scipy.stats import chi2

    rng = np.random.default_rng(7)
    right = [noise_law_cautions(_innovations(chi2.rvs(6, size=40, random_state=rng))) for _ in range(2000)]
    assert sum(bool(c) for c in right) <= 10                     # about 2 alpha = 0.2 %: 4 of 2000
    nis = chi2.rvs(6, size=39, random_state=rng) * 0.3            # a bulk the law overstates...
    nis[[5, 17, 30]] = [60.0, 95.0, 40.0]                         # ...and tails it understates
    (tails,) = noise_law_cautions(_innovations(nis))
    assert '3 of 39 innovations beyond the 99.99% bound' in tails and 'too sure' in tails
    (bulk,) = noise_law_cautions(_innovations(2.0 * chi2.rvs(6, size=40, random_state=rng)))
    assert 'larger than the noise law' in bulk and 'understates the typical error' in bulk
    assert noise_law_cautions(_innovations(0.3 * chi2.rvs(6, size=40, random_state=rng))) == []   # cautious
    assert noise_law_cautions({'innovations': None}) == [] and noise_law_cautions({}) == []
    with pytest.raises(ValueError, match="'beyond'"):
        noise_law_cautions({'innovations': {'count': 3, 'median': 5.0, 'bound': 27.9, 'probability': 0.9999}})
    with pytest.raises(ValueError, match='noise_law_alpha'):
        CheckSettings(noise_law_alpha=0.0)


def test_a_caution_on_the_noise_law_is_printed_but_does_not_fail_the_run(tmp_path: Path) -> None:
    import json

    rows = _rows(['accepted'] * 5)
    with (tmp_path / 'metrics.csv').open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=[f.name for f in fields(IterationRow)])
        w.writeheader()
        w.writerows(_csv(rows))
    (tmp_path / 'report.md').write_text(_report(rows, 0.0))
    (tmp_path / 'summary.json').write_text(json.dumps(_innovations([3.0] * 30 + [80.0] * 3)))
    cmd = [sys.executable, '-m', 'calibration_bringup.run_check', str(tmp_path)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert 'CAUTION (noise law): 3 of 33 innovations beyond' in out.stderr and 'UNHEALTHY' not in out.stderr
    (tmp_path / 'summary.json').write_text('{not json')
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and 'summary.json' in out.stderr, out.stderr   # named, not fatal
