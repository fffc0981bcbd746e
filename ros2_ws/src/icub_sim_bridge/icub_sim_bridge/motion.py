"""Joint-trajectory validation and bounded-speed following (pure; no ROS, no simulator).

A command is a list of waypoints over a subset of the arm's joints. :func:`validate_command`
turns it into full-arm targets or raises :class:`CommandError` naming the problem;
:class:`TrajectoryFollower` moves the joints along straight joint-space segments, every joint
arriving together, with no joint faster than the speed limit (and no earlier than the waypoint's
``time_from_start``), then holds the last target exactly.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['CommandError', 'Waypoints', 'validate_command', 'TrajectoryFollower']


class CommandError(ValueError):
    """A joint command was rejected; the message says why."""


@dataclass(frozen=True)
class Waypoints:
    """A validated command: full-arm targets and the earliest arrival times.

    Attributes
    ----------
    targets : ndarray, shape (K, L)
        Joint targets [rad], one row per waypoint (joints not named keep their current value).
    times : ndarray, shape (K,)
        ``time_from_start`` of each waypoint [s] (0 when unspecified).
    """

    targets: NDArray[np.float64]
    times: NDArray[np.float64]


def validate_command(names: Sequence[str], positions: Sequence[Sequence[float]],
                     times: Sequence[float], joint_names: Sequence[str], limits: ArrayLike,
                     current: ArrayLike, tol: float = 1e-9) -> Waypoints:
    """Check a joint trajectory and expand it to full-arm waypoints.

    Parameters
    ----------
    names : sequence of str
        Joint names of the command (a subset of ``joint_names``, any order, no repeats).
    positions : sequence of sequences of float, shape (K, len(names))
        Target positions per waypoint [rad].
    times : sequence of float, shape (K,)
        ``time_from_start`` per waypoint [s].
    joint_names : sequence of str, length L
    limits : array_like, shape (L, 2)
        Joint limits [rad].
    current : array_like, shape (L,)
        Present joint positions; fill joints the command does not name.
    tol : float
        Slack on the limits [rad].

    Raises
    ------
    CommandError
        Empty trajectory or names, unknown or repeated joint names, wrong number of positions,
        NaN/inf, a target outside the limits, or decreasing times.
    """
    names = list(names)
    if not names:
        raise CommandError('command names no joints')
    unknown = [n for n in names if n not in joint_names]
    if unknown:
        raise CommandError(f'unknown joint names {unknown}; expected a subset of {list(joint_names)}')
    if len(set(names)) != len(names):
        raise CommandError(f'repeated joint names in {names}')
    if len(positions) == 0:
        raise CommandError('empty trajectory: no points')
    limits = np.asarray(limits, dtype=float)
    idx = [list(joint_names).index(n) for n in names]
    targets = np.empty((len(positions), len(joint_names)))
    prev = np.asarray(current, dtype=float)
    for k, pos in enumerate(positions):
        pos = np.asarray(pos, dtype=float)
        if pos.shape != (len(names),):
            raise CommandError(f'point {k} has {pos.size} positions for {len(names)} joint names')
        if not np.all(np.isfinite(pos)):
            bad = [names[i] for i in np.nonzero(~np.isfinite(pos))[0]]
            raise CommandError(f'point {k}: non-finite target (NaN/inf) for {bad}')
        lo, hi = limits[idx, 0], limits[idx, 1]
        out = np.nonzero((pos < lo - tol) | (pos > hi + tol))[0]
        if out.size:
            i = out[0]
            raise CommandError(f'point {k}: {names[i]} target {np.degrees(pos[i]):.2f} deg is outside '
                               f'the limits [{np.degrees(lo[i]):.2f}, {np.degrees(hi[i]):.2f}] deg')
        row = prev.copy()
        row[idx] = np.clip(pos, lo, hi)
        targets[k] = row
        prev = row
    t = np.asarray(times, dtype=float) if len(times) else np.zeros(len(positions))
    if t.shape != (len(positions),) or not np.all(np.isfinite(t)) or np.any(t < 0):
        raise CommandError(f'time_from_start must be finite, >= 0 and given for every point, got {t.tolist()}')
    if np.any(np.diff(t) < 0):
        raise CommandError(f'time_from_start must not decrease, got {t.tolist()}')
    return Waypoints(targets, t)


class TrajectoryFollower:
    """Bounded-speed joint-space interpolation through waypoints, then hold.

    Parameters
    ----------
    q0 : array_like, shape (L,)
        Initial joint positions [rad].
    max_speed : float
        Maximum speed of any joint [rad/s].
    """

    def __init__(self, q0: ArrayLike, max_speed: float) -> None:
        if not (np.isfinite(max_speed) and max_speed > 0):
            raise ValueError(f'max_speed must be finite and > 0, got {max_speed}')
        self.max_speed = float(max_speed)
        self._q = np.array(q0, dtype=float)
        self._segments: list[tuple[NDArray[np.float64], NDArray[np.float64], float]] = []
        self._t = 0.0   # time into the current segment [s]

    @property
    def q(self) -> NDArray[np.float64]:
        """Current joint positions, shape (L,)."""
        return self._q.copy()

    @property
    def moving(self) -> bool:
        return bool(self._segments)

    @property
    def target(self) -> NDArray[np.float64]:
        """Where the arm will come to rest, shape (L,)."""
        return self._segments[-1][1].copy() if self._segments else self._q.copy()

    def start(self, waypoints: Waypoints) -> float:
        """Replace any motion in progress by a new one from the current position.

        Returns
        -------
        float
            Duration of the whole motion [s].
        """
        self._segments, self._t = [], 0.0
        start, t_prev = self._q.copy(), 0.0
        for target, t_k in zip(waypoints.targets, waypoints.times):
            fastest = float(np.max(np.abs(target - start))) / self.max_speed
            duration = max(fastest, float(t_k) - t_prev)
            t_prev = max(float(t_k), t_prev + duration)
            if duration > 0:
                self._segments.append((start, target.copy(), duration))
            start = target
        if not self._segments:
            self._q = waypoints.targets[-1].copy()
        return sum(s[2] for s in self._segments)

    def stop(self) -> None:
        """Hold the present position."""
        self._segments, self._t = [], 0.0

    def advance(self, dt: float) -> NDArray[np.float64]:
        """Move ``dt`` seconds along the motion; returns the new positions, shape (L,)."""
        self._t += dt
        while self._segments:
            start, target, duration = self._segments[0]
            if self._t < duration:
                self._q = start + (target - start) * (self._t / duration)
                break
            # Segment finished: land exactly on its target, carry the leftover time on.
            self._q = target.copy()
            self._t -= duration
            self._segments.pop(0)
        if not self._segments:
            self._t = 0.0
        return self._q.copy()
