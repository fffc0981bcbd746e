"""What the experiment's Ray tasks need from the nodes they run on, and stopping early when a node lacks it.

A Ray worker inherits the environment of the ``ray start`` that started its node, not the
driver's: on a node started from the venv with nothing exported, ``AMENT_PREFIX_PATH`` is unset
and every recorded run failed at its first message definition. So the driver hands every task
the environment its runs read (:func:`task_options`: ``runtime_env={'env_vars': ...}``, a Ray
built-in that installs nothing), the values as the driver has them (:func:`run_environment`).

Before the first run the driver runs :func:`check_node` on every node that has a CPU
(:func:`check_nodes`): it imports what a run imports and, when runs are recorded, finds the
message definitions through the ament index, as a run does, and describes its numeric environment
(:mod:`calibration_interfaces.provenance`; the experiment records it). A node that fails stops the
experiment with one :class:`NodeEnvironmentError` naming the node and the cause (a node started
from a Python without this workspace: ``ModuleNotFoundError: No module named
'calibration_bringup'``). During the runs, :class:`FailFast` stops it when :data:`FAIL_FAST_RUNS`
runs failed on one node for the same environmental cause (:func:`environmental_cause`: an import
error, a missing package, file or variable), instead of queueing every remaining run into the same
failure; a run's own failure (a stuck loop, a crashed node of the graph) never stops the others.
"""
from __future__ import annotations

import importlib
import os
import re
import socket
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from calibration_interfaces.provenance import ENVIRONMENT_VARIABLES, numeric_environment

#: Environment variables a run reads, handed from the driver to every task when set there: the
#: ament index (the recorder's message definitions, the parameter files) and the middleware's
#: choice and profile. ROS_DOMAIN_ID and the discovery range are set per run (graph.ros_session).
#: And the variables that choose the numeric kernels (provenance.ENVIRONMENT_VARIABLES): pinned on
#: the driver, pinned on every node.
RUN_ENV_VARS: tuple[str, ...] = ('AMENT_PREFIX_PATH', 'RMW_IMPLEMENTATION', 'FASTRTPS_DEFAULT_PROFILES_FILE',
                                 'FASTDDS_DEFAULT_PROFILES_FILE', *ENVIRONMENT_VARIABLES)

#: Modules a run imports on its node (graph.InProcessGraph's nodes; rclpy and the ROS messages
#: with them); the recorder's is added when runs are recorded.
RUN_MODULES: tuple[str, ...] = ('calibration_bringup.graph', 'icub_sim_bridge.sim_node',
                                'marker_detector.detector_node', 'dh_estimator.estimator_node',
                                'active_selector.selector_node')
RECORDER_MODULE = 'calibration_bringup.recorder_node'

#: Runs failed on one node for one environmental cause before the experiment stops.
FAIL_FAST_RUNS = 3

#: Exception types (by name: a run's error arrives as ``'Type: message'``) that say the node lacks
#: something every run needs, not that one run went wrong. Not TimeoutError (an OSError too): the
#: graph's own deadlines raise it.
ENVIRONMENTAL_ERRORS = frozenset({
    'ImportError', 'ModuleNotFoundError', 'OSError', 'FileNotFoundError', 'PermissionError',
    'PackageNotFoundError', 'DefinitionNotFoundError', 'RuntimeEnvSetupError'})

#: Seconds the driver waits for every node's check before it goes ahead without the silent ones.
CHECK_TIMEOUT = 60.0

_ERROR_LINE = re.compile(r'^([A-Za-z_][\w.]*(?:Error|Exception)): (.*)$')

_HINT = ('every node needs this workspace installed at the same path (make setup) and `ray start` run '
         'from its .venv (README: Running the experiment, Execution (Ray))')


def is_ament_prefix(prefix: str | os.PathLike[str]) -> bool:
    """Whether ``prefix`` holds this workspace's ament index (``make setup``'s venv does)."""
    return (Path(prefix) / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'calibration_bringup').is_file()


