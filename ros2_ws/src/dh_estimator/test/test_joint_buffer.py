"""JointStateBuffer: samples by stamp, judged against the receiver's clock (pure, no rclpy)."""
import numpy as np
import pytest

from dh_estimator.joint_buffer import JointStateBuffer, StampInFuture, StampOutOfRange


def _q(v: float) -> np.ndarray:
    return np.full(2, v)


def test_out_of_order_samples_are_inserted_at_their_stamp() -> None:
    buf = JointStateBuffer(2)
    for t in (0.0, 0.2, 0.1, 0.3):            # 0.1 arrives late (another publisher, a deep queue)
        buf.add(t, _q(10 * t))
    np.testing.assert_allclose(buf.at(0.1), _q(1.0))
    np.testing.assert_allclose(buf.at(0.15), _q(1.5))
    buf.add(0.1, _q(7.0))                      # the same stamp again: the newer message wins
    np.testing.assert_allclose(buf.at(0.1), _q(7.0))
    assert len(buf) == 4


def test_the_window_is_bounded_behind_the_newest_stamp() -> None:
    buf = JointStateBuffer(2, horizon=1.0)
    for t in np.arange(0.0, 3.01, 0.1):
        buf.add(float(t), _q(t))
    assert len(buf) == 11 and buf.latest[0] == pytest.approx(3.0)
    with pytest.raises(StampOutOfRange, match='1.500'):
        buf.at(1.5)
    buf.add(0.5, _q(0.5))                      # late beyond the window: not kept
    assert len(buf) == 11


def test_a_stamp_far_ahead_of_the_clock_is_refused_and_the_buffer_keeps_working() -> None:
    buf = JointStateBuffer(2, future_tolerance=0.5)
    for t in np.arange(0.0, 1.0, 0.1):
        buf.add(float(t), _q(t), now=float(t) + 0.01)
    with pytest.raises(StampInFuture, match=r'stamp 1000\.000 s is 999\.0\d+ s ahead'):
        buf.add(1000.0, _q(9.0), now=1.0)
    buf.add(1.3, _q(1.3), now=1.0)             # within the tolerance (a clock lagging its publisher)
    for t in (1.4, 1.5, 1.6, 1.7, 1.8, 1.9):   # real samples after the stray one are all kept
        buf.add(float(t), _q(t), now=float(t))
    assert buf.latest[0] == pytest.approx(1.9)
    np.testing.assert_allclose(buf.at(1.85), _q(1.85))


def test_the_clock_stepping_back_starts_a_new_timeline() -> None:
    buf = JointStateBuffer(2, future_tolerance=0.5)
    for t in np.arange(50.0, 51.0, 0.1):
        buf.add(float(t), _q(t), now=float(t))
    assert not buf.observe_clock(50.6)         # jitter within the tolerance is not a jump
    assert len(buf) == 10
    buf.add(0.1, _q(0.1), now=0.1)             # the simulator restarted at 0
    buf.add(0.2, _q(0.2), now=0.2)
    assert len(buf) == 2
    np.testing.assert_allclose(buf.at(0.15), _q(0.15))


def test_bad_arguments_name_the_value() -> None:
    with pytest.raises(ValueError, match='-1'):
        JointStateBuffer(2, horizon=-1.0)
    with pytest.raises(ValueError, match='2 finite values'):
        JointStateBuffer(2).add(0.0, [0.0, np.nan])
