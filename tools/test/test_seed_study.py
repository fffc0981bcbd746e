"""The seed study: seeds parsed, runs launched once each, the summary counted right."""
from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from tools import seed_study
from tools.seed_study import parse_seeds, summarise


def _record(final_mm: float, nees: float, cam_err: list[float], accepted: int = 48) -> dict:
    return {'title': 't', 'wall_seconds': 300.0, 'iterations': 50,
            'outcomes': {'accepted': accepted, 'no_marker': 50 - accepted},
            'initial': {'position_mm': 200.0, 'orientation_deg': 20.0},
            'final': {'position_mm': final_mm, 'orientation_deg': 0.1},
            'online': {'position_mm': final_mm, 'orientation_deg': 0.1},
            'information_limit': {'position_mm': 0.5, 'orientation_deg': 0.08}, 'movement_deg': 9000.0,
            'identifiable': 28, 'parameters': 36, 'nees_identifiable': nees, 'nees_band': [15.31, 44.46],
            'unidentifiable': [], 'extrinsics': {'camera': {'error': cam_err, 'sigma': [1.0] * 6}},
            'max_online_offline_difference': 0.0}


def test_seeds_are_ranges_and_lists_and_bad_ones_are_named() -> None:
    assert parse_seeds('1-3,9,2') == [1, 2, 3, 9]
    for bad, words in (('3-1', "range '3-1' is empty"), ('a', "'a' is neither"), (',', 'no seed')):
        with pytest.raises(ValueError, match=words):
            parse_seeds(bad)


def test_summary_counts_the_band_and_the_sigmas() -> None:
    records = {1: _record(0.6, 28.0, [0.5, -0.5, 1.5, 0.1, 2.5, 0.0]), 2: _record(1.0, 60.0, [0.1] * 6)}
    text = summarise(records, {1: 0, 2: 1}, 'cmd')
    assert '| 2 | 1 | 48 / 50 |' in text and '60.0 (out) (15.3-44.5)' in text
    assert 'inside the 95% band in 1 of 2 runs' in text
    # The average over the runs against its own (narrower) band: (28 + 60) / 2 = 44 > 39.3.
    assert 'average over the runs 44.0, OUTSIDE its 95% band 18.6-39.3' in text and 'all 2 with 0.90' in text
    assert 'average over the runs 30.0, inside' in summarise({1: _record(0.6, 28.0, [0.0] * 6),
                                                              2: _record(0.6, 32.0, [0.0] * 6)}, {}, 'cmd')
    assert 'mean 0.80, median 0.80, min 0.60, max 1.00' in text
    assert 'camera pose components within one sigma: 10 of 12' in text and 'within two: 11' in text
    assert "exited non-zero (see `seed_<S>.log`; 1 is the launcher's UNHEALTHY RUN): [2]" in text


def test_summary_adds_up_the_innovations_of_the_runs_that_have_them() -> None:
    records = {s: _record(0.5, 30.0, [0.0] * 6) for s in (1, 2, 3)}
    for s, (median, beyond) in ((1, (4.0, 0)), (2, (8.0, 3))):
        records[s]['innovations'] = {'count': 40, 'median': median, 'beyond': beyond, 'bound': 27.86,
                                     'probability': 0.9999}
    text = summarise(records, {}, 'cmd')
    assert ('median NIS per run mean 6.0, median 6.0, min 4.0, max 8.0' in text
            and "beyond the 99.99% bound in 3 of 80 (0.01 expected), in 1 of 2 runs" in text)
    # seed 2's 3 exceedances and its median of 8 fail both of the health check's tests; seed 1 none
    assert 'the health check cautions against the law in 1 of 2' in text
    assert 'innovations' not in summarise({1: _record(0.5, 30.0, [0.0] * 6)}, {}, 'cmd')


