"""The paper's experiment on the real node graph: methods x repetitions x iterations.

Usage::

    python -m calibration_bringup.experiment                 # 7 methods x 50 repetitions x 50 iterations
    python -m calibration_bringup.experiment --quick         # 7 methods x 3 repetitions x 20 iterations
    python -m calibration_bringup.experiment --methods AL CCSAL --repetitions 3 --iterations 10
    python -m calibration_bringup.experiment_figures results/experiment     # re-plot only

Methods (docs/architecture.md section 5): ``R``, ``AL``, ``UCSAL``, ``CCSAL`` with the pose-dependent noise
model, and ``AL-CN``, ``UCSAL-CN``, ``CCSAL-CN`` with the constant one (selector and estimator
both use the CN covariance; the detector keeps publishing pose-dependent covariances, which the
estimator then ignores).

Repetition ``r`` uses the seed ``s = seed_base + r`` for the simulated robot (``perturb_seed``),
the estimator's initial guess (``initial_seed``) and the selector (``seed``), so every method of a
repetition starts from the same true robot and the same guess.

One run is one fresh graph (SimNode, DetectorNode, EstimatorNode, SelectorNode, optionally the
MCAP recorder, and a probe) on a SingleThreadedExecutor with its own ``Context`` and
``ROS_DOMAIN_ID``, inside a worker process (``--jobs`` spawned workers, each with its own domain
id, running its runs one after another). After every ``/calibration/progress`` record the probe
scores the estimator's current table with :class:`body_schema.metrics.PoseErrorEvaluator` against
the simulator's true table (row 0 is the initial guess). Each run's rows are written atomically
to ``<output>/runs/<method>/rep<NN>.csv`` when the run ends, so a killed run is simply redone and
finished runs are skipped on restart; its log goes to ``rep<NN>.log`` and, with ``--record``, its
non-image topics to ``rep<NN>.mcap``. At the end all runs are combined into
``<output>/metrics.csv`` and :mod:`calibration_bringup.experiment_figures` draws the figures and
writes ``<output>/summary.md``.

Time accounting per iteration (CSV columns, wall seconds unless named ``_sim_``): ``selection_s``
(the selector's DIRECT search), ``move_sim_s`` (the simulated move), ``sim_s`` (simulator
callbacks: physics, rendering, publishing), ``render_s`` (rendering alone), ``detect_s``
(detector callbacks), ``estimator_s`` (estimator callbacks, the EKF update among them),
``selector_s`` (selector callbacks, the selection among them), ``recorder_s``, ``cpu_s`` (CPU
time of the whole process: on a shared machine, what the iteration costs with a core of its own)
and ``wall_s`` (everything, the executor's own work included).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing as mp
import os
import queue
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, TextIO

from .graph import InProcessGraph, default_parameters, merge_parameters, recorder_available, ros_session

__all__ = ['METHODS', 'COLUMNS', 'Method', 'RunSpec', 'GraphSettings', 'ExperimentConfig', 'RunError',
           'plan_runs', 'is_finished', 'node_parameters', 'run_graph', 'write_rows', 'read_rows', 'combine_runs',
           'Progress', 'run_experiment', 'main']


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
    'method', 'repetition', 'seed', 'iteration', 'outcome', 'detected', 'position_mm', 'orientation_deg',
    'movement_deg', 'discarded', 'selection_s', 'move_sim_s', 'sim_s', 'render_s', 'detect_s',
    'estimator_s', 'selector_s', 'recorder_s', 'cpu_s', 'wall_s')

#: Callback time accounting: CSV column -> node attribute of the graph.
_NODE_COLUMNS = {'sim_s': 'sim', 'detect_s': 'detector', 'estimator_s': 'estimator',
                 'selector_s': 'selector', 'recorder_s': 'recorder'}


class RunError(RuntimeError):
    """A run that could not finish (stuck loop, crashed node)."""


@dataclass(frozen=True)
class GraphSettings:
    """Simulator settings of experiment runs, chosen by measurement (AL, 20 iterations, same seed:
    identical outcomes and final errors for every setting below, only the time differs).

    Attributes
    ----------
    image_rate : float
        Camera rate [Hz, sim time]. Frames during a move are never measurement attempts, so a low
        rate only delays the first frame after settling by up to one period of sim time. CPU
        time per iteration outside the selection, R / AL / CCSAL (30 iterations, 2 seeds):
        5 Hz 0.23 / 0.18 / 0.11 s, 3.3 Hz 0.19 / 0.14 / 0.10 s, 2.5 Hz 0.16 / 0.12 / 0.09 s,
        2 Hz 0.18 / 0.11 / 0.10 s (fewer renders, but more sim ticks waiting for the frame);
        10 Hz cost 0.21 s for AL.
    physics_step : float
        Physics step [s]; the arm is kinematic (placed, not simulated), so one step per
        joint-state period suffices: 0.24 -> 0.21 s per AL iteration at 10 Hz.
    max_joint_speed_deg : float
        Joint speed limit [deg/s]. The metrics count degrees, not seconds; the default is the
        simulator's.
    image_width, image_height : int
        Camera resolution (the iCub simulator's 320 x 240 by default).
    run_timeout : float
        Wall seconds a run may take per iteration before it is declared stuck (plus one minute).
    """

    image_rate: float = 2.5
    physics_step: float = 0.02
    max_joint_speed_deg: float = 30.0
    image_width: int = 320
    image_height: int = 240
    run_timeout: float = 30.0


@dataclass(frozen=True)
class RunSpec:
    """One run: a method on one repetition (true robot + initial guess)."""

    method: str
    repetition: int
    seed: int
    iterations: int

    @property
    def stem(self) -> str:
        return f'runs/{self.method}/rep{self.repetition:02d}'

    def path(self, root: Path, suffix: str) -> Path:
        """``<root>/runs/<method>/rep<NN><suffix>``."""
        return Path(root) / f'{self.stem}{suffix}'

    @property
    def label(self) -> str:
        return f'{self.method} rep {self.repetition} (seed {self.seed})'


@dataclass(frozen=True)
class ExperimentConfig:
    """What to run and where (the CLI's options)."""

    repetitions: int = 50
    iterations: int = 50
    methods: tuple[str, ...] = tuple(METHODS)
    jobs: int = 2
    output: Path = Path('results/experiment')
    seed_base: int = 0
    record: bool = True
    domain_base: int | None = None
    figures: bool = True
    graph: GraphSettings = field(default_factory=GraphSettings)

    def __post_init__(self) -> None:
        bad = [m for m in self.methods if m not in METHODS]
        if bad:
            raise ValueError(f'unknown methods {bad}; expected any of {list(METHODS)}')
        if not self.methods:
            raise ValueError('methods must not be empty')
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


def node_parameters(spec: RunSpec, settings: GraphSettings = GraphSettings()) -> dict[str, dict[str, Any]]:
    """Parameter overrides of each node for ``spec`` (pure; the graph applies them).

    Returns
    -------
    dict
        ``{'sim': {...}, 'detector': {...}, 'estimator': {...}, 'selector': {...}}``.
    """
    method = METHODS[spec.method]
    noise = {'noise_model': 'constant'} if method.constant_noise else {}
    return merge_parameters(default_parameters(), {
        'sim': {'perturb_seed': spec.seed, 'image_rate': settings.image_rate, 'physics_step': settings.physics_step,
                'max_joint_speed_deg': settings.max_joint_speed_deg,
                'image_width': settings.image_width, 'image_height': settings.image_height},
        'estimator': {'initial_seed': spec.seed, **noise},
        'selector': {'strategy': method.strategy, 'iterations': spec.iterations, 'seed': spec.seed, **noise},
    })


# ------------------------------------------------------------------------------------------
# One run: the graph in this process

def run_graph(spec: RunSpec, domain_id: int, settings: GraphSettings = GraphSettings(),
              record_path: Path | None = None,
              on_iteration: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run ``spec`` on a fresh in-process graph and return its rows (iteration 0 = initial guess).

    Parameters
    ----------
    spec : RunSpec
    domain_id : int
        ROS_DOMAIN_ID of this graph (distinct from any other graph running at the same time).
    settings : GraphSettings
    record_path : Path or None
        Record the non-image topics to this MCAP file.
    on_iteration : callable or None
        Called with each row as soon as its iteration ends (progress reporting).

    Raises
    ------
    RunError
        If the selector has not finished ``spec.iterations`` iterations within the deadline.
    """
    import numpy as np
    from rclpy.node import Node
    from std_msgs.msg import String

    from body_schema.metrics import PoseErrorEvaluator

    rows: list[dict[str, Any]] = []
    with ros_session(domain_id) as (ctx, executor):
        try:
            graph = InProcessGraph(ctx, executor, node_parameters(spec, settings), record_path, time_callbacks=True)
        except RuntimeError as exc:     # the recorder asked for but missing
            raise RunError(f'{exc}; use --no-record') from exc
        with graph:
            sim, est, sel = graph.sim, graph.estimator, graph.selector
            evaluate = PoseErrorEvaluator(sim.robot.base, sim.true_dh, sim.robot.calibration_box)

            def totals() -> dict[str, float]:
                return {**graph.callback_seconds, 'render': sim.world.render_seconds}

            base = {'method': spec.method, 'repetition': spec.repetition, 'seed': spec.seed}
            e0 = evaluate(est.estimator.dh)
            rows.append({**base, 'iteration': 0, 'outcome': 'initial', 'detected': '',
                         'position_mm': e0.position_mm, 'orientation_deg': e0.orientation_deg,
                         'movement_deg': 0.0, 'discarded': 0, 'selection_s': 0.0, 'move_sim_s': 0.0,
                         **{c: 0.0 for c in ('render_s', 'cpu_s', 'wall_s', *_NODE_COLUMNS)}})
            last = {'wall': time.perf_counter(), 'cpu': time.process_time(), **totals()}
            tables: list[np.ndarray] = []

            def on_progress(msg: String) -> None:
                rec = json.loads(msg.data)
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
                if len(rows) > n:
                    # Scored after the fact so the loop pays nothing; the table is the one current
                    # when the record arrived.
                    err = evaluate(tables[-1])
                    rows[-1]['position_mm'], rows[-1]['orientation_deg'] = err.position_mm, err.orientation_deg
                    if on_iteration is not None:
                        on_iteration(rows[-1])
                if time.monotonic() > deadline:
                    raise RunError(f'{spec.label}: only {len(rows) - 1} of {spec.iterations} iterations '
                                   f'within {limit:.0f} s '
                                   f'(selector phase: {sel.phase.value})')
            # The bag is complete once it holds the last progress record too.
            graph.wait_for_recorder('/calibration/progress', spec.iterations)
    return rows


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


def read_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV written by :func:`write_rows`, as strings."""
    with Path(path).open(newline='') as f:
        return list(csv.DictReader(f))


def is_finished(spec: RunSpec, root: Path) -> bool:
    """Whether ``spec``'s CSV exists (it is written only at the end of a run).

    Raises
    ------
    ValueError
        If the CSV belongs to another experiment (other seed or iteration count): resuming would
        mix two configurations in one output directory.
    """
    path = spec.path(root, '.csv')
    if not path.exists():
        return False
    rows = read_rows(path)
    its = max((int(r['iteration']) for r in rows), default=-1)
    seeds = {r['seed'] for r in rows}
    if its != spec.iterations or seeds != {str(spec.seed)}:
        raise ValueError(f'{path} holds {its} iterations with seed(s) {sorted(seeds)}, but this experiment '
                         f'asks for {spec.iterations} iterations with seed {spec.seed}: use another --output')
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


# ------------------------------------------------------------------------------------------
# Progress

def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return '?'
    s = int(round(seconds))
    return f'{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}' if s >= 3600 else f'{s // 60}:{s % 60:02d}'


class Progress:
    """A plain-text progress bar with ETA on a stream.

    On a terminal the bar is redrawn in place after every iteration; otherwise one line is printed
    per finished run (log files stay readable).

    Parameters
    ----------
    runs, iterations_per_run : int
        What this session has to do (runs skipped as already finished are not counted).
    stream : text stream
    tty : bool or None
        Redraw in place; default: ``stream.isatty()``.
    clock : callable
        Monotonic seconds (injectable for tests).
    """

    def __init__(self, runs: int, iterations_per_run: int, stream: TextIO = sys.stderr,
                 tty: bool | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.runs, self.per_run = runs, iterations_per_run
        self.stream, self.clock = stream, clock
        self.tty = stream.isatty() if tty is None else tty
        self.t0 = clock()
        self.done_runs = self.failed_runs = 0
        self.partial: dict[str, int] = {}      # iterations of unfinished runs
        self.done_iterations = 0

    @property
    def iterations(self) -> int:
        return self.done_iterations + sum(self.partial.values())

    def line(self) -> str:
        total = self.runs * self.per_run
        elapsed = self.clock() - self.t0
        rate = self.iterations / elapsed if elapsed > 0 else 0.0
        eta = (total - self.iterations) / rate if rate > 0 else math.inf
        frac = self.iterations / total if total else 1.0
        width = 30
        bar = '#' * int(frac * width) + '-' * (width - int(frac * width))
        failed = f', {self.failed_runs} failed' if self.failed_runs else ''
        return (f'[{bar}] {self.done_runs}/{self.runs} runs{failed}, {self.iterations}/{total} iterations, '
                f'{rate:.2f} it/s, elapsed {_duration(elapsed)}, ETA {_duration(eta)}')

    def iteration(self, run: str, iteration: int) -> None:
        """Iteration ``iteration`` of ``run`` finished."""
        self.partial[run] = iteration
        if self.tty:
            self.stream.write('\r' + self.line() + '\x1b[K')
            self.stream.flush()

    def run_finished(self, run: str, ok: bool = True, note: str = '') -> None:
        """A run ended (``ok=False``: failed; its iterations still count as spent)."""
        self.partial.pop(run, None)
        self.done_iterations += self.per_run
        self.done_runs += ok
        self.failed_runs += not ok
        prefix = '\r' if self.tty else ''
        status = 'done' if ok else 'FAILED'
        self.stream.write(f'{prefix}{run}: {status}{" " + note if note else ""}\x1b[K\n' if self.tty else
                          f'{run}: {status}{" " + note if note else ""} | {self.line()}\n')
        if self.tty:
            self.stream.write(self.line())
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write('\n')
            self.stream.flush()


# ------------------------------------------------------------------------------------------
# Workers

_WORKER: dict[str, Any] = {}


def _init_worker(domain_ids: Any, events: Any) -> None:
    _WORKER['domain_id'] = domain_ids.get()
    _WORKER['events'] = events


@contextmanager
def _output_to(path: Path) -> Iterator[None]:
    """Send this process's stdout and stderr (file descriptors 1 and 2: rcutils logs and
    PyBullet's C prints included) to ``path``."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with path.open('w') as f:
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


def _run_in_worker(spec: RunSpec, root: str, settings: GraphSettings, record: bool) -> dict[str, Any]:
    """Worker entry: run ``spec``, write its CSV; returns a short summary."""
    root_p = Path(root)
    events = _WORKER.get('events')
    t0 = time.perf_counter()

    def tick(row: dict[str, Any]) -> None:
        if events is not None:
            events.put((spec.label, row['iteration']))

    if _WORKER.get('interrupted'):
        # Ctrl-C reaches the workers too: runs queued in this worker before it was interrupted end
        # at once instead of running to completion.
        raise RunError('not started: the experiment was interrupted')
    log = spec.path(root_p, '.log')
    log.parent.mkdir(parents=True, exist_ok=True)
    try:
        with _output_to(log):
            rows = run_graph(spec, _WORKER.get('domain_id', 0), settings,
                             spec.path(root_p, '.mcap') if record else None, tick)
    except KeyboardInterrupt:
        _WORKER['interrupted'] = True
        raise RunError('interrupted') from None
    write_rows(spec.path(root_p, '.csv'), rows)
    last = rows[-1]
    return {'wall_s': time.perf_counter() - t0, 'position_mm': last['position_mm'],
            'orientation_deg': last['orientation_deg'], 'movement_deg': last['movement_deg']}


def _domain_ids(config: ExperimentConfig) -> list[int]:
    # 215-232 are valid on Linux (their ports lie above the ephemeral range) and unused by the
    # test suite (1-100); offset by our pid so two experiments on one machine rarely collide.
    if config.domain_base is not None:
        return [config.domain_base + k for k in range(config.jobs)]
    span = 232 - 215 + 1
    if config.jobs > span:
        raise ValueError(f'at most {span} jobs without --domain-base, got {config.jobs}')
    first = os.getpid() % span
    return [215 + (first + k) % span for k in range(config.jobs)]


def run_experiment(config: ExperimentConfig, stream: TextIO = sys.stderr) -> int:
    """Run every unfinished run of ``config``, combine, plot; returns the number of failed runs."""
    root = Path(config.output)
    root.mkdir(parents=True, exist_ok=True)
    (root / 'config.json').write_text(json.dumps(
        {**asdict(config), 'output': str(root), 'methods': list(config.methods)}, indent=2) + '\n')
    runs = plan_runs(config)
    todo = [s for s in runs if not is_finished(s, root)]
    stream.write(f'experiment: {len(runs)} runs ({len(config.methods)} methods x {config.repetitions} '
                 f'repetitions x {config.iterations} iterations) in {root}; {len(runs) - len(todo)} already '
                 f'finished, {len(todo)} to run with {config.jobs} worker(s)\n')
    record = config.record
    if record and not recorder_available():
        stream.write('experiment: calibration_bringup.recorder_node is not installed; runs are not recorded\n')
        record = False
    failures: list[str] = []
    if todo:
        failures = _run_all(todo, config, record, stream)
    n = combine_runs(root, runs, root / 'metrics.csv')
    stream.write(f'experiment: {n} rows in {root / "metrics.csv"}\n')
    if config.figures and n:
        from . import experiment_figures

        outputs = experiment_figures.render(root)
        stream.write(f'experiment: summary {root / "summary.md"}, figures {", ".join(p.name for p in outputs)}\n')
    for f in failures:
        stream.write(f'experiment: FAILED {f}\n')
    return len(failures)


def _run_all(todo: list[RunSpec], config: ExperimentConfig, record: bool, stream: TextIO) -> list[str]:
    root = Path(config.output)
    ctx = mp.get_context('spawn')
    ids, events = ctx.Queue(), ctx.Queue()
    for d in _domain_ids(config):
        ids.put(d)
    progress = Progress(len(todo), config.iterations, stream)
    failures: list[str] = []
    jobs = min(config.jobs, len(todo))
    with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_init_worker, initargs=(ids, events)) as pool:
        pending: dict[Future, RunSpec] = {
            pool.submit(_run_in_worker, s, str(root), config.graph, record): s for s in todo}
        try:
            while pending:
                finished, _ = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                _drain(events, progress)
                for fut in finished:
                    spec = pending.pop(fut)
                    try:
                        r = fut.result()
                    except Exception as exc:  # noqa: BLE001 (a failed run must not stop the others)
                        failures.append(f'{spec.label}: {type(exc).__name__}: {exc} '
                                        f'(log: {spec.path(root, ".log")})')
                        progress.run_finished(spec.label, ok=False, note=str(exc)[:200])
                        continue
                    progress.run_finished(spec.label, note=(
                        f"{r['wall_s']:.0f} s, final {r['position_mm']:.1f} mm / {r['orientation_deg']:.2f} deg, "
                        f"movement {r['movement_deg']:.0f} deg"))
        except KeyboardInterrupt:
            progress.close()
            stream.write('experiment: interrupted; stopping the workers (finished runs are kept, '
                         'rerun to resume)\n')
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    progress.close()
    return failures


def _drain(events: Any, progress: Progress) -> None:
    while True:
        try:
            label, iteration = events.get_nowait()
        except queue.Empty:
            return
        progress.iteration(label, iteration)


# ------------------------------------------------------------------------------------------
# CLI

QUICK = {'repetitions': 3, 'iterations': 20, 'output': Path('results/experiment-quick')}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='experiment', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog='Finished runs (their CSV exists) are skipped: rerun the same command to resume.')
    p.add_argument('--quick', action='store_true',
                   help=f"preset: {QUICK['repetitions']} repetitions x {QUICK['iterations']} iterations into "
                        f"{QUICK['output']} (explicit --repetitions/--iterations/--output win)")
    p.add_argument('--repetitions', type=int, default=None, help='repetitions (seeds) per method [50]')
    p.add_argument('--iterations', type=int, default=None, help='iterations per run [50]')
    p.add_argument('--methods', nargs='+', default=list(METHODS), choices=list(METHODS), metavar='METHOD',
                   help=f'methods to run {list(METHODS)} [all]')
    p.add_argument('--jobs', type=int, default=2, help='worker processes, one graph each [2]')
    p.add_argument('--output', type=Path, default=None,
                   help=f"[results/experiment; with --quick {QUICK['output']}]")
    p.add_argument('--seed-base', type=int, default=0, help='repetition r uses seed seed_base + r [0]')
    p.add_argument('--record', action=argparse.BooleanOptionalAction, default=True,
                   help='record each run (non-image topics) to runs/<method>/repNN.mcap [on]')
    p.add_argument('--domain-base', type=int, default=None,
                   help='ROS_DOMAIN_ID of worker 0 (worker k: base + k) [215-232, from the pid]')
    p.add_argument('--no-figures', dest='figures', action='store_false', help='skip figures and summary')
    g = GraphSettings()
    p.add_argument('--image-rate', type=float, default=g.image_rate, help=f'camera rate [Hz, sim] [{g.image_rate}]')
    p.add_argument('--image-size', type=int, nargs=2, default=(g.image_width, g.image_height),
                   metavar=('W', 'H'), help=f'camera resolution [{g.image_width} {g.image_height}]')
    p.add_argument('--joint-speed', type=float, default=g.max_joint_speed_deg,
                   help=f'simulated joint speed limit [deg/s] [{g.max_joint_speed_deg}]')
    return p


def config_from_args(argv: Sequence[str] | None = None) -> ExperimentConfig:
    """Parse the command line into an :class:`ExperimentConfig`."""
    a = build_parser().parse_args(argv)
    reps = a.repetitions if a.repetitions is not None else (QUICK['repetitions'] if a.quick else 50)
    its = a.iterations if a.iterations is not None else (QUICK['iterations'] if a.quick else 50)
    graph = replace(GraphSettings(), image_rate=a.image_rate, image_width=a.image_size[0],
                    image_height=a.image_size[1], max_joint_speed_deg=a.joint_speed)
    output = a.output if a.output is not None else (QUICK['output'] if a.quick else Path('results/experiment'))
    return ExperimentConfig(repetitions=reps, iterations=its, methods=tuple(dict.fromkeys(a.methods)),
                            jobs=a.jobs, output=output, seed_base=a.seed_base, record=a.record,
                            domain_base=a.domain_base, figures=a.figures, graph=graph)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``experiment``."""
    try:
        config = config_from_args(argv)
        t0 = time.monotonic()
        failed = run_experiment(config)
    except ValueError as exc:
        print(f'experiment: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print(f'experiment: finished in {_duration(time.monotonic() - t0)}'
          f'{f", {failed} run(s) failed (rerun to retry them)" if failed else ""}', file=sys.stderr)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
