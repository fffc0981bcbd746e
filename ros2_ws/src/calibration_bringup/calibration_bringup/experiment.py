"""The paper's experiment on the real node graph: methods x repetitions x iterations, fanned out with Ray.

Usage::

    python -m calibration_bringup.experiment                  # ours: 7 methods x 50 repetitions x 50 iterations
    python -m calibration_bringup.experiment --system paper   # the paper's system, same seeds and robots
    python -m calibration_bringup.experiment --quick          # 7 methods x 3 repetitions x 20 iterations
    python -m calibration_bringup.experiment --methods AL CCSAL --repetitions 3 --iterations 10
    python -m calibration_bringup.experiment --address HEAD:6379 --jobs 16  # on a running Ray cluster
    python -m calibration_bringup.experiment_figures results/experiment-ours     # re-plot only

Methods (docs/architecture.md section 5): ``R``, ``AL``, ``UCSAL``, ``CCSAL`` with the pose-dependent noise
model, and ``AL-CN``, ``UCSAL-CN``, ``CCSAL-CN`` with the constant one (selector and estimator
both use the CN covariance; the detector keeps publishing pose-dependent covariances, which the
estimator then ignores).

Systems (:data:`SYSTEMS`): ``ours`` is the nodes' parameter files as they are; ``paper`` overrides
them with the paper's system (EKF with one linearisation, the cost ``C0 / eta``, a-optimality, the
occlusion model learned from a flat prior, DIRECT-L with 1000 evaluations, repeated configurations
allowed). Both draw the same robots and guesses from the same seeds.

Seeds: repetition ``r`` has the seed ``s = seed_base + r``; :func:`derive_seeds` spawns three
independent seeds from it (``numpy.random.SeedSequence(s).spawn(3)``) for the real robot
(``perturb_seed``), the estimator's initial guess (``initial_seed``) and the selector (``seed``).
Every method of a repetition shares all three; they are recorded in each run's CSV and in
``config.json``.

Execution: one Ray task per run (``num_cpus=1``), at most ``--jobs`` in flight. Without
``--address`` the command starts a local Ray runtime of ``--jobs`` CPUs for its own use;
``--address host:6379`` or ``--address ray://host:10001`` submits to an existing cluster whose nodes
have this workspace installed; the tasks carry the environment their runs read, every node is
checked first and runs failing on one node for one environmental cause stop the driver
(:mod:`calibration_bringup.cluster`). Each task runs one fresh graph (SimNode, DetectorNode,
EstimatorNode, SelectorNode, optionally the MCAP recorder, and a probe) on a
SingleThreadedExecutor with its own ``Context`` and a ``ROS_DOMAIN_ID`` that the driver leases
to it from a pool of ``--jobs`` ids, so no two runs in flight share one on any node. After every
``/calibration/progress`` record the probe scores the estimator's current table with
:class:`body_schema.metrics.PoseErrorEvaluator` against the simulator's true table (row 0 is the
initial guess). The task returns its rows, its log and (``--record``) its MCAP bytes; the driver
writes ``<output>/runs/<method>/rep<NN>.log`` and ``.mcap``, then the CSV ``rep<NN>.csv``
atomically, last: a run whose CSV exists is finished and skipped on restart, a run interrupted
or failed leaves none. With ``--shared-output PATH`` (a path every node sees) the tasks write
their logs and MCAPs there themselves. Ctrl-C cancels the runs in flight (their workers are
killed) and writes nothing more. At the end all runs are combined into ``<output>/metrics.csv``
and :mod:`calibration_bringup.experiment_figures` draws the figures and writes ``<output>/summary.md``.

Resume checks settings: ``config.json`` records, per method, everything that changes a run's
results (:func:`run_settings`: every node parameter but the seeds, iterations, seed base,
system) and its hash; every CSV row carries that hash. Resuming with other settings is refused
with the differing keys named; ``--force-new`` moves the old results aside and starts over.

Time accounting per iteration (CSV columns, wall seconds unless named ``_sim_``): ``selection_s``
(the selector's search), ``move_sim_s`` (the simulated move), ``sim_s`` (simulator
callbacks: physics, rendering, publishing), ``render_s`` (rendering alone), ``detect_s``
(detector callbacks), ``estimator_s`` (estimator callbacks, the update among them),
``selector_s`` (selector callbacks, the selection among them), ``recorder_s``, ``cpu_s`` (CPU
time of the whole process: on a shared machine, what the iteration costs with a core of its own)
and ``wall_s`` (everything, the executor's own work included).
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import json
import logging
import os
import socket
import sys
import tempfile
import time
import traceback
from collections import deque
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence, TextIO

import numpy as np

from calibration_interfaces.provenance import distinct_environments, environment_differences

from . import cluster
from .graph import (NODES, InProcessGraph, default_parameters, merge_parameters, recorder_available, ros_session,
                    with_detector_eyes)
from .run_check import observations_used
from .systems import SYSTEMS

__all__ = ['METHODS', 'SYSTEMS', 'COLUMNS', 'Method', 'Seeds', 'RunSpec', 'GraphSettings', 'ExperimentConfig',
           'RunError', 'RunResult', 'ExperimentOutcome', 'derive_seeds', 'plan_runs', 'node_parameters',
           'run_settings', 'settings_hash', 'settings_difference', 'is_finished', 'run_graph', 'execute_run',
           'parse_override', 'run_cautions',
           'write_rows', 'read_rows', 'read_environments', 'combine_runs', 'domain_ids', 'run_experiment', 'main']


@dataclass(frozen=True)
class Method:
    """One compared method: a selector strategy and a noise model."""

    name: str
    strategy: str
    constant_noise: bool = False


METHODS: dict[str, Method] = {m.name: m for m in (
    Method('R', 'random'), Method('AL', 'al'), Method('UCSAL', 'ucsal'), Method('CCSAL', 'ccsal'),
    Method('AL-CN', 'al', True), Method('UCSAL-CN', 'ucsal', True), Method('CCSAL-CN', 'ccsal', True))}

#: Columns of every run's CSV and of the combined ``metrics.csv``.
COLUMNS: tuple[str, ...] = (
    'method', 'repetition', 'seed', 'robot_seed', 'guess_seed', 'selector_seed', 'iteration', 'outcome',
    'detected', 'position_mm', 'orientation_deg', 'movement_deg', 'discarded', 'selection_s', 'move_sim_s',
    'sim_s', 'render_s', 'detect_s', 'estimator_s', 'selector_s', 'recorder_s', 'cpu_s', 'wall_s',
    'settings_hash')

#: Callback time accounting: CSV column -> node attribute of the graph.
_NODE_COLUMNS = {'sim_s': 'sim', 'detect_s': 'detector', 'estimator_s': 'estimator',
                 'selector_s': 'selector', 'recorder_s': 'recorder'}

#: The node parameters that take a run's seeds (the rest of the parameters are its settings).
_SEED_PARAMETERS = (('sim', 'perturb_seed'), ('estimator', 'initial_seed'), ('selector', 'seed'))

#: Exclusive upper bound of the nodes' seed parameters (declared range 0 .. 2**31 - 1).
SEED_MODULUS = 2**31 - 1


class RunError(RuntimeError):
    """A run that could not finish (stuck loop, crashed node)."""


@dataclass(frozen=True)
class GraphSettings:
    """Simulator settings of experiment runs, chosen by measurement: for the same seed they leave
    every iteration's outcome, error and movement as they were (the arm is kinematic and the
    images noise-free, so what the camera sees at rest does not depend on when it looks); only
    the time differs. Checked on 7 methods x seeds 0-3 x 50 iterations (before the Ray runner)
    against 30 deg/s and 2.5 Hz: every CSV field but the timings identical, except one run from
    its iteration 49 (UCSAL, seed 2; final error 1.32 -> 1.35 mm), through the selector's change
    below, not these settings. There an iteration ended on the previous iteration's verdict (its
    target lay within the settle tolerance of the previous one, and the loop takes any verdict at
    the reached configuration) and the next target used to be chosen on the selector's next 50 ms
    wall-clock step, with whatever estimate had arrived by then: that depends on how far the
    simulator ran in those 50 ms, i.e. on load (two runs of main's own code, UCSAL seed 0, part
    from iteration 18). The selector now chooses on the next joint state: three concurrent runs
    gave identical rows.

    Wall seconds per iteration, one worker, two seeds, 50 iterations, on the shared 2-core machine,
    R / AL / UCSAL / CCSAL: 0.164 / 0.288 / 0.205 / 0.148 with 30 deg/s, 2.5 Hz, a render per
    frame and selection on the selector's 50 ms step; 0.027 / 0.064 / 0.065 / 0.061 now (AL:
    selection 0.027, simulator 0.014 of which rendering 0.011, MAP update 0.008, detection 0.003,
    executor 0.008). The selector choosing on the first joint state after an iteration, one
    render per resting arm (``SimWorld.render``) and an executor that does not wait on the QoS
    event handlers (``ros_session(qos_events=False)``) are part of it.

    Attributes
    ----------
    image_rate : float
        Camera rate [Hz, sim time]. An iteration (the attempt frame's detection, the estimator's
        verdict, the next selection and command, a one- or two-step move, settling and the
        selector's 0.1 s ``settle_time``) takes about 12 physics steps of 0.02 s, so it ends one
        frame after the previous one at 4 Hz (0.25 s of sim time, one render); at 5 Hz it needs two
        frames (0.40 s), at 10 Hz three (0.30 s), at 20 Hz five (0.25 s, five detections). CPU s per
        iteration, R / AL (3600 deg/s, load 8-10, +-20%): 4 Hz 0.032 / 0.055, 3.3 Hz
        0.031 / 0.058, 5 Hz 0.039 / 0.065, 10 Hz 0.054 / 0.081, 20 Hz 0.049 / 0.070.
    physics_step : float
        Physics step [s]; the arm is kinematic (placed, not simulated), so one step per
        joint-state period suffices: 0.24 -> 0.21 s per AL iteration at 10 Hz.
    max_joint_speed_deg : float
        Joint speed limit [deg/s]. The metrics count degrees, not seconds, and the arm is
        kinematic: at 3600 deg/s any move in the calibration box takes one or two physics steps
        (at the simulator's 30 deg/s, 0.5-2 s of sim time: 25-100 steps, each a joint state and a
        clock message to every node). 360 deg/s left 0.2 s per move.
    image_width, image_height : int
        Camera resolution (the iCub simulator's 320 x 240 by default).
    run_timeout : float
        Wall seconds a run may take per iteration before it is declared stuck (plus one minute).
    """

    image_rate: float = 4.0
    physics_step: float = 0.02
    max_joint_speed_deg: float = 3600.0
    image_width: int = 320
    image_height: int = 240
    run_timeout: float = 30.0


@dataclass(frozen=True)
class Seeds:
    """The independent seeds of one repetition (each in ``0 .. SEED_MODULUS - 1``)."""

    robot: int
    guess: int
    selector: int


def derive_seeds(seed: int) -> Seeds:
    """Independent seeds of the real robot, the initial guess and the selector from one repetition seed.

    ``numpy.random.SeedSequence(seed).spawn(3)``, each child's first 32-bit word modulo
    :data:`SEED_MODULUS` (the nodes' seed parameters are 31-bit).

    Raises
    ------
    ValueError
        If ``seed`` is negative.
    """
    if seed < 0:
        raise ValueError(f'repetition seed must be >= 0, got {seed}')
    robot, guess, selector = (int(c.generate_state(1)[0]) % SEED_MODULUS
                              for c in np.random.SeedSequence(seed).spawn(3))
    return Seeds(robot, guess, selector)


@dataclass(frozen=True)
class RunSpec:
    """One run: a method on one repetition (true robot + initial guess, from the repetition's seed)."""

    method: str
    repetition: int
    seed: int
    iterations: int

    @property
    def seeds(self) -> Seeds:
        return derive_seeds(self.seed)

    @property
    def stem(self) -> str:
        return f'runs/{self.method}/rep{self.repetition:02d}'

    def path(self, root: Path | str, suffix: str) -> Path:
        """``<root>/runs/<method>/rep<NN><suffix>``."""
        return Path(root) / f'{self.stem}{suffix}'

    @property
    def label(self) -> str:
        return f'{self.method} rep {self.repetition} (seed {self.seed})'


def _default_output(system: str, quick: bool = False) -> Path:
    return Path(f'results/experiment-{system}{"-quick" if quick else ""}')


@dataclass(frozen=True)
class ExperimentConfig:
    """What to run, with which system, where (the CLI's options).

    ``address`` None starts a local Ray runtime of ``jobs`` CPUs; otherwise ``ray.init``'s address
    (``auto``, ``ray://host:10001``, ``host:6379``). ``shared``: ``output`` is visible at the same
    path on every node (the tasks write logs and MCAPs there). ``force_new``: move earlier results
    in ``output`` aside instead of resuming them. ``combine``: write ``metrics.csv`` (and with
    ``figures`` the summary and figures) from this configuration's runs at the end; off when another
    command shares the directory's runs (the ablation) and must not replace its combined files.
    """

    repetitions: int = 50
    iterations: int = 50
    methods: tuple[str, ...] = tuple(METHODS)
    system: str = 'ours'
    jobs: int = 2
    output: Path = _default_output('ours')
    seed_base: int = 0
    record: bool = True
    domain_base: int | None = None
    figures: bool = True
    graph: GraphSettings = field(default_factory=GraphSettings)
    address: str | None = None
    shared: bool = False
    force_new: bool = False
    overrides: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    combine: bool = True

    def __post_init__(self) -> None:
        bad_nodes = sorted(set(self.overrides) - set(NODES))
        if bad_nodes:
            raise ValueError(f'overrides for unknown nodes {bad_nodes}; expected any of {list(NODES)}')
        bad = [m for m in self.methods if m not in METHODS]
        if bad:
            raise ValueError(f'unknown methods {bad}; expected any of {list(METHODS)}')
        if not self.methods:
            raise ValueError('methods must not be empty')
        if self.system not in SYSTEMS:
            raise ValueError(f'unknown system {self.system!r}; expected one of {list(SYSTEMS)}')
        for name in ('repetitions', 'iterations', 'jobs'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
        if self.seed_base < 0:
            raise ValueError(f'seed_base must be >= 0, got {self.seed_base}')
        if self.domain_base is not None and not 0 <= self.domain_base <= 232 - self.jobs + 1:
            raise ValueError(f'domain_base must be in [0, {232 - self.jobs + 1}] for {self.jobs} jobs, '
                             f'got {self.domain_base}')


def plan_runs(config: ExperimentConfig) -> list[RunSpec]:
    """Every run of the experiment, repetition-major (all methods of repetition 0 first).

    Repetition-major order means an interrupted experiment still holds complete repetitions, which
    compare methods fairly.
    """
    return [RunSpec(m, r, config.seed_base + r, config.iterations)
            for r in range(config.repetitions) for m in config.methods]


def node_parameters(spec: RunSpec, settings: GraphSettings = GraphSettings(), system: str = 'ours',
                    overrides: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, dict[str, Any]]:
    """Parameter overrides of each node for ``spec`` on ``system`` (pure; the graph applies them).

    Layers, later winning: the nodes' parameter files, :data:`SYSTEMS` ``[system]``, ``overrides``
    (the CLI's ``--set``, an ablation step), the run's graph settings, seeds and method.

    Returns
    -------
    dict
        ``{'sim': {...}, 'detector': {...}, 'estimator': {...}, 'selector': {...}}``.
    """
    method = METHODS[spec.method]
    seeds = spec.seeds
    noise = {'noise_model': 'constant'} if method.constant_noise else {}
    # with_detector_eyes: the simulator renders the eyes the detector reads, and the settings say so.
    return with_detector_eyes(merge_parameters(default_parameters(), SYSTEMS[system], overrides or {}, {
        'sim': {'perturb_seed': seeds.robot, 'image_rate': settings.image_rate,
                'physics_step': settings.physics_step, 'max_joint_speed_deg': settings.max_joint_speed_deg,
                'image_width': settings.image_width, 'image_height': settings.image_height},
        'estimator': {'initial_seed': seeds.guess, **noise},
        # The selector times its commands with the simulator's speed limit (else a move would take
        # the parameter file's 30 deg/s of sim time: 25-100 physics steps instead of one or two).
        'selector': {'strategy': method.strategy, 'iterations': spec.iterations, 'seed': seeds.selector,
                     'max_joint_speed_deg': settings.max_joint_speed_deg, **noise},
    }))


# ------------------------------------------------------------------------------------------
# Settings: what a run's results depend on besides its seeds

def run_settings(config: ExperimentConfig, method: str) -> dict[str, Any]:
    """Everything that changes the results of ``method``'s runs in ``config`` except the
    per-repetition seeds (which follow from ``seed_base``), flattened to ``node.parameter`` keys.

    The repetition count, the method list, ``jobs``, recording and where the runs execute are
    not in it: they change which runs exist or how fast, not what a run computes. Nor is the
    system's name: its parameters are, so a system and the same parameters reached another way
    (an ablation step, ``--set``) share finished runs.
    """
    params = node_parameters(RunSpec(method, 0, config.seed_base, config.iterations), config.graph, config.system,
                             config.overrides)
    for node, name in _SEED_PARAMETERS:
        params[node].pop(name)
    flat: dict[str, Any] = {'seed_base': config.seed_base,
                            'iterations': config.iterations, 'seeding': 'SeedSequence.spawn(3)'}
    for node, values in sorted(params.items()):
        flat.update({f'{node}.{k}': v for k, v in sorted(values.items())})
    return flat


def settings_hash(settings: Mapping[str, Any]) -> str:
    """A short stable hash of ``settings`` (SHA-256 of its sorted JSON, 16 hex digits)."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def settings_difference(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """``key: old -> new`` for every key whose value differs (``<unset>`` where one side lacks it)."""
    missing = '<unset>'
    return [f'{k}: {old.get(k, missing)!r} -> {new.get(k, missing)!r}'
            for k in sorted(set(old) | set(new)) if old.get(k, missing) != new.get(k, missing)]


# ------------------------------------------------------------------------------------------
# One run: the graph in this process

def run_graph(spec: RunSpec, domain_id: int, settings: GraphSettings = GraphSettings(),
              record_path: Path | None = None, system: str = 'ours',
              overrides: Mapping[str, Mapping[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Run ``spec`` on a fresh in-process graph and return its rows (iteration 0 = initial guess).

    Parameters
    ----------
    spec : RunSpec
    domain_id : int
        ROS_DOMAIN_ID of this graph (distinct from any other graph running at the same time).
    settings : GraphSettings
    record_path : Path or None
        Record the non-image topics to this MCAP file.
    system : str
        A key of :data:`SYSTEMS`.
    overrides : mapping, optional
        Per-node parameters over the system's (:func:`node_parameters`).

    Raises
    ------
    RunError
        If the selector has not finished ``spec.iterations`` iterations within the deadline.
    """
    from rclpy.node import Node
    from std_msgs.msg import String

    from body_schema.metrics import PoseErrorEvaluator

    rows: list[dict[str, Any]] = []
    # The whole graph lives in this process: discovery OFF keeps another run (or a test) that
    # drew the same domain id on this machine from mixing its messages into this one's.
    with ros_session(domain_id, qos_events=False, discovery='OFF') as (ctx, executor):
        try:
            graph = InProcessGraph(ctx, executor, node_parameters(spec, settings, system, overrides), record_path,
                                   time_callbacks=True)
        except RuntimeError as exc:     # the recorder asked for but missing
            raise RunError(f'{exc}; use --no-record') from exc
        with graph:
            sim, est, sel = graph.sim, graph.estimator, graph.selector
            evaluate = PoseErrorEvaluator(sim.robot.base, sim.true_dh, sim.robot.calibration_box)

            def totals() -> dict[str, float]:
                return {**graph.callback_seconds, 'render': sim.world.render_seconds}

            seeds = spec.seeds
            base = {'method': spec.method, 'repetition': spec.repetition, 'seed': spec.seed,
                    'robot_seed': seeds.robot, 'guess_seed': seeds.guess, 'selector_seed': seeds.selector}
            e0 = evaluate(est.estimator.dh)
            rows.append({**base, 'iteration': 0, 'outcome': 'initial', 'detected': '',
                         'position_mm': e0.position_mm, 'orientation_deg': e0.orientation_deg,
                         'movement_deg': 0.0, 'discarded': 0, 'selection_s': 0.0, 'move_sim_s': 0.0,
                         **{c: 0.0 for c in ('render_s', 'cpu_s', 'wall_s', *_NODE_COLUMNS)}})
            last = {'wall': time.perf_counter(), 'cpu': time.process_time(), **totals()}
            tables: list[np.ndarray] = []
            foreign: list[int] = []

            def on_progress(msg: String) -> None:
                rec = json.loads(msg.data)
                if int(rec['iteration']) != len(rows):
                    # Records come in order, one per iteration: anything else is another graph's.
                    foreign.append(int(rec['iteration']))
                    return
                now, cpu = time.perf_counter(), time.process_time()
                tables.append(est.estimator.dh.copy())
                row = {**base, 'iteration': int(rec['iteration']), 'outcome': rec['outcome'],
                       'detected': bool(rec['detected']), 'movement_deg': float(rec['movement_deg']),
                       'discarded': int(rec['discarded']), 'selection_s': float(rec['selection_s']),
                       'move_sim_s': float(rec['move_sim_s']), 'cpu_s': cpu - last['cpu'],
                       'wall_s': now - last['wall']}
                current = totals()
                for col, key in (*_NODE_COLUMNS.items(), ('render_s', 'render')):
                    total = current.get(key, 0.0)
                    row[col] = total - last.get(key, 0.0)
                    last[key] = total
                last['wall'], last['cpu'] = now, cpu
                rows.append(row)

            probe = graph.add('probe', Node('experiment_probe', context=ctx, start_parameter_services=False))
            probe.create_subscription(String, '/calibration/progress', on_progress, 100)

            limit = 60.0 + settings.run_timeout * spec.iterations
            deadline = time.monotonic() + limit
            while len(rows) <= spec.iterations:
                n = len(rows)
                graph.spin_once(timeout_sec=0.05)
                if not ctx.ok():
                    raise KeyboardInterrupt    # rclpy's signal handler shut the context down
                if foreign:
                    raise RunError(f'{spec.label}: progress record for iteration {foreign[0]} while expecting '
                                   f'{len(rows)}: another graph on ROS_DOMAIN_ID {domain_id}?')
                if len(rows) > n:
                    # Scored after the fact so the loop pays nothing; the table is the one current
                    # when the record arrived.
                    err = evaluate(tables[-1])
                    rows[-1]['position_mm'], rows[-1]['orientation_deg'] = err.position_mm, err.orientation_deg
                if time.monotonic() > deadline:
                    raise RunError(f'{spec.label}: only {len(rows) - 1} of {spec.iterations} iterations '
                                   f'within {limit:.0f} s '
                                   f'(selector phase: {sel.phase.value})')
            # The bag is complete once it holds the last progress record too.
            graph.wait_for_recorder('/calibration/progress', spec.iterations)
    return rows


@dataclass
class RunResult:
    """What a run's task returns to the driver.

    Attributes
    ----------
    spec : RunSpec
    rows : list of dict or None
        The run's rows; None if it failed.
    error : str or None
        Why it failed (exception type and message; the traceback is in the log).
    log, mcap : bytes or None
        The run's output and recording, when the driver writes them (not with a shared output).
    node_id, host : str
        The Ray node and host the run executed on ('' outside Ray).
    domain_id : int
    wall_s : float
        Wall time of the whole task.
    """

    spec: RunSpec
    rows: list[dict[str, Any]] | None
    error: str | None
    log: bytes | None
    mcap: bytes | None
    node_id: str
    host: str
    domain_id: int
    wall_s: float


@contextmanager
def _output_to(path: Path) -> Iterator[None]:
    """Append this process's stdout and stderr (file descriptors 1 and 2: rcutils logs and
    PyBullet's C prints included) to ``path``."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with path.open('a') as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)


def _node_id() -> str:
    import ray

    return ray.get_runtime_context().get_node_id() if ray.is_initialized() else ''


def execute_run(spec: RunSpec, domain_id: int, settings: GraphSettings, system: str, record: bool,
                shared_root: str | None = None,
                overrides: Mapping[str, Mapping[str, Any]] | None = None) -> RunResult:
    """A run's task body: run ``spec`` with its output captured; never raises for a failed run.

    With ``shared_root`` the log and MCAP go to ``spec.path(shared_root, ...)`` directly;
    otherwise to a temporary directory whose files are returned as bytes.
    """
    t0 = time.perf_counter()
    node_id, host = _node_id(), socket.gethostname()
    with tempfile.TemporaryDirectory(prefix='experiment-run-') as tmp:
        if shared_root is not None:
            log_path, mcap_path = spec.path(shared_root, '.log'), spec.path(shared_root, '.mcap')
            log_path.parent.mkdir(parents=True, exist_ok=True)
        else:
            log_path, mcap_path = Path(tmp) / 'run.log', Path(tmp) / 'run.mcap'
        rows: list[dict[str, Any]] | None = None
        error: str | None = None
        log_path.write_text(f'{spec.label}: {spec.seeds}, system {system}, ROS_DOMAIN_ID {domain_id}, '
                            f'host {host}, Ray node {node_id or "-"}\n')
        with _output_to(log_path):
            try:
                rows = run_graph(spec, domain_id, settings, mcap_path if record else None, system, overrides)
            except Exception as exc:  # noqa: BLE001 (a failed run must not stop the others; the log keeps why)
                traceback.print_exc()
                error = f'{type(exc).__name__}: {exc}'
        returned = shared_root is None
        log = log_path.read_bytes() if returned else None
        mcap = mcap_path.read_bytes() if returned and mcap_path.exists() else None
    return RunResult(spec, rows, error, log, mcap, node_id, host, domain_id, time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------
# Files

def write_rows(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """Write rows as CSV atomically (temporary file + rename): a file that exists is complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    with tmp.open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction='ignore')
        w.writeheader()
        for r in rows:
            w.writerow({k: (f'{v:.6g}' if isinstance(v, float) else v) for k, v in r.items()})
    os.replace(tmp, path)


def _write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` atomically (temporary file + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    tmp.write_bytes(data)
    os.replace(tmp, path)


def read_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV written by :func:`write_rows`, as strings."""
    with Path(path).open(newline='') as f:
        return list(csv.DictReader(f))


def is_finished(spec: RunSpec, root: Path, expected_hash: str) -> bool:
    """Whether ``spec``'s CSV exists (the driver writes it only when the run has ended well).

    Raises
    ------
    ValueError
        If the CSV belongs to another experiment (other iteration count, seed or settings hash):
        resuming would mix two configurations in one output directory.
    """
    path = spec.path(root, '.csv')
    if not path.exists():
        return False
    rows = read_rows(path)
    its = max((int(r['iteration']) for r in rows), default=-1)
    seeds = {r['seed'] for r in rows}
    if its != spec.iterations or seeds != {str(spec.seed)}:
        raise ValueError(f'{path} holds {its} iterations with seed(s) {sorted(seeds)}, but this experiment '
                         f'asks for {spec.iterations} iterations with seed {spec.seed}: use another --output '
                         f'or --force-new')
    hashes = {r.get('settings_hash') or '<none>' for r in rows}
    if hashes != {expected_hash}:
        raise ValueError(f'{path} was made with settings hash {sorted(hashes)}, this experiment has '
                         f'{expected_hash} (config.json lists the settings): use another --output or --force-new')
    return True


def combine_runs(root: Path, runs: Sequence[RunSpec], out: Path) -> int:
    """Concatenate the CSVs of the finished ``runs`` into ``out`` (atomically); returns the row count."""
    rows: list[dict[str, str]] = []
    for spec in runs:
        p = spec.path(root, '.csv')
        if p.exists():
            rows.extend(read_rows(p))
    write_rows(out, rows)
    return len(rows)


#: What an experiment writes into its output directory (moved aside together by --force-new).
_OUTPUTS = ('config.json', 'runs', 'metrics.csv', 'summary.md', 'figures')


def _move_aside(root: Path) -> Path | None:
    """Move the earlier results in ``root`` to ``root/previous-<time>``; that directory, or None
    if there was nothing to move."""
    present = [root / name for name in _OUTPUTS if (root / name).exists()]
    if not present:
        return None
    aside = root / time.strftime('previous-%Y%m%d-%H%M%S')
    aside = aside if not aside.exists() else root / f'{aside.name}-{os.getpid()}'
    aside.mkdir(parents=True)
    for p in present:
        p.rename(aside / p.name)
    return aside


def _check_resume(root: Path, config: ExperimentConfig, settings: Mapping[str, Mapping[str, Any]]) -> None:
    """Refuse to resume ``root`` if a method with finished runs there had other settings.

    Raises
    ------
    ValueError
        Naming each such method and its differing keys (old -> new).
    """
    path = root / 'config.json'
    if not path.exists():
        return
    old = json.loads(path.read_text()).get('settings', {})
    problems = []
    for method, new in settings.items():
        if not any((root / 'runs' / method).glob('rep*.csv')):
            continue
        if method not in old:
            problems.append(f'{method}: finished runs but no recorded settings (an older runner)')
        elif settings_hash(old[method]) != settings_hash(new):
            problems.append(f'{method}: ' + '; '.join(settings_difference(old[method], new)))
    if problems:
        raise ValueError(f'{root} holds finished runs made with other settings:\n  ' + '\n  '.join(problems)
                         + '\nrerun with the same settings to resume, use another --output, or --force-new '
                           f'to move the old results to {root}/previous-<time> and start over')


def _write_config(root: Path, config: ExperimentConfig, settings: Mapping[str, Mapping[str, Any]]) -> None:
    path = root / 'config.json'
    # Methods of an earlier session not run in this one keep their recorded settings, and the
    # runs already made their numeric environments.
    old = json.loads(path.read_text()) if path.exists() else {}
    recorded = old.get('settings', {})
    recorded.update(settings)
    doc = {**asdict(config), 'output': str(root), 'methods': list(config.methods),
           'system_overrides': merge_parameters(SYSTEMS[config.system], config.overrides),
           'seeds': [{'repetition': r, 'seed': config.seed_base + r, **asdict(derive_seeds(config.seed_base + r))}
                     for r in range(config.repetitions)],
           'settings_hash': {m: settings_hash(s) for m, s in recorded.items()},
           'settings': recorded, **({'environments': old['environments']} if 'environments' in old else {})}
    _write_bytes(path, (json.dumps(doc, indent=2, default=str) + '\n').encode())


def _without_hosts(entry: Mapping[str, Any]) -> dict[str, str]:
    """A ``config.json`` ``environments`` entry without its ``hosts``: the environment itself."""
    return {k: v for k, v in entry.items() if k != 'hosts'}


def read_environments(root: Path) -> list[dict[str, str]]:
    """The distinct numeric environments an experiment's runs were made on (``config.json``'s
    ``environments``; empty for an experiment made before it was recorded)."""
    path = Path(root) / 'config.json'
    if not path.exists():
        return []
    recorded = json.loads(path.read_text()).get('environments', [])
    return distinct_environments(_without_hosts(e) for e in recorded)


def _record_environments(root: Path, current: Mapping[str, Mapping[str, str]]) -> list[str]:
    """Add this session's node environments (host -> environment) to ``config.json``'s
    ``environments`` (one entry per distinct environment, with its hosts); a line for each
    environment that differs from one already recorded there (runs of the two do not repeat)."""
    path = root / 'config.json'
    doc = json.loads(path.read_text()) if path.exists() else {}
    recorded: list[dict[str, Any]] = doc.get('environments', [])
    earlier = [_without_hosts(e) for e in recorded]
    cautions = []
    for host, env in current.items():
        env = dict(env)
        if env in earlier:
            entry = recorded[earlier.index(env)]
            entry['hosts'] = sorted(set(entry.get('hosts', [])) | {host})
            continue
        if earlier:
            cautions.append(f'{root} now holds runs made on another numeric environment ({host}: '
                            f'{"; ".join(environment_differences(earlier[0], env))}); runs of the two do not '
                            'repeat one another step by step (docs/experiment.md, "Repeating a run")')
        recorded.append({'hosts': [host], **env})
        earlier.append(env)
    doc['environments'] = recorded
    _write_bytes(path, (json.dumps(doc, indent=2, default=str) + '\n').encode())
    return cautions


# ------------------------------------------------------------------------------------------
# Execution on Ray

def domain_ids(config: ExperimentConfig) -> list[int]:
    """The ``jobs`` ROS_DOMAIN_IDs the driver leases to the runs in flight, one each."""
    # 215-232 are valid on Linux (their ports lie above the ephemeral range) and unused by the
    # test suite (1-100); offset by our pid so two experiments on one machine rarely collide.
    if config.domain_base is not None:
        return [config.domain_base + k for k in range(config.jobs)]
    span = 232 - 215 + 1
    if config.jobs > span:
        raise ValueError(f'at most {span} jobs without --domain-base, got {config.jobs}')
    first = os.getpid() % span
    return [215 + (first + k) % span for k in range(config.jobs)]


@contextmanager
def ray_runtime(address: str | None, jobs: int) -> Iterator[None]:
    """Ray for the experiment: a connection the caller already made, else a local runtime of
    ``jobs`` CPUs started here (``address`` None) or a connection to the cluster at ``address``;
    what is started here is shut down on exit."""
    import ray

    if ray.is_initialized():
        yield
        return
    quiet = {'logging_level': logging.ERROR, 'log_to_driver': False}
    if address is None:
        # Runs return small results (rows, a few MB of MCAP): a small object store suffices.
        ray.init(address='local', num_cpus=jobs, include_dashboard=False,
                 object_store_memory=256 * 1024**2, **quiet)
    else:
        ray.init(address=address, **quiet)
    try:
        yield
    finally:
        ray.shutdown()


@dataclass
class ExperimentOutcome:
    """What :func:`run_experiment` did: this session's results (bytes dropped once written), failures,
    and the numeric environment of each node that ran them (host -> environment)."""

    results: list[RunResult] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    environments: dict[str, dict[str, str]] = field(default_factory=dict)


def run_cautions(results: Sequence[RunResult]) -> list[str]:
    """One line per finished run in which no observation reached the estimate (every attempt
    failed or was refused): a result, not a failure, since the method's statistics rightly carry
    it, but its final error is the initial guess's and the reader should know why."""
    return [f'{r.spec.label}: no observation reached the estimate in its {len(r.rows) - 1} iterations; '
            "its final error is the initial guess's"
            for r in results if r.rows is not None and _no_observation_used(r.rows)]


def _no_observation_used(rows: Sequence[Mapping[str, Any]]) -> bool:
    """Whether none of a run's iteration rows (row 0 is the initial guess) moved the estimate."""
    return not observations_used(row['outcome'] for row in rows[1:])


def _store(result: RunResult, root: Path, run_hash: str) -> None:
    """Write a finished task's files; the CSV last, and only for a run that ended well."""
    spec = result.spec
    if result.log is not None:
        _write_bytes(spec.path(root, '.log'), result.log)
    if result.mcap is not None:
        _write_bytes(spec.path(root, '.mcap'), result.mcap)
    if result.rows is not None:
        write_rows(spec.path(root, '.csv'), [{**r, 'settings_hash': run_hash} for r in result.rows])


def _run_all(todo: list[RunSpec], config: ExperimentConfig, record: bool, hashes: Mapping[str, str],
             stream: TextIO) -> ExperimentOutcome:
    import ray
    from tqdm import tqdm

    root = Path(config.output)
    # Workers inherit their node's `ray start` environment, not this one: the tasks carry theirs.
    options = cluster.task_options()
    task = ray.remote(num_cpus=1, max_retries=0, scheduling_strategy='SPREAD', **options)(execute_run)
    nodes, silent = cluster.check_nodes(record, options)    # raises naming a node that cannot run runs
    if silent:
        stream.write(f'experiment: Ray node(s) {", ".join(silent)} did not answer the environment check within '
                     f'{cluster.CHECK_TIMEOUT:.0f} s; their runs go ahead unchecked\n')
    fail_fast = cluster.FailFast()
    shared = str(root.resolve()) if config.shared else None
    free, waiting = domain_ids(config), deque(todo)
    in_flight: dict[Any, tuple[RunSpec, int]] = {}
    outcome = ExperimentOutcome(environments={n.host or n.node_id: dict(n.numeric) for n in nodes})
    # Recorded before the first run, so an interrupted experiment's runs have theirs too.
    for line in _record_environments(root, outcome.environments):
        stream.write(f'experiment: CAUTION {line}\n')
    bar = tqdm(total=len(todo), unit='run', file=stream, disable=None, dynamic_ncols=True)
    try:
        while waiting or in_flight:
            # At most `jobs` runs in flight, each with a domain id no other run in flight holds.
            while waiting and free:
                spec, domain = waiting.popleft(), free.pop(0)
                ref = task.remote(spec, domain, config.graph, config.system, record, shared, config.overrides)
                in_flight[ref] = (spec, domain)
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=0.5)
            for ref in ready:
                spec, domain = in_flight.pop(ref)
                free.append(domain)
                cause: str | None = None
                try:
                    result: RunResult = ray.get(ref)
                except ray.exceptions.RayError as exc:   # the worker or its node died, or never ran the task
                    result = RunResult(spec, None, f'{type(exc).__name__}: {exc}', None, None, '', '', domain, 0.0)
                    cause = cluster.root_cause(exc)
                _store(result, root, hashes[spec.method])
                if result.error is not None:
                    outcome.failures.append(f'{spec.label}: {result.error} (log: {spec.path(root, ".log")})')
                    note = f'FAILED {result.error[:200]}'
                else:
                    last = result.rows[-1]
                    note = (f"done in {result.wall_s:.0f} s on {result.host}, final {last['position_mm']:.1f} mm / "
                            f"{last['orientation_deg']:.2f} deg, movement {last['movement_deg']:.0f} deg")
                    if _no_observation_used(result.rows):
                        note += ', NO OBSERVATION USED (the final estimate is the initial guess)'
                outcome.results.append(replace(result, log=None, mcap=None))
                bar.update(1)
                tqdm.write(f'{spec.label}: {note}', file=stream)
                if result.error is not None:
                    stop = fail_fast.record(result.node_id, result.host, cause or result.error)
                    if stop is not None and not result.node_id:
                        cluster.check_nodes(record, options)    # names the node, if the check fails there
                    if stop is not None:
                        raise stop
    except BaseException:
        # Ctrl-C, a failure to write or a failing node: kill the runs in flight; nothing they did is written.
        for ref in in_flight:
            ray.cancel(ref, force=True)
        bar.close()
        stream.write(f'experiment: stopped; {len(in_flight)} run(s) in flight cancelled (finished runs are '
                     'kept, rerun to resume)\n')
        raise
    bar.close()
    return outcome


def run_experiment(config: ExperimentConfig, stream: TextIO = sys.stderr) -> ExperimentOutcome:
    """Run every unfinished run of ``config`` on Ray, combine, plot.

    Raises
    ------
    ValueError
        If the output directory holds finished runs made with other settings (unless
        ``config.force_new``).
    calibration_bringup.cluster.NodeEnvironmentError
        If a Ray node cannot run runs (its check failed, or runs kept failing there for one
        environmental cause); it names the node and the cause.
    """
    root = Path(config.output)
    root.mkdir(parents=True, exist_ok=True)
    settings = {m: run_settings(config, m) for m in config.methods}
    hashes = {m: settings_hash(s) for m, s in settings.items()}
    if config.force_new:
        aside = _move_aside(root)
        stream.write(f'experiment: --force-new: earlier results moved to {aside}\n' if aside else
                     f'experiment: --force-new: nothing to move aside in {root}\n')
    else:
        _check_resume(root, config, settings)
    runs = plan_runs(config)
    todo = [s for s in runs if not is_finished(s, root, hashes[s.method])]
    _write_config(root, config, settings)
    where = config.address or f'a local Ray runtime of {config.jobs} CPUs'
    stream.write(f'experiment: system {config.system}, {len(runs)} runs ({len(config.methods)} methods x '
                 f'{config.repetitions} repetitions x {config.iterations} iterations) in {root}; '
                 f'{len(runs) - len(todo)} already finished, {len(todo)} to run on {where}, '
                 f'at most {config.jobs} at a time\n')
    record = config.record
    if record and not recorder_available():
        stream.write('experiment: calibration_bringup.recorder_node is not installed; runs are not recorded\n')
        record = False
    outcome = ExperimentOutcome()
    if todo:
        with ray_runtime(config.address, config.jobs):
            outcome = _run_all(todo, config, record, hashes, stream)
    n = combine_runs(root, runs, root / 'metrics.csv') if config.combine else 0
    if config.combine:
        stream.write(f'experiment: {n} rows in {root / "metrics.csv"}\n')
    if config.figures and n:
        from . import experiment_figures

        outputs = experiment_figures.render(root)
        stream.write(f'experiment: summary {root / "summary.md"}, figures {", ".join(p.name for p in outputs)}\n')
    for c in run_cautions(outcome.results):
        stream.write(f'experiment: CAUTION {c}\n')
    for f in outcome.failures:
        stream.write(f'experiment: FAILED {f}\n')
    return outcome


# ------------------------------------------------------------------------------------------
# CLI

QUICK = {'repetitions': 3, 'iterations': 20}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='experiment', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog='Finished runs (their CSV exists) are skipped: rerun the same command to '
                                       'resume. Resuming with other settings is refused (see --force-new).')
    p.add_argument('--system', choices=list(SYSTEMS), default='ours',
                   help="compared system: 'ours' (the nodes' parameter files) or 'paper' (EKF, C0/eta, "
                        'a-optimality, DIRECT-L 1000) [ours]')
    p.add_argument('--quick', action='store_true',
                   help=f"preset: {QUICK['repetitions']} repetitions x {QUICK['iterations']} iterations into "
                        'results/experiment-<system>-quick (explicit --repetitions/--iterations/--output win)')
    p.add_argument('--repetitions', type=int, default=None, help='repetitions (seeds) per method [50]')
    p.add_argument('--iterations', type=int, default=None, help='iterations per run [50]')
    p.add_argument('--methods', nargs='+', default=list(METHODS), choices=list(METHODS), metavar='METHOD',
                   help=f'methods to run {list(METHODS)} [all]')
    p.add_argument('--jobs', type=int, default=2,
                   help='runs in flight at once, one CPU each (and the local runtime\'s CPUs) [2]')
    p.add_argument('--address', default=None,
                   help="Ray cluster to submit to: 'auto', 'ray://host:10001' or 'host:6379' "
                        '[start a local runtime]')
    out = p.add_mutually_exclusive_group()
    out.add_argument('--output', type=Path, default=None,
                     help='output directory, on the driver [results/experiment-<system>[-quick]]')
    out.add_argument('--shared-output', type=Path, default=None, metavar='PATH',
                     help='output directory at the same path on every node: runs write their logs and '
                          'MCAPs there instead of returning them')
    p.add_argument('--force-new', action='store_true',
                   help='move earlier results in the output directory to previous-<time>/ and start over')
    p.add_argument('--set', action='append', default=[], metavar='NODE.PARAMETER=VALUE',
                   help="a node parameter over the system's, e.g. --set estimator.q_length=1e-6 (repeatable; "
                        f'nodes: {", ".join(NODES)}; write 0.0 for a float); part of the settings a resume checks')
    p.add_argument('--seed-base', type=int, default=0,
                   help='repetition r has seed seed_base + r, from which its robot, guess and selector '
                        'seeds are spawned [0]')
    p.add_argument('--record', action=argparse.BooleanOptionalAction, default=True,
                   help='record each run (non-image topics) to runs/<method>/repNN.mcap [on]')
    p.add_argument('--domain-base', type=int, default=None,
                   help='ROS_DOMAIN_IDs base .. base + jobs - 1 leased to the runs in flight [215-232, from the pid]')
    p.add_argument('--no-figures', dest='figures', action='store_false', help='skip figures and summary')
    g = GraphSettings()
    p.add_argument('--image-rate', type=float, default=g.image_rate, help=f'camera rate [Hz, sim] [{g.image_rate}]')
    p.add_argument('--image-size', type=int, nargs=2, default=(g.image_width, g.image_height),
                   metavar=('W', 'H'), help=f'camera resolution [{g.image_width} {g.image_height}]')
    p.add_argument('--joint-speed', type=float, default=g.max_joint_speed_deg,
                   help=f'simulated joint speed limit [deg/s] [{g.max_joint_speed_deg}]')
    return p


def parse_override(text: str) -> tuple[str, str, Any]:
    """``'node.parameter=value'`` -> ``(node, parameter, value)``.

    The value is read as a ROS parameter is typed: ``true``/``false`` a bool, a literal without a
    decimal point or exponent an int, one with either a float (write ``0.0``, not ``0``, for a
    float parameter), ``[...]`` a YAML list, anything else a string.

    Raises
    ------
    ValueError
        Naming the text, if it is not ``node.parameter=value`` with a node of :data:`NODES`.
    """
    import yaml

    key, sep, raw = text.partition('=')
    node, dot, name = key.strip().partition('.')
    if not (sep and dot and name):
        raise ValueError(f'--set {text!r}: expected NODE.PARAMETER=VALUE, e.g. estimator.q_length=1e-6')
    if node not in NODES:
        raise ValueError(f'--set {text!r}: unknown node {node!r}; expected one of {list(NODES)}')
    raw = raw.strip()
    value: Any
    if raw.lower() in ('true', 'false'):
        value = raw.lower() == 'true'
    else:
        try:
            value = int(raw)
        except ValueError:
            try:
                value = float(raw)
            except ValueError:
                value = yaml.safe_load(raw) if raw.startswith('[') else raw
    return node, name.strip(), value


def config_from_args(argv: Sequence[str] | None = None) -> ExperimentConfig:
    """Parse the command line into an :class:`ExperimentConfig`."""
    a = build_parser().parse_args(argv)
    reps = a.repetitions if a.repetitions is not None else (QUICK['repetitions'] if a.quick else 50)
    its = a.iterations if a.iterations is not None else (QUICK['iterations'] if a.quick else 50)
    graph = replace(GraphSettings(), image_rate=a.image_rate, image_width=a.image_size[0],
                    image_height=a.image_size[1], max_joint_speed_deg=a.joint_speed)
    output = a.shared_output or a.output or _default_output(a.system, a.quick)
    overrides: dict[str, dict[str, Any]] = {}
    for text in a.set:
        node, name, value = parse_override(text)
        overrides.setdefault(node, {})[name] = value
    return ExperimentConfig(repetitions=reps, iterations=its, methods=tuple(dict.fromkeys(a.methods)),
                            system=a.system, jobs=a.jobs, output=output, seed_base=a.seed_base, record=a.record,
                            domain_base=a.domain_base, figures=a.figures, graph=graph, address=a.address,
                            shared=a.shared_output is not None, force_new=a.force_new, overrides=overrides)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``experiment``."""
    from tqdm import tqdm

    try:
        config = config_from_args(argv)
        t0 = time.monotonic()
        outcome = run_experiment(config)
    except ValueError as exc:
        print(f'experiment: {exc}', file=sys.stderr)
        return 2
    except cluster.NodeEnvironmentError as exc:
        print(f'experiment: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    failed = len(outcome.failures)
    print(f'experiment: finished in {tqdm.format_interval(time.monotonic() - t0)}'
          f'{f", {failed} run(s) failed (rerun to retry them)" if failed else ""}', file=sys.stderr)
    return 1 if failed else 0


if __name__ == '__main__':
    # Ray pickles this module's classes by reference: run them from the importable module, not
    # from __main__ (which workers cannot import).
    from calibration_bringup.experiment import main as _main

    sys.exit(_main())