def test_each_seed_runs_once_and_an_existing_summary_is_kept(tmp_path: Path, monkeypatch) -> None:
    calls = tmp_path / 'calls'
    fake = tmp_path / 'run_calibration.sh'
    # A stand-in for the launcher: records its arguments, writes the run's summary.json.
    fake.write_text('#!/usr/bin/env python3\nimport json, sys, pathlib\n'
                    'a = sys.argv[1:]\nopen(%r, "a").write(" ".join(a) + "\\n")\n'
                    'out = pathlib.Path(a[a.index("--output") + 1]); out.mkdir(parents=True, exist_ok=True)\n'
                    'seed = int(a[a.index("--seed") + 1])\n'
                    'rec = json.loads(%r); rec["final"]["position_mm"] = seed / 10\n'
                    '(out / "summary.json").write_text(json.dumps(rec))\n'
                    'sys.exit(1 if seed == 3 else 0)\n' % (str(calls), json.dumps(_record(0.0, 30.0, [0.0] * 6))))
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setattr(seed_study, 'LAUNCHER', fake)
    out = tmp_path / 'study'
    rc = seed_study.main(['--robot', 'ur5e', '--seeds', '1-3', '--jobs', '2', '--output', str(out), '--',
                          '--camera-error', '0.02 2'])
    assert rc == 1                                         # seed 3 exited 1
    lines = calls.read_text().splitlines()
    assert len(lines) == 3 and all('--robot ur5e' in ln and '--camera-error 0.02 2' in ln for ln in lines)
    text = (out / 'summary.md').read_text()
    assert "--camera-error '0.02 2'" in text and 'min 0.10, max 0.30' in text
    assert seed_study.main(['--seeds', '1-3', '--output', str(out)]) == 1      # nothing re-run; seed 3 still bad
    assert len(calls.read_text().splitlines()) == 3


def test_a_summary_reads_back_as_its_rounded_records() -> None:
    from tools.seed_study import read_summary

    records = {1: _record(0.6123, 28.0, [0.0] * 6), 7: _record(1.0, 60.0, [0.1] * 6, accepted=41)}
    back = read_summary(summarise(records, {1: 0, 7: 1}, 'cmd'))
    assert sorted(back) == [1, 7]
    assert back[1]['final'] == {'position_mm': 0.61, 'orientation_deg': 0.1}
    assert back[7]['outcomes'] == {'accepted': 41} and back[7]['iterations'] == 50
    assert back[7]['information_limit'] == {'position_mm': 0.5, 'orientation_deg': 0.08}
    with pytest.raises(ValueError, match='no seed row'):
        read_summary('# a report\n| a | b |\n')


def test_the_committed_summaries_read_back_whole() -> None:
    from tools.seed_study import read_summary

    root = Path(__file__).resolve().parents[2] / 'docs' / 'results'
    for name in ('ur5e/summary.md', 'safety/ur5e-summary.md', 'safety/icub-summary.md'):
        back = read_summary((root / name).read_text())
        assert sorted(back) == list(range(1, 21)), name


def test_the_summary_names_the_numeric_environment_or_says_the_runs_had_two() -> None:
    env = {'cpu': 'Xeon', 'numpy_simd': 'X86_V2 + X86_V3', 'blas': 'openblas SkylakeX x2', 'opencv': '5.0.0 (...)',
           'numpy': '2.4.6'}
    one = {s: {**_record(0.6, 28.0, [0.0] * 6), 'environment': env} for s in (1, 2)}
    text = summarise(one, {}, 'cmd')
    assert '- made on one numeric environment (cpu Xeon; numpy_simd X86_V2 + X86_V3; blas openblas SkylakeX x2' in text
    two = {**one, 3: {**_record(0.6, 28.0, [0.0] * 6), 'environment': {**env, 'blas': 'openblas Haswell x2'}},
           4: _record(0.6, 28.0, [0.0] * 6)}
    text = summarise(two, {}, 'cmd')
    assert ('- made on 2 numeric environments (runs of two do not repeat one another step by step: blas: '
            'openblas SkylakeX x2 -> openblas Haswell x2); 1 runs recorded none') in text
    assert 'numeric environment' not in summarise({1: _record(0.6, 28.0, [0.0] * 6)}, {}, 'cmd')
