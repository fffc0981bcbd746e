"""A short history of joint states, queried at an image's stamp (pure Python, no rclpy)."""
from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['JointStateBuffer', 'StampOutOfRange']


class StampOutOfRange(LookupError):
    """The requested time is not covered by the buffered joint states."""


class JointStateBuffer:
    """Time-ordered joint positions with linear interpolation and a rest test.

    Parameters
    ----------
    n_joints : int
    horizon : float
        Seconds of history kept (older samples are dropped).
    """

    def __init__(self, n_joints: int, horizon: float = 10.0) -> None:
        self.n_joints = n_joints
        self.horizon = float(horizon)
        self._t: deque[float] = deque()
        self._q: deque[NDArray[np.float64]] = deque()

    def __len__(self) -> int:
        return len(self._t)

    @property
    def latest(self) -> tuple[float, NDArray[np.float64]] | None:
        return (self._t[-1], self._q[-1]) if self._t else None

    def add(self, t: float, q: ArrayLike) -> None:
        """Append a sample; out-of-order samples (older than the newest) are ignored."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_joints,) or not np.all(np.isfinite(q)):
            raise ValueError(f'joint positions must be {self.n_joints} finite values, got {q!r}')
        if self._t and t < self._t[-1]:
            return
        self._t.append(float(t))
        self._q.append(q)
        while self._t and self._t[0] < t - self.horizon:
            self._t.popleft()
            self._q.popleft()

    def at(self, t: float) -> NDArray[np.float64]:
        """Joint positions at time ``t``, linearly interpolated, shape (n_joints,).

        Raises
        ------
        StampOutOfRange
            If ``t`` is before the oldest or after the newest sample (no extrapolation).
        """
        if not self._t or t < self._t[0] or t > self._t[-1]:
            span = f'[{self._t[0]:.3f}, {self._t[-1]:.3f}]' if self._t else 'empty'
            raise StampOutOfRange(f'no joint state covers t = {t:.3f} s (buffer {span})')
        ts = np.fromiter(self._t, float)
        i = int(np.searchsorted(ts, t))
        if ts[i] == t or i == 0:
            return self._q[i].copy()
        w = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
        return (1 - w) * self._q[i - 1] + w * self._q[i]

    def is_static(self, t: float, window: float, tol: float) -> bool:
        """Whether every sample in ``[t - window, t]`` is within ``tol`` (rad) of ``at(t)``.

        False when the window is not covered by the buffer.
        """
        if not self._t or t - window < self._t[0] or t > self._t[-1]:
            return False
        ref = self.at(t)
        ts = np.fromiter(self._t, float)
        idx = np.nonzero((ts >= t - window) & (ts <= t))[0]
        return all(np.max(np.abs(self._q[i] - ref)) <= tol for i in idx) and \
            np.max(np.abs(self.at(t - window) - ref)) <= tol
