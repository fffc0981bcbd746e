"""The safety audit of recorded runs: commanded targets re-checked offline, the check's state read."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from body_schema import load_robot
from body_schema.collision import CollisionModel
from body_schema.sampling import uniform_configs
from tools.safety_audit import audit_run, table


@pytest.fixture(scope='module')
def collision() -> CollisionModel:
    return CollisionModel(load_robot('ur5e'))


def _run(root: Path, targets: np.ndarray, check: str | None, record_key: bool | None = None) -> Path:
    root.mkdir()
    recs = [{'iteration': i + 1, 'target_deg': np.degrees(q).tolist(), 'reached_deg': np.degrees(q).tolist(),
             'selection_s': 1.0, 'safety_s': 0.0, 'refused': 0, 'refused_paths': 0,
             **({} if record_key is None else {'collision_check': record_key})} for i, q in enumerate(targets)]
    (root / 'progress.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in recs))
    if check is not None:
        (root / 'run.env').write_text(f'robot=ur5e\ncollision_check={check}\n')
    return root


def test_an_unchecked_run_shows_its_targets_inside_the_margins(tmp_path: Path, collision: CollisionModel) -> None:
    q = uniform_configs(collision.robot.calibration_box, 400, seed=3)
    slack = collision.slack(q)
    bad, good = q[slack < 0][:2], q[slack > 0.04][:3]
    assert len(bad) == 2 and len(good) == 3           # the UR5e's box reaches its table and itself
    row = audit_run(_run(tmp_path / 'off', np.vstack([good, bad]), '0'), collision, samples=20)
    assert row['checked'] is False and row['targets_inside_margin'] == 2 and row['least_slack_m'] < 0
    assert row['paths_inside_margin'] >= 2
    text = table([row])
    assert '| not checked |' in text and '(1 without the collision check)' in text


@pytest.mark.parametrize('check, key, checked', [('1', None, True), (None, None, True), (None, False, False),
                                                  ('0', True, False)])
def test_the_check_state_comes_from_run_env_then_the_records(tmp_path: Path, collision: CollisionModel, check, key,
                                                             checked) -> None:
    q = collision.robot.calibration_box.mean(axis=1)[None]
    row = audit_run(_run(tmp_path / 'r', q, check, key), collision, samples=5)
    assert row['checked'] is checked
    assert ('not checked' in table([row])) is (not checked)
