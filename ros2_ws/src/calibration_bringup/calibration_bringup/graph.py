"""The calibration graph in one process: the one place it is assembled from the node classes.

Sim, detector, estimator and selector (and optionally the MCAP recorder) on one
``SingleThreadedExecutor`` with its own ``Context`` and ``ROS_DOMAIN_ID``; the experiment
(:mod:`calibration_bringup.experiment`), the closed-loop test and the loop benchmark
(``tools/loop_bench.py``) all run it. For separate processes the same nodes start from
``scripts/run_calibration.sh`` or ``launch/calibration.launch.py`` with the parameter files in
``config/``.

Usage::

    with ros_session(domain_id=42) as (context, executor):
        with InProcessGraph(context, executor, {'selector': {'iterations': 10}}) as graph:
            graph.spin_until(lambda: graph.selector.done, timeout=300.0)

Timing: with ``time_callbacks=True`` the graph accumulates the wall time of every subscription
and timer callback per node (those a node creates later, like the recorder's on discovery,
included) in :attr:`InProcessGraph.callback_seconds`; the simulator's rendering alone is
``graph.sim.world.render_seconds``.
"""
from __future__ import annotations

import functools
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

__all__ = ['NODES', 'PARAMS_FILES', 'GraphTimeout', 'config_dir', 'default_parameters', 'merge_parameters',
           'with_detector_eyes', 'recorder_available', 'ros_session', 'CallbackTimer', 'InProcessGraph']

#: The graph's nodes, in creation order (the recorder, if any, comes last).
NODES = ('sim', 'detector', 'estimator', 'selector')


class GraphTimeout(TimeoutError):
    """The graph did not reach a condition within its deadline (names the condition)."""


#: Each node's parameter file in ``share/calibration_bringup/config`` and its node name there.
PARAMS_FILES = {'sim': ('sim.yaml', 'icub_sim'), 'detector': ('detector.yaml', 'marker_detector'),
                'estimator': ('estimator.yaml', 'dh_estimator'), 'selector': ('selector.yaml', 'active_selector')}


def config_dir() -> Path:
    """``share/calibration_bringup/config`` when installed, else the package's ``config/`` sources."""
    try:
        from ament_index_python.packages import get_package_share_directory
        installed = Path(get_package_share_directory('calibration_bringup')) / 'config'
        if installed.is_dir():
            return installed
    except (ImportError, LookupError, ValueError, OSError):   # not installed, or no prefix path
        pass
    return Path(__file__).resolve().parents[1] / 'config'


def default_parameters() -> dict[str, dict[str, Any]]:
    """Parameters of an in-process graph: each node's parameter file (the values every run uses,
    as ``run_calibration.sh`` and the launch file pass them), then the in-process choices: the
    simulator as fast as it can, the left eye only and no contact check, every other node on the
    simulator's clock, no model export at shutdown.

    Returns
    -------
    dict
        ``{'sim': {...}, 'detector': {...}, 'estimator': {...}, 'selector': {...}}``.
    """
    from calibration_interfaces.parameters import read_params_file

    config = config_dir()
    files = {key: read_params_file(config / name, node) for key, (name, node) in PARAMS_FILES.items()}
    sim_time = {'use_sim_time': True}
    # No contact check in process: at ~1 ms a joint state it would double an experiment's wall time
    # (run_calibration.sh runs keep it; the selector's collision check is on either way).
    return merge_parameters(files, {'sim': {'real_time_factor': 0.0, 'cameras': ['left'], 'contact_check': False},
                                    'detector': dict(sim_time),
                                    'estimator': {**sim_time, 'export_on_shutdown': False},
                                    'selector': dict(sim_time)})


