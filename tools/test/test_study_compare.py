"""Seed studies compared seed by seed: the pairing, the ratios, the test, the inputs refused."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tools.seed_study import summarise
from tools.study_compare import Study, compare, load_study, main


def _record(final_mm: float, limit_mm: float = 0.5) -> dict:
    return {'title': 't', 'wall_seconds': 300.0, 'iterations': 50, 'outcomes': {'accepted': 45},
            'initial': {'position_mm': 200.0, 'orientation_deg': 20.0},
            'final': {'position_mm': final_mm, 'orientation_deg': final_mm / 10},
            'information_limit': {'position_mm': limit_mm, 'orientation_deg': limit_mm / 10},
            'nees_identifiable': 30.0, 'nees_band': [15.31, 44.46], 'identifiable': 28}


def _study_dir(root: Path, finals: dict[int, float]) -> Path:
    for seed, v in finals.items():
        (root / f'seed_{seed}').mkdir(parents=True)
        (root / f'seed_{seed}' / 'summary.json').write_text(json.dumps(_record(v)))
    (root / 'seed_12.log').write_text('a run log beside the directories\n')
    return root


def _row(text: str, label: str) -> list[str]:
    line = next(ln for ln in text.splitlines() if ln.startswith(f'| {label} |'))
    return [c.strip() for c in line.strip('|').split('|')]


def test_a_study_better_on_every_seed_is_lower_on_all_with_a_small_p() -> None:
    rng = np.random.default_rng(5)
    base = {s: 0.4 + 0.2 * rng.random() for s in range(1, 21)}
    better = Study('better', {s: _record(0.8 * v) for s, v in base.items()})
    text = compare([Study('base', {s: _record(v) for s, v in base.items()}), better])
    row = _row(text, 'final position error [mm]')
    assert row[3] == '0.800' and row[4] == '0.80-0.80' and row[5] == '20 of 20' and float(row[6]) < 1e-4, row
    assert '20 common seeds (1-20)' in text


def test_the_ratio_interval_pairs_the_seeds() -> None:
    # Seeds differ 4x, the two studies of a seed by a few percent: paired, the interval is narrow.
    rng = np.random.default_rng(6)
    base = {s: 0.2 + 0.6 * rng.random() for s in range(1, 21)}
    other = {s: 1.2 * v * rng.lognormal(0.0, 0.05) for s, v in base.items()}
    row = _row(compare([Study('a', {s: _record(v) for s, v in base.items()}),
                        Study('b', {s: _record(v) for s, v in other.items()})]), 'final position error [mm]')
    low, high = map(float, row[4].split('-'))
    assert low < float(row[3]) < high and 1.1 < low and high < 1.3, row


def test_a_study_equal_to_its_baseline_has_ratio_1_and_p_1() -> None:
    recs = {s: _record(0.1 * s) for s in range(1, 6)}
    row = _row(compare([Study('a', recs), Study('b', dict(recs))]), 'final / limit, position')
    assert row[3] == '1.000' and row[4] == '1.00-1.00' and row[5] == '0 of 5' and row[6] == '1', row


def test_only_the_common_seeds_are_paired_and_a_gap_is_said(tmp_path: Path) -> None:
    a = load_study(_study_dir(tmp_path / 'a', {1: 0.3, 2: 0.4, 3: 0.5}))
    b = load_study(_study_dir(tmp_path / 'b', {1: 0.3, 3: 0.25, 9: 9.0}), 'b')
    text = compare([a, b])
    assert '2 common seeds (1-3, not all)' in text
    assert _row(text, 'final position error [mm]')[2].startswith('0.275 / 0.275 / 0.250-0.300')


def test_a_committed_summary_reads_as_its_directory_rounded(tmp_path: Path) -> None:
    finals = {1: 0.3123, 2: 0.4567, 3: 0.5012}
    d = load_study(_study_dir(tmp_path / 'runs', finals))
    md = tmp_path / 'summary.md'
    md.write_text(summarise(d.records, {}, 'cmd'))
    m = load_study(md)
    assert sorted(m.records) == [1, 2, 3]
    assert [m.records[s]['final']['position_mm'] for s in (1, 2, 3)] == [0.31, 0.46, 0.5]


def test_bad_inputs_exit_2_naming_them(tmp_path: Path, capsys) -> None:
    empty = tmp_path / 'empty'
    empty.mkdir()
    assert main([str(empty), str(empty)]) == 2
    assert f'study {empty}: no seed_<S>/summary.json' in capsys.readouterr().err
    assert main([str(tmp_path / 'gone.md'), str(empty)]) == 2
    assert 'gone.md: no such file' in capsys.readouterr().err
    other = _study_dir(tmp_path / 'other', {5: 0.3})
    base = _study_dir(tmp_path / 'base', {1: 0.3})
    assert main([str(base), str(other), '--names', 'b', 'o']) == 2
    assert "study 'o' shares no seed with the baseline 'b'" in capsys.readouterr().err
    (base / 'seed_2').mkdir()
    (base / 'seed_2' / 'summary.json').write_text('{"final": ')     # a run killed while writing it
    assert main([str(base), str(other)]) == 2
    assert f"{base / 'seed_2' / 'summary.json'}: not a summary.json" in capsys.readouterr().err
    (base / 'seed_2' / 'summary.json').unlink()
    with pytest.raises(SystemExit):
        main([str(base), str(other), '--names', 'only-one'])
    with pytest.raises(ValueError, match='at least one other study'):
        compare([load_study(base)])


def test_a_study_in_parts_joins_its_seeds_and_refuses_one_seed_twice(tmp_path: Path) -> None:
    md = tmp_path / 'first.md'
    md.write_text(summarise(load_study(_study_dir(tmp_path / 'first', {1: 0.31, 2: 0.46})).records, {}, 'cmd'))
    more = _study_dir(tmp_path / 'more', {3: 0.52})
    joined = load_study(Path(f'{md}+{more}'), 'joined')
    assert sorted(joined.records) == [1, 2, 3] and joined.records[3]['final']['position_mm'] == 0.52
    with pytest.raises(ValueError, match=r'seeds \[3\] are in .*more and in an earlier part'):
        load_study(Path(f'{more}+{md}+{more}'))
    with pytest.raises(FileNotFoundError, match='gone.md: no such file'):
        load_study(Path(f'{md}+{tmp_path / "gone.md"}'))


def test_studies_of_two_numeric_environments_are_said_not_to_repeat_step_by_step() -> None:
    here, there = {'cpu': 'x', 'blas': 'SkylakeX'}, {'cpu': 'x', 'blas': 'Haswell'}
    base = {s: {**_record(0.5), 'environment': here} for s in range(1, 4)}
    same = compare([Study('a', base), Study('b', {s: dict(r) for s, r in base.items()})])
    assert 'b and a were made on the same numeric environment' in same
    other = compare([Study('a', base), Study('b', {s: {**r, 'environment': there} for s, r in base.items()})])
    assert 'b was made on another numeric environment than a (blas: SkylakeX -> Haswell)' in other
    old = compare([Study('a', {s: _record(0.5) for s in range(1, 4)}), Study('b', base)])
    assert 'No numeric environment recorded for a' in old
    assert 'numeric environment' not in compare([Study('a', {1: _record(0.5)}), Study('b', {1: _record(0.4)})])
