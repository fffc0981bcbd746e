"""Warnings throttled per kind of problem, not per call site (pure; no rclpy).

One throttle per logging call site hides every error but the first of a burst, even when the
errors differ (a detector probed with twelve distinct bad inputs logged six). A
:class:`KeyedThrottle` lets the first message of each key through at once, then at most one per
``period`` seconds per key, and says how many of that key it suppressed in between::

    throttle = KeyedThrottle(2.0)
    text = throttle(f'image.{field}', f'left image not usable: {exc}')
    if text is not None:
        logger.warning(text)
"""
from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ['KeyedThrottle']


class KeyedThrottle:
    """Decides which messages of each key are logged.

    Parameters
    ----------
    period : float
        Seconds between two messages of the same key (the first one always passes).
    clock : callable, optional
        Current time [s]; ``time.monotonic`` by default.

    Attributes
    ----------
    counts : dict of str to int
        Messages seen per key (logged or not), for tests and summaries.
    """

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not period >= 0:
            raise ValueError(f'period must be >= 0 s, got {period}')
        self.period = float(period)
        self.clock = clock
        self.counts: dict[str, int] = {}
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def __call__(self, key: str, text: str) -> str | None:
        """The text to log for this occurrence of ``key`` (with the count suppressed since the
        previous one), or None to stay quiet."""
        self.counts[key] = self.counts.get(key, 0) + 1
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return None
        self._last[key] = now
        skipped = self._suppressed.pop(key, 0)
        return f'{text} ({skipped} more like it suppressed)' if skipped else text
