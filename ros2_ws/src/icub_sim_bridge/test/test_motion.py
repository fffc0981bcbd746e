"""Command validation and bounded-speed following (pure)."""
from __future__ import annotations

import numpy as np
import pytest

from body_schema.robot import load_robot
from icub_sim_bridge.motion import CommandError, TrajectoryFollower, Waypoints, validate_command

ROBOT = load_robot()
NAMES = ROBOT.joint_names
Q0 = ROBOT.calibration_box.mean(axis=1)


def check(names, positions, times=()):
    return validate_command(names, positions, list(times), NAMES, ROBOT.limits, Q0)


def test_subset_command_keeps_other_joints() -> None:
    wp = check(['r_elbow', 'r_shoulder_pitch'], [[1.0, -0.5]])
    want = Q0.copy()
    want[3], want[0] = 1.0, -0.5
    np.testing.assert_allclose(wp.targets[0], want)


@pytest.mark.parametrize('names, positions, times, match', [
    (['r_knee'], [[0.1]], (), 'unknown joint names'),
    (['r_elbow', 'r_elbow'], [[0.5, 0.5]], (), 'repeated'),
    ([], [], (), 'no joints'),
    (['r_elbow'], [], (), 'empty trajectory'),
    (['r_elbow'], [[float('nan')]], (), 'non-finite'),
    (['r_elbow'], [[np.radians(120.0)]], (), 'r_elbow target 120.00 deg is outside'),
    (['r_elbow'], [[0.5, 0.6]], (), '2 positions for 1 joint'),
    (['r_elbow'], [[0.5], [0.6]], (2.0, 1.0), 'must not decrease'),
])
def test_bad_commands_are_named(names, positions, times, match) -> None:
    with pytest.raises(CommandError, match=match):
        check(names, positions, times)


def test_follower_respects_speed_and_lands_exactly() -> None:
    f = TrajectoryFollower(Q0, max_speed=np.radians(30.0))
    target = Q0 + np.radians([20, -10, 5, 30, 0, 0, 0])
    duration = f.start(Waypoints(target[None], np.zeros(1)))
    assert duration == pytest.approx(1.0)             # 30 deg at 30 deg/s, all joints together
    dt, prev, t = 0.002, f.q, 0.0
    while f.moving:
        q = f.advance(dt)
        assert np.max(np.abs(q - prev)) <= np.radians(30.0) * dt + 1e-12
        prev, t = q, t + dt
    assert t == pytest.approx(duration, abs=dt)
    np.testing.assert_array_equal(f.q, target)
    np.testing.assert_array_equal(f.advance(1.0), target)   # then holds


def test_waypoints_in_order_and_time_from_start_slows_down() -> None:
    f = TrajectoryFollower(Q0, max_speed=np.radians(30.0))
    a, b = Q0 + np.radians([10, 0, 0, 0, 0, 0, 0]), Q0 + np.radians([10, 0, 0, 10, 0, 0, 0])
    assert f.start(Waypoints(np.stack([a, b]), np.array([2.0, 2.5]))) == pytest.approx(2.5)   # arrive no earlier than time_from_start
    f.advance(2.0)
    np.testing.assert_allclose(f.q, a)
    f.advance(1.0)
    np.testing.assert_array_equal(f.q, b)


def test_stop_holds_mid_motion() -> None:
    f = TrajectoryFollower(Q0, max_speed=1.0)
    f.start(Waypoints((Q0 + 1.0)[None], np.zeros(1)))
    mid = f.advance(0.3)
    f.stop()
    np.testing.assert_array_equal(f.advance(1.0), mid)