def with_detector_eyes(params: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``params`` with the simulator rendering every eye the detector reads: the in-process graph
    renders the left eye only unless the detector's ``use_right_eye`` asks for the right one too
    (on a robot with eyes: a fixed camera has no right eye, and the detector ignores it there)."""
    from body_schema import load_robot

    cameras = list(params.get('sim', {}).get('cameras', []))
    if params.get('detector', {}).get('use_right_eye') and cameras and 'right' not in cameras:
        if load_robot(params['sim'].get('robot', 'icub_right_arm')).eyes is not None:
            params['sim']['cameras'] = [*cameras, 'right']
    return params


def merge_parameters(*layers: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-node parameter dicts merged left to right (later layers win per parameter)."""
    out: dict[str, dict[str, Any]] = {}
    for layer in layers:
        for node, params in layer.items():
            out.setdefault(node, {}).update(params)
    return out


def recorder_available() -> bool:
    """Whether :mod:`calibration_bringup.recorder_node` is installed."""
    import importlib.util

    return importlib.util.find_spec('calibration_bringup.recorder_node') is not None


@contextmanager
def ros_session(domain_id: int, qos_events: bool = True,
                discovery: str = 'LOCALHOST') -> Iterator[tuple[Any, Any]]:
    """A fresh ``Context`` on ``domain_id`` and a ``SingleThreadedExecutor``.

    Parameters
    ----------
    domain_id : int
    discovery : {'LOCALHOST', 'OFF'}
        ``ROS_AUTOMATIC_DISCOVERY_RANGE`` for the context. ``OFF`` confines it to its own
        process (its nodes still talk to each other): a graph that lives in one process then
        cannot meet another on the same domain id, which a pid-derived id does not rule out.
    qos_events : bool
        Wait on the QoS event handlers rclpy gives every publisher and subscription (their
        default callbacks warn about incompatible QoS or types). An in-process graph takes all
        its QoS from one contract, and the ~70 handlers make each wait about 15% dearer: the
        experiment turns them off.

    Yields
    ------
    (Context, SingleThreadedExecutor)
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.event_handler import EventHandler
    from rclpy.executors import SingleThreadedExecutor

    class WithoutQosEvents(SingleThreadedExecutor):
        """Never waits on (nor runs) QoS event handlers."""

        def can_execute(self, entity: Any) -> bool:
            return not isinstance(entity, EventHandler) and super().can_execute(entity)

    if discovery not in ('LOCALHOST', 'OFF'):
        raise ValueError(f"discovery must be 'LOCALHOST' or 'OFF', got {discovery!r}")
    # rcl reads the range from the environment at init; the process keeps what it had, so that
    # processes started later (a test's nodes, a launcher) do not inherit OFF.
    before = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = discovery
    ctx = Context()
    try:
        rclpy.init(context=ctx, domain_id=domain_id)
    finally:
        if discovery == 'OFF':
            if before is None:
                del os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']
            else:
                os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = before
    executor = (SingleThreadedExecutor if qos_events else WithoutQosEvents)(context=ctx)
    try:
        yield ctx, executor
    finally:
        executor.shutdown()
        rclpy.try_shutdown(context=ctx)


class CallbackTimer:
    """Accumulates the wall time of nodes' subscription and timer callbacks, per key.

    Wrapping keeps each callback's signature (``__wrapped__``), which rclpy inspects to decide
    whether a subscription callback also gets the message info.
    """

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self._nodes: list[tuple[str, Any]] = []
        self._seen: dict[int, int] = {}

    def watch(self, key: str, node: Any) -> None:
        """Time ``node``'s callbacks into ``totals[key]``, present ones and (after
        :meth:`refresh`) ones it creates later."""
        self.totals.setdefault(key, 0.0)
        self._nodes.append((key, node))
        self.refresh()

    def refresh(self) -> None:
        """Wrap the callbacks created since the last call (cheap when there are none)."""
        for key, node in self._nodes:
            subs, timers = list(node.subscriptions), list(node.timers)
            n = len(subs) + len(timers)
            if self._seen.get(id(node)) == n:
                continue
            self._seen[id(node)] = n
            for entity in subs + timers:
                if not getattr(entity.callback, '_timed', False):
                    entity.callback = self._wrap(key, entity.callback)

    def _wrap(self, key: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        totals, clock = self.totals, time.perf_counter

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[key] += clock() - t0
        timed._timed = True  # type: ignore[attr-defined]
        return timed


class InProcessGraph:
    """The calibration nodes created in ``context`` and added to ``executor``.

    Parameters
    ----------
    context : rclpy.context.Context
    executor : rclpy.executors.Executor
    parameters : mapping, optional
        Per-node overrides (keys of :data:`NODES`) merged over :func:`default_parameters`.
    record_path : Path or None
        Also run the MCAP recorder, writing every contract topic except the images and the right
        eye (not simulated here) to this file.
    time_callbacks : bool
        Accumulate callback wall time per node in :attr:`callback_seconds`.
    parameter_services : bool
        Start each node's parameter services (not needed in process; they cost discovery time).

    Raises
    ------
    RuntimeError
        If ``record_path`` is given but the recorder is not installed.
    """

    def __init__(self, context: Any, executor: Any, parameters: Mapping[str, Mapping[str, Any]] | None = None,
                 record_path: Path | None = None, time_callbacks: bool = False,
                 parameter_services: bool = False) -> None:
        from rclpy.parameter import Parameter

        from active_selector.selector_node import SelectorNode
        from dh_estimator.estimator_node import EstimatorNode
        from icub_sim_bridge.sim_node import SimNode
        from marker_detector.detector_node import DetectorNode

        self.context, self.executor = context, executor
        self.parameters = with_detector_eyes(merge_parameters(default_parameters(), parameters or {}))
        unknown = set(self.parameters) - set(NODES)
        if unknown:
            raise ValueError(f'parameters for unknown nodes {sorted(unknown)}; the graph has {list(NODES)}')
        self.nodes: dict[str, Any] = {}
        self.timer = CallbackTimer() if time_callbacks else None
        classes = {'sim': SimNode, 'detector': DetectorNode, 'estimator': EstimatorNode, 'selector': SelectorNode}
        try:
            for key in NODES:
                node = classes[key](context=context, start_parameter_services=parameter_services,
                                    parameter_overrides=[Parameter(k, value=v) for k, v in
                                                         self.parameters[key].items()])
                self._add(key, node)
                # rclpy keeps an override no node declared without a word: a misspelt --set
                # would run the experiment with the default instead.
                undeclared = sorted(k for k in self.parameters[key] if not node.has_parameter(k))
                if undeclared:
                    raise ValueError(f'{key} has no parameter {", ".join(undeclared)}')
            if record_path is not None:
                self._add('recorder', self._recorder(Path(record_path), parameter_services))
        except BaseException:
            self.close()
            raise

    def _recorder(self, path: Path, parameter_services: bool) -> Any:
        from rclpy.parameter import Parameter

        from calibration_interfaces.contract import CONTRACT, IMAGE_TOPICS

        try:
            from .recorder_node import RecorderNode
        except ImportError as exc:
            raise RuntimeError(f'recording asked for but calibration_bringup.recorder_node is missing ({exc})') from exc
        path.parent.mkdir(parents=True, exist_ok=True)
        topics = [t.name for t in CONTRACT if t.name not in IMAGE_TOPICS and not t.name.startswith('/camera/right/')]
        return RecorderNode(context=self.context, start_parameter_services=parameter_services, parameter_overrides=[
            Parameter('output', value=str(path)), Parameter('topics', value=topics),
            Parameter('use_sim_time', value=True)])   # log times on the sim clock, like the stamps

    def _add(self, key: str, node: Any, timed: bool = True) -> Any:
        self.nodes[key] = node
        if self.timer is not None and timed:
            self.timer.watch(key, node)
        self.executor.add_node(node)
        return node

    def add(self, key: str, node: Any, timed: bool = False) -> Any:
        """Add another node (a probe) to the executor; it is destroyed with the graph. Its
        callbacks are timed only if ``timed`` (a probe's work is usually the caller's, not the graph's)."""
        if key in self.nodes:
            raise ValueError(f'the graph already has a node {key!r}')
        return self._add(key, node, timed)

    @property
    def sim(self) -> Any:
        return self.nodes['sim']

    @property
    def estimator(self) -> Any:
        return self.nodes['estimator']

    @property
    def selector(self) -> Any:
        return self.nodes['selector']

    @property
    def recorder(self) -> Any | None:
        return self.nodes.get('recorder')

    @property
    def callback_seconds(self) -> dict[str, float]:
        """Wall seconds in each node's callbacks so far (empty unless ``time_callbacks``)."""
        return dict(self.timer.totals) if self.timer is not None else {}

    def spin_once(self, timeout_sec: float = 0.01) -> None:
        """Execute at most one callback."""
        self.executor.spin_once(timeout_sec=timeout_sec)
        if self.timer is not None:
            self.timer.refresh()

    def spin_until(self, predicate: Callable[[], bool], timeout: float, what: str = 'condition') -> None:
        """Spin until ``predicate()`` holds.

        Raises
        ------
        GraphTimeout
            After ``timeout`` wall seconds, naming ``what`` and the selector's phase.
        """
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise GraphTimeout(f'{what} not reached within {timeout:.0f} s '
                                   f'(selector phase: {self.selector.phase.value})')
            self.spin_once()

    def wait_for_recorder(self, topic: str, count: int, timeout: float = 5.0) -> bool:
        """Spin until the recorder has written ``count`` messages of ``topic``; whether it has."""
        rec, deadline = self.recorder, time.monotonic() + timeout
        while rec is not None and rec.counts.get(topic, 0) < count and time.monotonic() < deadline:
            self.spin_once()
        return rec is None or rec.counts.get(topic, 0) >= count

    def close(self) -> None:
        """Close the recorder's file, remove and destroy every node (idempotent)."""
        rec = self.nodes.get('recorder')
        if rec is not None:
            rec.close()
        for node in self.nodes.values():
            self.executor.remove_node(node)
            node.destroy_node()
        self.nodes.clear()

    def __enter__(self) -> 'InProcessGraph':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
