"""tools.innovations: the NIS of the recorded updates, read back from a bag the recorder's way."""
from __future__ import annotations

from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.serialization import serialize_message

from calibration_bringup.mcap_writer import McapBagWriter
from calibration_interfaces.outcome import Outcome, StatusFormatError, encode_status, recorded_statuses
from tools.innovations import main, recorded_nis, runs_of

COUNTERS = {'updates': 0, 'rejected': 0, 'duplicates': 0, 'outliers': 0, 'changes': 0}


def _bag(path: Path, verdicts: list[tuple[Outcome, float]], malformed: int = -1) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with McapBagWriter(path) as w:
        w.add_channel('/body_schema/update_status', 'diagnostic_msgs/msg/DiagnosticStatus')
        for i, (outcome, m) in enumerate(verdicts):
            kv = encode_status(outcome, float(i), [0.0] * 7, m, 0.01, COUNTERS)
            if i == malformed:
                kv['mahalanobis'] = 'not a number'
            msg = DiagnosticStatus(name='dh_estimator', values=[KeyValue(key=k, value=v) for k, v in kv.items()])
            w.write('/body_schema/update_status', serialize_message(msg), (i + 1) * 10**9)
    return path


def test_updates_are_read_back_and_summed_over_a_study(tmp_path: Path, capsys) -> None:
    verdicts = [(Outcome.ACCEPTED, 100.0)] * 3 + [(Outcome.DUPLICATE, 50.0), (Outcome.ACCEPTED, 2.0),
                                                  (Outcome.OUTLIER, 6.0), (Outcome.FAILED, 0.0)]
    _bag(tmp_path / 'study' / 'seed_2' / 'calibration.mcap', verdicts)
    _bag(tmp_path / 'study' / 'seed_10' / 'calibration.mcap', [(Outcome.ACCEPTED, 1.0)] * 4)
    nis = recorded_nis(tmp_path / 'study' / 'seed_2' / 'calibration.mcap')
    assert nis == pytest.approx([1e4, 1e4, 1e4, 4.0, 36.0])         # no duplicate, no failure
    assert [r.name for r in runs_of([tmp_path / 'study'])] == ['seed_2', 'seed_10']
    assert main([str(tmp_path / 'study'), '--skip', '3']) == 0
    out = capsys.readouterr().out
    assert f'| {tmp_path / "study" / "seed_2"} | 5 | 2 | 20.0 | 1 | tails |' in out   # 36 > 27.86
    assert 'beyond the bound in 1 of 3 (33.3%; a right law: 0.01%), in 1 of 2 runs' in out
    assert 'the health check cautions against the law in 1 of 2 runs' in out


def test_a_path_that_is_no_run_is_named(tmp_path: Path, capsys) -> None:
    assert main([str(tmp_path)]) == 2
    assert f'{tmp_path}: neither a run' in capsys.readouterr().err


def test_a_malformed_verdict_is_named_or_skipped_on_request(tmp_path: Path, capsys) -> None:
    """tools.innovations refuses a bag with a status it cannot decode (the figures would be of
    another run); the fault table, counting what survived a fault, skips it."""
    bag = _bag(tmp_path / 'run' / 'calibration.mcap', [(Outcome.ACCEPTED, 2.0)] * 3, malformed=1)
    assert [s.mahalanobis for s in recorded_statuses(bag, skip_malformed=True)] == [2.0, 2.0]
    with pytest.raises(StatusFormatError, match='mahalanobis'):
        recorded_nis(bag)
    assert main([str(tmp_path / 'run')]) == 2
    assert 'mahalanobis' in capsys.readouterr().err
