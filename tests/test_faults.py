"""Fault injection on the calibration graph: a dead node, a burst of bad messages, a clock that
jumps back. The scenarios live in :mod:`tools.fault_table` (which also prints docs/faults.md's fault
table from the same rows); here each row is held to what must be true:

* no accepted observation the estimator made is missing from the bag;
* no silent wrong answer (an iteration recorded accepted that the estimator never accepted, or a
  run that finished with only successful outcomes and an estimate no better than its start);
* every node that was not killed survives, and the run finishes, or, where nothing in process
  can notice the death (sim, selector), stops in a named phase (the launcher notices a dead
  process: tests/test_end_to_end.py::test_a_node_that_dies_fails_the_run_with_its_log_tail);
* after a burst or a clock jump, good data is accepted again (after the burst: not yet, a
  strict xfail with what was found).

That a bad frame is no longer a hidden hand is tested node by node
(marker_detector/test/test_detector_node.py, active_selector/test/test_selector_node.py).
"""
from __future__ import annotations

from pathlib import Path

import pytest

from tools.fault_table import KILLABLE, FaultRow, run_burst, run_clock_back, run_kill, run_kill_recorder_process


@pytest.mark.parametrize('node', KILLABLE)
def test_a_node_killed_mid_run_loses_no_recorded_observation(ros, tmp_path: Path, node: str) -> None:
    row = run_kill(node, tmp_path, domain_id=ros.domain_id)
    assert row.survived, row
    assert row.accepted_lost == 0 and row.silent_wrong == 0, row
    assert 'accepted' in row.outcomes[:row.fault_at] or row.fault_at == 0, row
    if node in ('detector', 'estimator'):
        # The selector notices: every later attempt ends timeout (or failed, unreachable: never
        # accepted without an estimator), and the run finishes.
        after = row.outcomes[row.fault_at:]
        assert row.ended and after and 'accepted' not in after and 'timeout' in after, row
    else:
        # Nothing in process drives the loop on (a dead sim stops the clock the selector's
        # timeouts run on): the run stops in a named phase instead of inventing outcomes.
        assert not row.ended and 'selector phase' in row.note, row


def test_sigkill_of_the_recorder_process_keeps_every_recorded_observation(ros, tmp_path: Path) -> None:
    """The bag of a recorder killed mid-run is read with the project's reader up to its last
    complete chunk (the recovering reader of branch h17a makes every tool read it so)."""
    row = run_kill_recorder_process(tmp_path, domain_id=ros.domain_id)
    assert row.survived and row.ended, row
    assert 'reader:' not in row.note, row
    assert row.accepted_lost == 0, row


@pytest.fixture(scope='module')
def burst(tmp_path_factory: pytest.TempPathFactory) -> FaultRow:
    from conftest import RosSession

    session = RosSession()            # only for a domain id of this test run
    try:
        return run_burst(tmp_path_factory.mktemp('burst'), domain_id=session.domain_id)
    finally:
        session.close()


def test_a_burst_of_bad_messages_on_every_input_topic_is_survived(burst: FaultRow) -> None:
    assert burst.injected >= 10_000 * 11, burst
    assert burst.survived and burst.ended, burst
    assert burst.silent_wrong == 0, burst


@pytest.mark.xfail(strict=True, reason='found by this suite, not fixed: after a burst of bad /joint_states from '
                   'a second publisher the estimator stops receiving the simulator\'s joint states a few '
                   'sim seconds later (its buffer stays at an old stamp, hand poses pend, later attempts '
                   'end timeout; the samples are in the reader, the wait set stops reporting them: '
                   'docs/faults.md); bad /arm/command stop the arm mid-move (unreachable); a burst on '
                   '/body_schema/update_status can evict a genuine verdict from the keep-last queues')
def test_after_a_burst_good_data_is_accepted_again_and_recorded(burst: FaultRow) -> None:
    assert burst.accepted_lost == 0, burst
    assert 'accepted' in burst.outcomes[burst.fault_at:], burst


def test_the_clock_jumping_back_is_survived_and_the_run_resumes(ros, tmp_path: Path) -> None:
    row = run_clock_back(tmp_path, domain_id=ros.domain_id)
    assert row.survived and row.ended, row
    assert row.accepted_lost == 0 and row.silent_wrong == 0, row
    # Seed 1's random targets after the jump are seen, not seen, seen without the fault; with a
    # 1 s outcome timeout, shorter than the jump, nothing may be lost to the repeated times.
    after = row.outcomes[row.fault_at:]
    assert 'accepted' in after and 'timeout' not in after, row
