"""A short history of joint states, queried at an image's stamp (pure Python, no rclpy).

Samples are kept sorted by stamp within ``horizon`` seconds of the newest one. Time is judged
against the receiver's clock when the caller gives it (``now``): a stamp further ahead of it than
``future_tolerance`` is refused (one stray stamp would otherwise become the newest sample and push
every real one out of the window), and a clock that steps back (a simulator restarted) empties
the buffer, whose stamps belong to the old timeline.
"""
from __future__ import annotations

import bisect

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['JointStateBuffer', 'StampOutOfRange', 'StampInFuture']


class StampOutOfRange(LookupError):
    """The requested time is not covered by the buffered joint states."""


class StampInFuture(ValueError):
    """A stamp further ahead of the receiver's clock than the tolerance (names both times)."""


class JointStateBuffer:
    """Stamp-ordered joint positions with linear interpolation and a rest test.

    Parameters
    ----------
    n_joints : int
    horizon : float
        Seconds of history kept behind the newest sample (older samples are dropped).
    future_tolerance : float
        How far a stamp may lead the clock given to :meth:`add` [s]; also how far that clock
        may step back before the buffer is taken to be on a new timeline and emptied.
    """

    def __init__(self, n_joints: int, horizon: float = 10.0, future_tolerance: float = 1.0) -> None:
        if horizon <= 0 or future_tolerance < 0:
            raise ValueError(f'horizon must be positive and future_tolerance non-negative, '
                             f'got {horizon} and {future_tolerance}')
        self.n_joints = n_joints
        self.horizon = float(horizon)
        self.future_tolerance = float(future_tolerance)
        self._t: list[float] = []
        self._q: list[NDArray[np.float64]] = []
        self._now: float | None = None      # the latest clock reading seen
        #: Times the buffer was emptied because the clock stepped back.
        self.resets = 0

    def __len__(self) -> int:
        return len(self._t)

    @property
    def latest(self) -> tuple[float, NDArray[np.float64]] | None:
        return (self._t[-1], self._q[-1]) if self._t else None

    def clear(self) -> None:
        """Forget every sample and the clock."""
        self._t.clear()
        self._q.clear()
        self._now = None

    def observe_clock(self, now: float) -> bool:
        """Take a reading of the receiver's clock [s]; True if it stepped back and the buffer was emptied.

        A step back by more than ``future_tolerance`` (a simulator restart, a bag looped) starts
        a new timeline: the buffered stamps would otherwise all lie ahead of the new ones.
        """
        jumped = self._now is not None and now < self._now - self.future_tolerance
        if jumped:
            self.clear()
            self.resets += 1
        self._now = float(now)
        return jumped

    def add(self, t: float, q: ArrayLike, now: float | None = None) -> None:
        """Insert a sample at its stamp (out-of-order samples included; an equal stamp replaces).

        Parameters
        ----------
        t : float
            The sample's stamp [s].
        q : array_like, shape (n_joints,)
            Joint positions [rad].
        now : float, optional
            The receiver's clock [s]; without it the stamp is not checked against time.

        Raises
        ------
        ValueError
            If ``q`` is not ``n_joints`` finite values.
        StampInFuture
            If ``t`` is more than ``future_tolerance`` ahead of ``now``; the buffer is unchanged.
        """
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_joints,) or not np.all(np.isfinite(q)):
            raise ValueError(f'joint positions must be {self.n_joints} finite values, got {q!r}')
        t = float(t)
        if now is not None:
            self.observe_clock(now)
            if t > now + self.future_tolerance:
                raise StampInFuture(f'stamp {t:.3f} s is {t - now:.3f} s ahead of the clock ({now:.3f} s; '
                                    f'tolerance {self.future_tolerance:g} s)')
        if self._t and t < self._t[-1] - self.horizon:
            return                                   # older than the window keeps
        i = bisect.bisect_left(self._t, t)
        if i < len(self._t) and self._t[i] == t:
            self._q[i] = q
            return
        self._t.insert(i, t)
        self._q.insert(i, q)
        cut = bisect.bisect_left(self._t, self._t[-1] - self.horizon)
        if cut:
            del self._t[:cut], self._q[:cut]

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
        i = bisect.bisect_left(self._t, t)
        if self._t[i] == t or i == 0:
            return self._q[i].copy()
        w = (t - self._t[i - 1]) / (self._t[i] - self._t[i - 1])
        return (1 - w) * self._q[i - 1] + w * self._q[i]

    def is_static(self, t: float, window: float, tol: float) -> bool:
        """Whether every sample in ``[t - window, t]`` is within ``tol`` (rad) of ``at(t)``.

        False when the window is not covered by the buffer.
        """
        if not self._t or t - window < self._t[0] or t > self._t[-1]:
            return False
        ref = self.at(t)
        lo, hi = bisect.bisect_left(self._t, t - window), bisect.bisect_right(self._t, t)
        return all(np.max(np.abs(self._q[i] - ref)) <= tol for i in range(lo, hi)) and \
            np.max(np.abs(self.at(t - window) - ref)) <= tol
