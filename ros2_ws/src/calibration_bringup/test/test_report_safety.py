"""The report's safety line read from a bag's selection records (calibration_bringup.report).

Synthetic bags written the recorder's way (McapBagWriter); no ROS graph.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from calibration_bringup.mcap_writer import McapBagWriter
from calibration_bringup.report import _safety_lines, safety_record


def _bag(path: Path, records: list[dict[str, object]]) -> Path:
    with McapBagWriter(path) as w:
        w.add_channel('/calibration/progress', 'std_msgs/msg/String')
        for i, r in enumerate(records):
            w.write('/calibration/progress', serialize_message(String(data=json.dumps(r))), (i + 1) * 10**9)
    return path


@pytest.mark.parametrize('checks, checked', [
    ([True, True], True),
    ([None, None], True),            # records from before the key: the check was always on then
    ([True, False], False),          # one unchecked selection makes the run unchecked
])
def test_the_report_says_whether_the_selector_checked_its_targets(tmp_path: Path, checks, checked) -> None:
    records = [{'iteration': i + 1, 'source': 'batch:BOBYQA', 'refused': 2, 'refused_paths': 1,
                **({} if c is None else {'collision_check': c})} for i, c in enumerate(checks)]
    s = safety_record(_bag(tmp_path / 'run.mcap', records))
    assert s['checked'] is checked and s['refused'] == 4 and s['refused_paths'] == 2
    line = _safety_lines(s)[0]
    if checked:
        assert 'refused 4 candidates inside a collision margin and 2 behind one' in line, line
    else:
        assert 'did NOT check' in line and 'refused' not in line, line
    assert 'no contact report in the bag' in line