def run_environment(environ: Mapping[str, str] | None = None, prefix: str | None = None) -> dict[str, str]:
    """The environment variables of :data:`RUN_ENV_VARS` the driver hands every task.

    Parameters
    ----------
    environ : mapping, optional
        The driver's environment (default ``os.environ``).
    prefix : str, optional
        The driver's Python prefix (default ``sys.prefix``): the ament prefix when
        ``AMENT_PREFIX_PATH`` is unset and it holds the workspace (the venv run directly).

    Returns
    -------
    dict
        Name -> value, only the variables set (non-empty) in ``environ``.
    """
    environ = os.environ if environ is None else environ
    prefix = sys.prefix if prefix is None else prefix
    env = {k: environ[k] for k in RUN_ENV_VARS if environ.get(k)}
    if 'AMENT_PREFIX_PATH' not in env and is_ament_prefix(prefix):
        env['AMENT_PREFIX_PATH'] = str(prefix)
    return env


def task_options() -> dict[str, Any]:
    """Ray task options that carry :func:`run_environment` to every node."""
    return {'runtime_env': {'env_vars': run_environment()}}


@dataclass(frozen=True)
class NodeInfo:
    """A node that passed :func:`check_node`: ``numeric`` its numeric environment as a run there
    sees it (:func:`calibration_interfaces.provenance.numeric_environment`)."""

    node_id: str
    host: str
    python: str
    numeric: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class NodeProblem:
    """Why runs cannot run (or keep failing) on a node: ``host`` its host name (and address),
    ``cause`` ``'Type: message'``."""

    node_id: str
    host: str
    cause: str

    def describe(self) -> str:
        where = f'node {self.node_id}' if self.node_id else 'a node the driver cannot name'
        return f'{where}{f" ({self.host})" if self.host else ""}: {self.cause}'


class NodeEnvironmentError(RuntimeError):
    """Runs cannot run on some node: its environment lacks what they need (names nodes and causes)."""

    def __init__(self, problems: Sequence[NodeProblem], runs: int = 0) -> None:
        self.problems = tuple(problems)
        self.runs = runs
        lead = (f'{runs} runs failed for the same cause on one node; stopped' if runs else
                f'{len(self.problems)} Ray node(s) cannot run the experiment; no run was started')
        super().__init__(lead + ':\n  ' + '\n  '.join(p.describe() for p in self.problems) + f'\n{_HINT}')


def root_cause(exc: BaseException) -> str:
    """``'Type: message'`` (first line) of what made a Ray task fail, unwrapped from Ray's errors.

    A task whose function or arguments cannot be unpickled on its worker (the module is not
    importable there) arrives as ``RayTaskError`` around a ``RaySystemError`` or around Ray's
    ``RuntimeError('The remote function failed to import on the worker ...')`` whose text ends
    with the original traceback; its last error line is the cause.
    """
    from ray.exceptions import RaySystemError, RayTaskError

    for _ in range(10):     # a few wrappers deep at most
        inner = (exc.cause if isinstance(exc, RayTaskError) else
                 exc.client_exc if isinstance(exc, RaySystemError) else None)
        if not isinstance(inner, BaseException) or inner is exc:
            break
        exc = inner
    text = str(exc)
    if 'failed to import on the worker' in text:
        found = [m for m in map(_ERROR_LINE.match, text.splitlines()) if m]
        if found:
            return f'{found[-1].group(1).rsplit(".", 1)[-1]}: {found[-1].group(2)}'
    first = text.strip().splitlines()[0] if text.strip() else ''
    return f'{type(exc).__name__}: {first}'


def environmental_cause(error: str | None) -> str | None:
    """The cause (first line) if ``error`` (``'Type: message'``) is environmental, else None."""
    if not error:
        return None
    line = error.strip().splitlines()[0]
    name = line.split(':', 1)[0].strip().rsplit('.', 1)[-1]
    return line if name in ENVIRONMENTAL_ERRORS else None


