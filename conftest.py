"""Shared pytest fixtures.

``ros``: an isolated ROS 2 session for in-process integration tests: its own ``Context``, a
unique ``ROS_DOMAIN_ID`` and localhost-only discovery, a ``SingleThreadedExecutor`` (the
multi-threaded one collapses under fast timers in this rclpy), and ``spin_until`` which waits on a
condition with a deadline instead of sleeping.
"""
from __future__ import annotations

import itertools
import os
import time
from typing import Any, Callable

import pytest

# Discovery stays on this machine whatever the caller's environment says.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('AMENT_PREFIX_PATH', os.path.join(os.path.dirname(__file__), '.venv'))

# Domain ids 1..100, offset by the process id so two test runs on one machine rarely collide.
_DOMAIN_IDS = itertools.cycle([1 + (os.getpid() + i) % 100 for i in range(100)])


class RosSession:
    """Context, executor and helpers for one test."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.domain_id = next(_DOMAIN_IDS)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: list[Any] = []

    def add(self, node: Any) -> Any:
        """Add a node to the executor; it is destroyed at teardown."""
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str, **kwargs: Any) -> Any:
        """A plain probe node in this context."""
        from rclpy.node import Node

        return self.add(Node(name, context=self.context, **kwargs))

    def spin_until(self, predicate: Callable[[], bool], timeout: float = 10.0,
                   what: str = 'condition') -> None:
        """Spin until ``predicate()`` is true; fail the test with ``what`` after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                pytest.fail(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, seconds: float) -> None:
        """Spin for a wall-clock duration (for 'nothing happens' checks only)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        import rclpy

        for n in self.nodes:
            self.executor.remove_node(n)
            n.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def ros() -> Any:
    """An isolated in-process ROS 2 session (see module docstring)."""
    session = RosSession()
    try:
        yield session
    finally:
        session.close()
