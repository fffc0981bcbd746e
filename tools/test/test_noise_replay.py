"""The noise-law replay of a study: a run's settings from its run.env, the paired report."""
from __future__ import annotations

from pathlib import Path

import pytest

from tools.noise_replay import main, report, run_settings


def test_a_runs_settings_come_from_its_run_env(tmp_path: Path) -> None:
    (tmp_path / 'run.env').write_text("robot=panda\nstrategy=al\nnoise=pose_dependent\nestimator=map\n"
                                      "camera_error=0.02\\ 2\nmarker_error=0.005\\ 5\nbody_change=''\n")
    s = run_settings(tmp_path)
    assert s.robot == 'panda' and s.estimator.estimator == 'map'
    assert s.estimator.camera_prior == '0.02 2' and s.estimator.marker_prior == '0.005 5'
    (tmp_path / 'run.env').write_text("robot=ur5e\ncamera_error=''\nmarker_error=''\n")
    s = run_settings(tmp_path)
    assert s.robot == 'ur5e' and s.estimator.camera_prior == '' and s.estimator.marker_prior == ''


def test_the_report_pairs_the_runs() -> None:
    rows = [{'seed': s, 'recorded_mm': 0.8 + 0.01 * s, 'law_mm': 0.4, 'recorded_deg': 0.04, 'law_deg': 0.03 + 0.02 * (s == 3),
             'recorded_limit_mm': 0.5, 'law_limit_mm': 0.25, 'recorded_nees': 30.0, 'law_nees': 60.0,
             'recorded_in_band': 1.0, 'law_in_band': 0.0} for s in range(1, 7)]
    text = report(rows, 'study')
    assert '| 3 | 0.83 / 0.040 | 30.0 (yes) | **0.40 / 0.050** | 60.0 (no) | 0.50 / 0.25 |' in text
    assert 'lower in 6 of 6' in text and 'lower in 5 of 6' in text
    assert 'NEES in its 95% band: recorded 6 of 6, new law 0 of 6' in text
    assert 'paired Wilcoxon signed-rank test, position: p = 0.031' in text


def test_the_command_names_what_is_missing(tmp_path: Path, capsys) -> None:
    law = tmp_path / 'law.yaml'
    law.write_text('noise_model: {floor_pos: 1.0e-6, floor_rot: 1.0e-5, depth_ratio: 3}\n')
    assert main([str(tmp_path), '--noise-law', str(law)]) == 2
    assert f'{tmp_path}: no seed_<S>/calibration.mcap' in capsys.readouterr().err
    law.write_text('noise_model: {depth_ratio: -1}\n')
    assert main([str(tmp_path), '--noise-law', str(law)]) == 2
    assert f'{law}: noise_model.depth_ratio: must be finite and > 0, got -1' in capsys.readouterr().err