class FailFast:
    """Counts runs' environmental failures per (node, cause); says when to stop.

    Parameters
    ----------
    limit : int
        Failures of one node for one cause that stop the experiment (:data:`FAIL_FAST_RUNS`).
    """

    def __init__(self, limit: int = FAIL_FAST_RUNS) -> None:
        if limit < 1:
            raise ValueError(f'limit must be >= 1, got {limit}')
        self.limit = limit
        self._counts: Counter[tuple[str, str]] = Counter()
        self._hosts: dict[str, str] = {}

    def record(self, node_id: str, host: str, error: str | None) -> NodeEnvironmentError | None:
        """Count a failed run's ``error`` (``'Type: message'``; ``node_id`` '' if unknown).

        Returns
        -------
        NodeEnvironmentError or None
            The error to stop with once ``limit`` runs failed on ``node_id`` for this cause.
        """
        cause = environmental_cause(error)
        if cause is None:
            return None
        key = (node_id, cause)
        self._counts[key] += 1
        self._hosts[node_id] = host or self._hosts.get(node_id, '')
        if self._counts[key] < self.limit:
            return None
        return NodeEnvironmentError([NodeProblem(node_id, self._hosts[node_id], cause)], runs=self._counts[key])


def check_node(record: bool) -> NodeInfo:
    """On a node (as a Ray task): import what a run imports; with ``record``, find every contract
    type's message definition and the recorded ``/tf`` type's through the ament index, as the
    recorder does; and describe the node's numeric environment (the kernels its runs compute with).
    Raises what a run would raise there (``node_id`` '' outside Ray)."""
    import ray

    for name in RUN_MODULES + ((RECORDER_MODULE,) if record else ()):
        importlib.import_module(name)
    if record:
        from calibration_interfaces.contract import CONTRACT

        from .mcap_writer import schema_for
        from .tf_recording import TF_TYPE

        for type_name in sorted({t.type for t in CONTRACT} | {TF_TYPE}):
            schema_for(type_name)
    node_id = ray.get_runtime_context().get_node_id() if ray.is_initialized() else ''
    return NodeInfo(node_id, socket.gethostname(), sys.executable, numeric_environment())


def check_nodes(record: bool, options: Mapping[str, Any], timeout: float = CHECK_TIMEOUT
                ) -> tuple[list[NodeInfo], list[str]]:
    """Run :func:`check_node` on every alive node with a CPU, with the runs' task ``options``.

    Returns
    -------
    (nodes, silent) : list of NodeInfo, list of str
        The nodes that passed; the ids of those that did not answer within ``timeout`` s (a
        worker that cannot start: their runs go ahead, :class:`FailFast` watches them).

    Raises
    ------
    NodeEnvironmentError
        At the first failed check, naming each node whose check had failed by then and why (the
        checks still running are cancelled).
    """
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    nodes = [n for n in ray.nodes() if n.get('Alive') and n.get('Resources', {}).get('CPU', 0) >= 1]
    # No CPU asked: the check must not queue behind other jobs' tasks.
    task = ray.remote(num_cpus=0, max_retries=0)(check_node)
    refs = {task.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n['NodeID'], soft=False),
                         **options).remote(record): n for n in nodes}
    passed: list[NodeInfo] = []
    problems: list[NodeProblem] = []
    pending, deadline = list(refs), time.monotonic() + timeout
    # A broken node fails within seconds, while a sound one is still importing: report at the first
    # failure (with any other that has failed by then), not after every node answered.
    while pending and not problems and time.monotonic() < deadline:
        ready, pending = ray.wait(pending, num_returns=1, timeout=max(0.0, deadline - time.monotonic()))
        if ready and len(pending):
            more, pending = ray.wait(pending, num_returns=len(pending), timeout=0)
            ready += more
        for ref in ready:
            try:
                passed.append(ray.get(ref))
            except ray.exceptions.RayError as exc:
                node = refs[ref]
                where = ', '.join(filter(None, (node.get('NodeManagerHostname'), node.get('NodeManagerAddress'))))
                problems.append(NodeProblem(node['NodeID'], where, root_cause(exc)))
    for ref in pending:
        ray.cancel(ref, force=True)
    if problems:
        raise NodeEnvironmentError(problems)
    return passed, [refs[r]['NodeID'] for r in pending]


__all__ = ['RUN_ENV_VARS', 'RUN_MODULES', 'FAIL_FAST_RUNS', 'ENVIRONMENTAL_ERRORS', 'CHECK_TIMEOUT', 'NodeInfo',
           'NodeProblem', 'NodeEnvironmentError', 'FailFast', 'is_ament_prefix', 'run_environment',
           'task_options', 'root_cause', 'environmental_cause', 'check_node', 'check_nodes']
