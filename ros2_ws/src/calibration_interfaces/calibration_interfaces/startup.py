"""A signal that arrives while a node executable is still importing (pure: no rclpy).

Python's default SIGINT handler raises KeyboardInterrupt wherever the main thread is. During a
node's imports (numpy, OpenCV, PyBullet, rclpy: seconds on a loaded machine) that can be inside
a callback whose exceptions Python only prints (``Exception ignored in: <function
_get_module_lock.<locals>.cb>``), and the signal is lost: the node then starts and runs until
it is SIGKILLed (seen in ``tests/test_node_signals.py``). Imported first by every node module,
this installs a handler that remembers the signal and still raises, so an import is cut short
as before, and :func:`calibration_interfaces.node_util.spin_node` ends the node if the
exception was swallowed.
"""
from __future__ import annotations

import signal
from types import FrameType

__all__ = ['RECEIVED']

#: Signals received since this module was imported (SIGINT, SIGTERM).
RECEIVED: list[int] = []


def _remember(signum: int, _frame: FrameType | None) -> None:
    RECEIVED.append(signum)
    raise KeyboardInterrupt


for _signum in (signal.SIGINT, signal.SIGTERM):
    # Also undoes an inherited SIG_IGN (a script's background job starts with SIGINT ignored).
    signal.signal(_signum, _remember)
