"""The paper's tuning procedure: its objective, its choices, and a dry run of the whole procedure."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from calibration_bringup import paper_tuning as pt
from calibration_bringup.systems import PAPER_TUNED


def _result(stage: str, point: dict, **methods: dict) -> pt.PointResult:
    return pt.PointResult(stage, point, {m: {'objective': 0.0, 'position_mm': 1.0, 'orientation_deg': 1.0,
                                             'movement_deg': 1000.0, **v} for m, v in methods.items()})


def test_the_objective_is_the_mean_log_error_and_refuses_nonsense() -> None:
    assert pt.objective([1.0, 100.0], [1.0, 1.0]) == pytest.approx(0.5 * 4.605170186, rel=1e-9)
    assert pt.objective([10.0], [0.1]) == pytest.approx(0.0, abs=1e-12)
    for bad in (([], []), ([1.0], [1.0, 2.0]), ([0.0], [1.0])):
        with pytest.raises(ValueError):
            pt.objective(*bad)


def test_the_procedure_covers_the_silent_constants_in_order() -> None:
    assert set(pt.START) == set(PAPER_TUNED)
    tuned = {k for s in pt.STAGES for p in s.grid for k in p}
    # What no stage tunes keeps its starting value: the arctan slope b (a alone scales the penalty).
    assert set(PAPER_TUNED) - tuned == {'penalty_b'} and PAPER_TUNED['penalty_b'] == pt.START['penalty_b']
    assert [s.name for s in pt.STAGES] == ['law', 'cn', 'kernel', 'penalty', 'search', 'movement']
    assert pt.STAGES[0].methods == ('R',) and pt.SEED_BASE >= 1000      # never the reported seeds 0-49


def test_choices_follow_the_written_rules() -> None:
    law = pt.STAGES[0]
    a = _result('law', {'noise_a': 1.0}, R={'objective': 2.0})
    b = _result('law', {'noise_a': 2.0}, R={'objective': 1.0})
    c = _result('law', {'noise_a': 3.0}, R={'objective': 1.0})
    assert pt.choose(law, [a, b, c]) == {'noise_a': 2.0}                 # lowest; ties to the earlier point
    search = next(s for s in pt.STAGES if s.name == 'search')
    cheap = _result('search', {'max_evals': 250}, AL={'objective': 1.04})
    mid = _result('search', {'max_evals': 1000}, AL={'objective': 1.0})
    dear = _result('search', {'max_evals': 4000}, AL={'objective': 0.99})
    assert pt.choose(search, [cheap, mid, dear]) == {'max_evals': 250}  # within the tolerance of the best
    assert pt.choose(search, [_result('search', {'max_evals': 250}, AL={'objective': 1.2}), mid, dear]) == \
        {'max_evals': 1000}
    movement = pt.STAGES[-1]
    ref = {'position_mm': 10.0, 'orientation_deg': 2.0}
    points = [_result('movement', {'gamma': 1e-4}, UCSAL={'position_mm': 11.0, 'orientation_deg': 2.1,
                                                          'movement_deg': 3000.0}),
              _result('movement', {'gamma': 1e-3}, UCSAL={'position_mm': 12.4, 'orientation_deg': 2.4,
                                                          'movement_deg': 1500.0}),
              _result('movement', {'gamma': 1e-2}, UCSAL={'position_mm': 30.0, 'orientation_deg': 2.0,
                                                          'movement_deg': 300.0, 'objective': -1.0}),
              _result('movement', {'delta': 0.1}, CCSAL={'position_mm': 20.0, 'orientation_deg': 2.0,
                                                         'objective': 3.0}),
              _result('movement', {'delta': 0.2}, CCSAL={'position_mm': 19.0, 'orientation_deg': 2.0,
                                                         'objective': 2.0})]
    # gamma: the least movement within 1.25x AL's errors; delta: none within, so the best objective.
    assert pt.choose(movement, points, ref) == {'gamma': 1e-3, 'delta': 0.2}
    with pytest.raises(ValueError, match='reference'):
        pt.choose(movement, points)


@pytest.mark.slow
def test_a_dry_run_of_the_whole_procedure_writes_its_record(tmp_path: Path, monkeypatch) -> None:
    """One repetition of two iterations per point: every stage runs on the real graph and chooses."""
    args = argparse.Namespace(repetitions=1, iterations=2, jobs=2, output=tmp_path)
    stages = pt.STAGES
    small = tuple(pt.Stage(s.name, s.methods, s.grid[:2] if s.name != 'movement' else
                           (s.grid[0], s.grid[-1]), s.constant_noise) for s in stages)
    monkeypatch.setattr(pt, 'STAGES', small)
    chosen = pt.run_tuning(args)
    record = json.loads((tmp_path / 'tuning.json').read_text())
    assert record['chosen'] == chosen and set(chosen) == set(PAPER_TUNED)
    assert record['seed_base'] == pt.SEED_BASE
    assert {p['stage'] for p in record['points']} == {s.name for s in small} | {'movement-reference'}
    text = (tmp_path / 'tuning.md').read_text()
    assert '## Stage `law` (R)' in text and '| `q_fraction` |' in text
    # Resuming costs nothing: every point's runs are finished.
    assert pt.run_tuning(args) == chosen


def test_a_choice_on_the_grids_edge_is_followed_beyond_it() -> None:
    law = pt.STAGES[0]
    assert law.axes()['noise_a'] == [1e-5, 1e-4, 1e-3, 1e-2]
    inside = {'noise_a': 1e-4, 'noise_b': 1e-7, 'q_fraction': 1e-4}
    assert all(pt.next_beyond(law, inside, k) is None for k in inside)
    top = {**inside, 'noise_b': 1e-6}
    assert pt.next_beyond(law, top, 'noise_b') == {**inside, 'noise_b': 1e-5}
    assert pt.next_beyond(law, {**inside, 'noise_b': 1e-5}, 'noise_b') == {**inside, 'noise_b': 1e-4}
    assert pt.next_beyond(law, {**inside, 'noise_a': 1e-5}, 'noise_a') == {**inside, 'noise_a': 1e-6}
    # No process noise is a true end: nothing lies below 0.
    assert pt.next_beyond(law, {**inside, 'q_fraction': 0.0}, 'q_fraction') is None
    assert not pt.STAGES[4].extend and not pt.STAGES[5].extend     # the budget and the trade-off
