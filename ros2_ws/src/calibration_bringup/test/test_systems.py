"""The paper's system and the ablation from it to ours: every step one named change, ending at ours."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from body_schema import sampling
from calibration_bringup import systems as sy

REPO = Path(__file__).resolve().parents[4]


def _keys(system: dict) -> set[str]:
    return {f'{node}.{name}' for node, params in system.items() for name in params}


def test_the_ablation_steps_partition_the_papers_overrides() -> None:
    keys = [k for step in sy.ABLATION for k in step.keys]
    assert len(keys) == len(set(keys)), 'a parameter is handed back twice'
    assert set(keys) == _keys(sy.PAPER), 'the walk must end at ours'
    names = [s.name for s in sy.ABLATION]
    assert len(names) == len(set(names))


def test_each_step_changes_exactly_its_keys_from_the_paper_to_ours() -> None:
    assert sy.ablation_overrides(0) == sy.PAPER
    assert sy.ablation_overrides(len(sy.ABLATION)) == {}
    for k, step in enumerate(sy.ABLATION, start=1):
        assert _keys(sy.ablation_overrides(k - 1)) - _keys(sy.ablation_overrides(k)) == set(step.keys), step.name
    for bad in (-1, len(sy.ABLATION) + 1):
        with pytest.raises(ValueError, match=str(bad)):
            sy.ablation_overrides(bad)
    with pytest.raises(KeyError, match='selector.nope'):
        sy.without(sy.PAPER, ['selector.nope'])


def test_the_papers_constants_become_its_parameters() -> None:
    tuned = {**sy.PAPER_TUNED, 'q_fraction': 1e-3, 'noise_a': 2e-4, 'noise_b': 3e-7, 'cn_sigma': 0.02}
    p = sy.paper_system(tuned)
    # Q is the fraction of the initial covariance's diagonal (the paper's widths).
    p0 = np.diag(sampling.initial_covariance(1))
    assert (p['estimator']['q_length'], p['estimator']['q_angle']) == pytest.approx((1e-3 * p0[0], 1e-3 * p0[2]))
    assert p['selector']['q_length'] == p['estimator']['q_length']
    # One law sigma^2 = a r^2 + b (phi - 45)^2 for both blocks, no floor; CN one sigma in m and rad.
    assert (p['detector']['pdn_a_pos'], p['detector']['pdn_a_rot'], p['selector']['pdn_b_rot']) == (2e-4, 2e-4, 3e-7)
    assert p['estimator']['cn_sigma_rot_deg'] == pytest.approx(np.degrees(0.02))
    with pytest.raises(KeyError, match='gamma'):
        sy.paper_system({k: v for k, v in sy.PAPER_TUNED.items() if k != 'gamma'})


def test_the_paper_constants_are_the_tuning_records_choice() -> None:
    record = REPO / 'docs' / 'results' / 'paper' / 'tuning.json'
    chosen = json.loads(record.read_text())['chosen']
    assert chosen == pytest.approx(sy.PAPER_TUNED), f'{record} and systems.PAPER_TUNED disagree'
