"""Offline evaluation of a recorded calibration run: re-run the EKF on a bag, score every iteration.

Reads an MCAP bag written by the recorder (``calibration_bringup.recorder_node``), feeds its
``/joint_states``, ``/arm/command`` and ``/hand_pose`` messages, in the order they were published
(recorded order for a bag whose publish times are not the publishers'), through the
same :class:`~dh_estimator.pairing.MessageFeeder`, :class:`~dh_estimator.pairing.ObservationPairer` and
:class:`~dh_estimator.estimator.OnlineEstimator` the node uses, with the run's settings (``--params-file``,
the estimator's parameter file) or others (``--noise-model constant`` re-runs the paper's CN
baseline on the very same images), and scores the estimate after every iteration (one
``/calibration/progress`` record each) against ``/body_schema/true`` with the paper's metrics:
average position and orientation error over 1000 configurations of the calibration box.

The estimate the online node published (``/body_schema/estimate``) is scored next to it; with
equal settings the two agree (the test suite checks it). A joint state's log time stands for
the node's clock when it arrived (the simulator publishes ``/clock`` with every joint state, and
the recorder logs on it), so joint states stamped in the future and clock steps back are judged
as online. Hand poses are not judged on it: under load the recorder logs them before the
joint states it is still catching up on (up to 2 s of log time early, measured at rtf 2), so
the re-run keeps them waiting for their joint states; a stray future one then never meets a
joint state and makes no update, as online, where it is refused.

Why publication order: the recorder's executor takes one message per topic per wait, so under load
it falls behind on the fast streams (/joint_states, /clock) and logs the slow ones (hand poses,
commands, verdicts) ahead of them, up to 2 s of sim time. Replayed in that order, each hand pose
waited behind some 30 newer ones for its joint states and the pairing dropped it after
``max_pending`` (a re-run with 2 of the 5 online updates). The estimator, which keeps up, receives
them as they were published; the recorder stores each message's source timestamp as its publish
time (metadata ``publish_time: source``,
:data:`calibration_interfaces.contract.PUBLISH_TIME_SOURCE`), and the re-run reads in that order.

Usage::

    evaluate BAG.mcap --output DIR [--params-file estimator.yaml] [--noise-model pose_dependent|constant] ...

writes ``DIR/metrics.csv``, ``DIR/error_vs_iteration.png`` and ``DIR/error_vs_movement.png``
and prints a summary. No rclpy is needed: messages are decoded with ``mcap-ros2-support``
(:mod:`calibration_interfaces.mcap_reader`, which also reads a killed recording: the summary
then says how much was recovered and what was lost). An empty, missing or non-MCAP file is
one line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from body_schema import load_robot, sampling
from body_schema.robot import parse_noise_law
from body_schema.extrinsics import absorbed_parameters, align_truth, perturb_pose, pose_delta
from body_schema.identifiability import average_nees_band, subspace_nees
from body_schema.kinematics import equivalent_table
from body_schema.map_estimator import COVARIANCES, LOSSES, MapSettings
from body_schema.metrics import PoseErrorEvaluator, expected_pose_errors
from body_schema.noise import NOISE_MODELS, InnovationCheck, PoseDependentNoise, innovation_check
from calibration_interfaces import mcap_reader
from calibration_interfaces.contract import PUBLISH_TIME_SOURCE
from calibration_interfaces.messages import msg_to_covariance, msg_to_extrinsics, msg_to_table
from calibration_interfaces.noise import NoiseSettings
from calibration_interfaces.parameters import read_params_file

from .estimator import ESTIMATORS, EstimatorSettings, OnlineEstimator
from .node_settings import settings_from_parameters
from .pairing import MessageError, MessageFeeder, ObservationPairer, PairingSettings

__all__ = ['BagFormatError', 'EvaluationSettings', 'IterationRow', 'Evaluation', 'evaluate_bag', 'true_state',
           'write_csv', 'plot_rows', 'main']

#: Topics the evaluation reads (images are never decoded).
TOPICS = ('/joint_states', '/arm/command', '/hand_pose', '/body_schema/estimate', '/body_schema/covariance',
          '/body_schema/true', '/body_schema/update_status', '/calibration/progress', '/body_schema/true_extrinsics')


class BagFormatError(ValueError):
    """The bag lacks what an evaluation needs (names the missing topic or message)."""


@dataclass(frozen=True)
class EvaluationSettings:
    """How the offline filter runs. Defaults equal the estimator node's defaults;
    :meth:`from_parameters` takes a run's parameters (e.g. ``config/estimator.yaml``).

    ``initial`` is 'recorded' (the first estimate and covariance in the bag, i.e. the online
    run's initial guess), 'perturbed' (seeded draw with ``initial_seed``, as the node does) or
    'nominal'. ``noise.noise_model`` 'pose_dependent' uses the recorded /hand_pose covariances,
    'constant' the CN baseline. ``noise_law`` (coefficients of
    :class:`body_schema.noise.PoseDependentNoise`, e.g. a ``noise_model:`` block that
    ``tools.fit_noise`` printed) replaces each recorded covariance by that law's at the observed
    hand pose, seen from the description's fixed camera, as the detector would have published it.
    """

    robot: str = 'icub_right_arm'
    initial: str = 'recorded'
    initial_seed: int = 0
    noise: NoiseSettings = NoiseSettings()
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    pairing: PairingSettings = field(default_factory=PairingSettings)
    noise_law: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.initial not in ('recorded', 'perturbed', 'nominal'):
            raise ValueError(f"initial must be 'recorded', 'perturbed' or 'nominal', got {self.initial!r}")

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any], initial: str = 'recorded') -> 'EvaluationSettings':
        """The settings of an estimator node run with parameters ``values`` (by parameter name)."""
        node, noise, estimator, pairing = settings_from_parameters(values)
        return cls(node.robot, initial, node.initial_seed, noise, estimator, pairing)


@dataclass(frozen=True)
class IterationRow:
    """Metrics after one iteration (iteration 0: the initial guess)."""

    iteration: int
    outcome: str
    detected: bool
    movement_deg: float
    discarded: int
    position_mm: float              # offline re-run
    orientation_deg: float
    online_position_mm: float       # the estimate the node published
    online_orientation_deg: float
    offline_updates: int
    selection_s: float
    sim_time: float
    # The information limit: the errors the offline posterior covariance implies over the box
    # (body_schema.metrics.expected_pose_errors), to set beside the achieved ones.
    expected_position_mm: float = float('nan')
    expected_orientation_deg: float = float('nan')


@dataclass
class Evaluation:
    """Result of :func:`evaluate_bag`."""

    rows: list[IterationRow]
    final_dh: NDArray[np.float64]           # offline, (L, 4)
    online_final_dh: NDArray[np.float64]    # last recorded estimate, (L, 4)
    true_dh: NDArray[np.float64]
    counters: dict[str, int]
    strategy: str
    #: What the bag held (``bag.loss``: what a crash of the recorder lost, empty when complete).
    bag: mcap_reader.BagSummary | None = None
    #: The pairing's time faults in the re-run (:attr:`~dh_estimator.pairing.ObservationPairer.counters`).
    pairing: dict[str, int] = field(default_factory=dict)
    # What the box cannot identify (body_schema.identifiability), and the final offline
    # estimate's NEES on the identifiable rest (chi-square with `identifiable` dof if consistent).
    unidentifiable: tuple[str, ...] = ()
    identifiable: int = 0
    nees_identifiable: float = float('nan')
    #: Parameters estimated (the table's, plus 6 per extrinsic block); 0: the table's.
    parameters: int = 0
    #: Per estimated extrinsic block ('camera', 'marker'): error (estimate - truth in the table's
    #: gauge) and one-sigma, 6 each (mm, mm, mm, deg, deg, deg); the truth from
    #: ``/body_schema/true_extrinsics`` (absent from older bags: error NaN).
    extrinsics: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = field(default_factory=dict)
    #: The re-run's innovations against its noise law (the check that needs no truth); None if
    #: no update followed the warm-up.
    innovations: InnovationCheck | None = None

    @property
    def outcome_counts(self) -> dict[str, int]:
        """How many iterations ended with each outcome (the initial row aside)."""
        counts: dict[str, int] = {}
        for r in self.rows[1:]:
            counts[r.outcome] = counts.get(r.outcome, 0) + 1
        return counts

    @property
    def nees_band(self) -> tuple[float, float] | None:
        """The 95 % chi-square band of :attr:`nees_identifiable` (None for an old evaluation)."""
        if not self.identifiable:
            return None
        return average_nees_band([self.identifiable])

    @property
    def max_online_offline_difference(self) -> float:
        """Largest absolute difference between the final offline and online tables."""
        return float(np.max(np.abs(self.final_dh - self.online_final_dh)))


def evaluate_bag(path: str | Path, settings: EvaluationSettings = EvaluationSettings()) -> Evaluation:
    """Re-run the filter on a bag and score every iteration.

    Parameters
    ----------
    path : str or Path
        MCAP file written by the recorder.
    settings : EvaluationSettings

    Returns
    -------
    Evaluation

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    calibration_interfaces.mcap_reader.BagError
        If ``path`` is empty or not an MCAP file.
    BagFormatError
        If the bag has no ``/body_schema/true`` or (for ``initial='recorded'``) no estimate
        recorded before the first update.
    """
    path = Path(path)
    bag = mcap_reader.summary(path)
    model = load_robot(settings.robot)
    x0: NDArray[np.float64] | None = None
    P0: NDArray[np.float64] | None = None  # noqa: N806
    if settings.initial == 'nominal':
        x0 = model.dh.copy()
    elif settings.initial == 'perturbed':
        x0 = sampling.perturb_dh(model.dh, settings.initial_seed)
    if x0 is not None:
        P0 = sampling.initial_covariance(model.n_joints)  # noqa: N806

    estimator: OnlineEstimator | None = None
    feeder: MessageFeeder | None = None
    evaluator: PoseErrorEvaluator | None = None
    true_dh = online = None
    true_extrinsics = None
    started = False                 # an update status seen: later estimates are not the initial one
    strategy = ''
    progress: list[tuple[dict[str, Any], NDArray[np.float64], NDArray[np.float64] | None, int]] = []
    backlog: list[tuple[str, Any, float]] = []    # inputs that arrive before the filter can start

    covariance_of = None
    if settings.noise_law:
        if not model.fixed_cameras:
            raise ValueError(f'noise_law: re-applying a law needs a fixed camera; {model.name!r} has none')
        law = PoseDependentNoise(**dict(settings.noise_law))
        camera = model.camera_pose(model.camera_names[0])

        def covariance_of(pose: NDArray[np.float64]) -> NDArray[np.float64]:
            return law.hand_covariance(camera, pose, model.markers)

    def start() -> None:
        nonlocal estimator, feeder
        estimator = OnlineEstimator(model, x0, P0, settings.estimator)
        feeder = MessageFeeder(ObservationPairer(estimator, settings.pairing), model.joint_names,
                               settings.noise.build() if settings.noise.constant else None, covariance_of)

    def feed(topic: str, msg: Any, now: float) -> None:
        try:
            feeder.feed(topic, msg, None if topic == '/hand_pose' else now)
        except MessageError:
            pass            # the node ignores it too (with a warning)

    # A camera pose / marker offset estimated with the table absorbs some of its parameters (held
    # at the description's values): the table is scored in that gauge, what the camera could see.
    cam_std, marker_std = settings.estimator.extrinsic_priors
    absorbed = list(absorbed_parameters(model.n_joints, cam_std is not None, marker_std is not None))
    n_cov = model.n_params + 6 * sum(s is not None for s in (cam_std, marker_std))
    order = 'publication' if mcap_reader.recording_metadata(path)['publish_time'] == PUBLISH_TIME_SOURCE else 'log'
    for topic, log_ns, msg in mcap_reader.read_messages(path, TOPICS, order):
        if topic == '/body_schema/true':
            true_dh = msg_to_table(msg, model.n_joints)
            scored = true_dh.copy()
            scored.ravel()[absorbed] = model.dh.ravel()[absorbed]
            evaluator = PoseErrorEvaluator(model.base, scored, model.calibration_box)
        elif topic == '/body_schema/true_extrinsics':
            true_extrinsics = msg_to_extrinsics(msg)
        elif topic == '/body_schema/estimate':
            online = msg_to_table(msg, model.n_joints)
            if x0 is None and not started:
                x0 = online.copy()
        elif topic == '/body_schema/covariance':
            if P0 is None and not started:
                P0 = msg_to_covariance(msg, n_cov)[:model.n_params, :model.n_params]  # noqa: N806
        elif topic == '/body_schema/update_status':
            started = True
        elif topic == '/calibration/progress':
            record = json.loads(msg.data)
            strategy = record.get('strategy', strategy)
            if estimator is None:
                raise BagFormatError(f'{path}: iteration {record.get("iteration")} recorded before any '
                                     'initial estimate and covariance; use initial=perturbed with its seed')
            progress.append((record, estimator.dh.copy(), None if online is None else online.copy(),
                             estimator.counters['updates'], estimator.P_dh.copy()))
        else:
            if estimator is None:
                if x0 is not None and P0 is not None:
                    start()
                    for item in backlog:
                        feed(*item)
                    backlog.clear()
                else:
                    backlog.append((topic, msg, log_ns * 1e-9))
                    continue
            feed(topic, msg, log_ns * 1e-9)
    if evaluator is None:
        raise BagFormatError(f'{path}: no /body_schema/true message; the evaluation needs the real table')
    if estimator is None:
        if x0 is None or P0 is None:
            raise BagFormatError(f'{path}: no initial estimate and covariance recorded')
        start()

    if progress:
        # Nothing follows the last iteration: what the recorder logged after its record (a topic it
        # fell behind on, under load) belongs to it, so the last row is the bag's final state.
        record = progress[-1][0]
        progress[-1] = (record, estimator.dh.copy(), None if online is None else online.copy(),
                        estimator.counters['updates'], estimator.P_dh.copy())

    def score(dh: NDArray[np.float64] | None) -> tuple[float, float]:
        if dh is None:
            return float('nan'), float('nan')
        e = evaluator(dh)
        return e.position_mm, e.orientation_deg

    def limit(dh: NDArray[np.float64], P: NDArray[np.float64]) -> tuple[float, float]:  # noqa: N803
        e = expected_pose_errors(model.base, dh, P, model.calibration_box)
        return e.position_mm, e.orientation_deg

    p0, o0 = score(x0)
    rows = [IterationRow(0, 'initial', False, 0.0, 0, p0, o0, p0, o0, 0, 0.0, 0.0, *limit(x0, P0))]
    for record, dh, online_dh, n_updates, P in progress:  # noqa: N806
        pos, ori = score(dh)
        opos, oori = score(online_dh)
        rows.append(IterationRow(int(record['iteration']), str(record['outcome']), bool(record['detected']),
                                 float(record['movement_deg']), int(record['discarded']), pos, ori, opos, oori,
                                 n_updates, float(record.get('selection_s', 0.0)),
                                 float(record.get('sim_time', 0.0)), *limit(dh, P)))
    ident = estimator.identifiability
    true_x, extrinsic_errors = true_state(estimator, true_dh, true_extrinsics)
    nees = (subspace_nees(estimator.x - true_x, estimator.P, ident.identifiable_basis)
            if true_x is not None else float('nan'))
    es = settings.estimator
    map_estimator = es.estimator == 'map'
    # Against the change test's bound; the EKF (no change test) and a MAP without one: its default's.
    innovations = innovation_check(estimator.innovations, es.warmup if map_estimator else es.gate_warmup,
                                   es.change_probability if map_estimator and es.change_probability > 0
                                   else MapSettings.change_probability)
    return Evaluation(rows, estimator.dh.copy(), x0 if online is None else online, true_dh,
                      estimator.counters, strategy, bag, dict(feeder.pairer.counters),
                      tuple(ident.describe()) if ident.n_unidentifiable else (), ident.rank, nees,
                      len(ident.names), extrinsic_errors, innovations)


def true_state(estimator: OnlineEstimator, true_dh: NDArray[np.float64],
               true_extrinsics: tuple[NDArray[np.float64], NDArray[np.float64]] | None
               ) -> tuple[NDArray[np.float64] | None, dict[str, tuple[tuple[float, ...], tuple[float, ...]]]]:
    """The truth as the estimator's state (None if unknown) and each extrinsic block's error and sigma.

    With extrinsics, the truth is taken in the estimate's gauge (:func:`body_schema.extrinsics.align_truth`):
    the parameters a camera or marker absorbs at the estimate's held values, the camera and the
    marker moved so that the camera sees the same. Either way the true table is first written as
    its kinematic twin nearest the estimate (:func:`body_schema.kinematics.equivalent_table`), so
    an estimate on the other branch of a DH symmetry is scored by what it does, not how it is
    written.
    """
    true_dh = equivalent_table(true_dh, estimator.dh)
    ex = estimator.extrinsics
    if ex is None:
        return true_dh.ravel(), {}
    sigma = np.sqrt(np.diag(estimator.P))[estimator.model.n_params:]
    deg = np.array([1e3] * 3 + [float(np.degrees(1.0))] * 3)
    if true_extrinsics is None:
        return None, {b: ((float('nan'),) * 6, tuple(float(v) for v in sigma[6 * i:6 * i + 6] * deg))
                      for i, b in enumerate(ex.blocks)}
    real_cam, real_marker = (perturb_pose(p, d) for p, d in zip((ex.camera, ex.marker), true_extrinsics))
    dh, cam, marker = align_truth(estimator.model.base, true_dh, real_cam, real_marker, estimator.dh,
                                  'camera' in ex.blocks, 'marker' in ex.blocks)
    truth = {'camera': pose_delta(cam, ex.camera), 'marker': pose_delta(marker, ex.marker)}
    true_x = np.concatenate([dh.ravel()] + [truth[b] for b in ex.blocks])
    errors = {}
    for i, b in enumerate(ex.blocks):
        start = estimator.model.n_params + 6 * i
        est_pose = perturb_pose(ex.camera if b == 'camera' else ex.marker, estimator.x[start:start + 6])
        err = pose_delta(est_pose, cam if b == 'camera' else marker)
        errors[b] = (tuple(float(v) for v in err * deg), tuple(float(v) for v in sigma[6 * i:6 * i + 6] * deg))
    return true_x, errors


def write_csv(rows: Sequence[IterationRow], path: str | Path) -> Path:
    """Write the rows as CSV (one line per iteration, header = field names)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(IterationRow.__dataclass_fields__))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    return path


def plot_rows(rows: Sequence[IterationRow], directory: str | Path, title: str = '') -> list[Path]:
    """Error vs iteration and error vs accumulated movement (PNG), offline and online.

    Returns the paths written: ``error_vs_iteration.png``, ``error_vs_movement.png``.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    it = np.array([r.iteration for r in rows])
    mv = np.array([r.movement_deg for r in rows])
    series = {'position error [mm]': ([r.position_mm for r in rows], [r.online_position_mm for r in rows]),
              'orientation error [deg]': ([r.orientation_deg for r in rows], [r.online_orientation_deg for r in rows])}
    failed = np.array([r.outcome in ('failed', 'unreachable', 'timeout') for r in rows])
    out = []
    for x, xlabel, name in ((it, 'iteration', 'error_vs_iteration.png'),
                            (mv, 'accumulated joint movement [deg]', 'error_vs_movement.png')):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
        limits = ([r.expected_position_mm for r in rows], [r.expected_orientation_deg for r in rows])
        for ax, (label, (offline, online)), limit in zip(axes, series.items(), limits):
            ax.semilogy(x, offline, '-o', ms=3, label='offline re-run')
            ax.semilogy(x, online, '--', lw=1, label='online estimate')
            ax.semilogy(x, limit, ':', lw=1.5, color='tab:green', label='information limit (from P)')
            if failed.any():
                ax.plot(x[failed], np.asarray(offline)[failed], 'x', color='tab:red', label='discarded sample')
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
            ax.grid(True, which='both', alpha=0.3)
        axes[0].legend()
        if title:
            fig.suptitle(title)
        fig.savefig(directory / name, dpi=110)
        plt.close(fig)
        out.append(directory / name)
    return out


def summary_text(ev: Evaluation) -> str:
    """A few lines: initial and final errors, movement, discarded samples, online/offline agreement."""
    first, last = ev.rows[0], ev.rows[-1]
    c = ev.counters
    faults = ', '.join(f'{k.replace("_", " ")} {n}' for k, n in ev.pairing.items() if n)
    return ((f'{ev.bag.loss}\n' if ev.bag is not None and ev.bag.loss else '')
            + (f'time faults in the re-run: {faults}\n' if faults else '')
            + f'iterations {last.iteration} ({ev.strategy or "unknown strategy"}), updates {c["updates"]}, '
            f'rejected {c["rejected"]}, outliers {c.get("outliers", 0)}, body changes detected '
            f'{c.get("changes", 0)}, discarded samples {last.discarded}\n'
            f'position error    {first.position_mm:8.2f} mm  -> {last.position_mm:7.2f} mm '
            f'(online {last.online_position_mm:.2f} mm)\n'
            f'orientation error {first.orientation_deg:8.2f} deg -> {last.orientation_deg:7.2f} deg '
            f'(online {last.online_orientation_deg:.2f} deg)\n'
            f'information limit {last.expected_position_mm:.2f} mm, {last.expected_orientation_deg:.2f} deg '
            '(the error the final covariance implies over the calibration box)\n'
            f'accumulated movement {last.movement_deg:.0f} deg; max |offline - online| DH difference '
            f'{ev.max_online_offline_difference:.2e}'
            + (f'\n{ev.innovations.text()}' if ev.innovations is not None else '')
            + identifiability_text(ev))


def identifiability_text(ev: Evaluation) -> str:
    """Lines on what the box cannot identify and the NEES on what it can ('' for an old evaluation)."""
    if not ev.identifiable:
        return ''
    n = ev.parameters or ev.final_dh.size
    band = ev.nees_band
    text = (f'\nidentifiable {ev.identifiable} of {n} parameter combinations; final NEES on them '
            f'{ev.nees_identifiable:.1f} (95% band {band[0]:.1f}-{band[1]:.1f})')
    for line in ev.unidentifiable:
        held = "the description's value" if ' held in the table' in line else 'the initial guess'
        text += f'\nnot identifiable (held at {held}): {line}'
    for block, (err, sigma) in ev.extrinsics.items():
        text += (f'\n{block} pose error (estimate - truth, in the table\'s gauge) '
                 f'{_six(err)} mm, deg; one-sigma {_six(sigma)}')
    return text


def _six(v: Sequence[float]) -> str:
    return f'[{", ".join(f"{x:.2f}" for x in v[:3])}] [{", ".join(f"{x:.3f}" for x in v[3:])}]'


def read_noise_law(path: str | Path) -> tuple[tuple[str, float], ...]:
    """The coefficients of the ``noise_model:`` block in the YAML file ``path`` (``covariance`` and
    ``loss_scale`` aside: :func:`read_noise_block` has them too).

    Raises
    ------
    ValueError
        Naming the file, if it has no ``noise_model`` mapping or a key or value the law refuses.
    """
    return read_noise_block(path)[0]


def read_noise_block(path: str | Path) -> tuple[tuple[tuple[str, float], ...], str, float]:
    """The ``noise_model:`` block in the YAML file ``path``: the law's coefficients, and the
    estimator's ``covariance`` ('' if not set) and ``loss_scale`` (0 if not set), for
    :func:`with_noise_law`.

    Raises
    ------
    ValueError
        As :func:`read_noise_law`.
    """
    data = yaml.safe_load(Path(path).read_text())
    block = data.get('noise_model') if isinstance(data, dict) else None
    if not isinstance(block, dict):
        raise ValueError(f"{path}: no 'noise_model:' mapping")
    law, covariance, loss_scale = parse_noise_law(block, f'{path}: noise_model')   # a description's parser
    try:
        PoseDependentNoise(**law)                                 # and the law's own (a singular covariance)
    except ValueError as exc:
        raise ValueError(f'{path}: noise_model: {exc}') from exc
    return tuple(law.items()), covariance, loss_scale


def with_noise_law(settings: EvaluationSettings,
                   block: tuple[tuple[tuple[str, float], ...], str, float]) -> EvaluationSettings:
    """``settings`` re-run as if the ``noise_model:`` ``block`` (:func:`read_noise_block`) were the
    description's: its law's covariance replaces each recorded one, and its ``covariance`` and
    ``loss_scale``, where the block sets them and ``settings`` leave them to the description,
    replace the description's.
    """
    law, covariance, loss_scale = block
    est = settings.estimator
    est = replace(est, covariance=est.covariance or covariance,
                  loss_scale=loss_scale if est.loss_scale < 0 and loss_scale > 0 else est.loss_scale)
    return replace(settings, noise_law=law, estimator=est)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='evaluate', description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument('bag', type=Path, help='MCAP file written by the recorder')
    ap.add_argument('--output', type=Path, help='directory for metrics.csv and the plots (default: next to the bag)')
    ap.add_argument('--params-file', type=Path,
                    help="the estimator's parameter file of the run (its dh_estimator section); "
                         'default: the node defaults')
    ap.add_argument('--initial', default='recorded', choices=['recorded', 'perturbed', 'nominal'])
    # Overrides of the run's parameters (None: keep the file's or the default value).
    ap.add_argument('--robot', help='packaged robot name or YAML path')
    ap.add_argument('--initial-seed', type=int)
    ap.add_argument('--noise-model', choices=list(NOISE_MODELS))
    ap.add_argument('--cn-sigma-pos', type=float, help='[m]')
    ap.add_argument('--cn-sigma-rot-deg', type=float, help='[deg]')
    ap.add_argument('--estimator', choices=list(ESTIMATORS), help="'map' (online MAP) or 'ekf' (the paper's)")
    ap.add_argument('--loss', choices=list(LOSSES), help='MAP robust loss')
    ap.add_argument('--loss-scale', type=float,
                    help="MAP: whitened residual where the robust loss departs from the square [sigma] (default: "
                         "the robot description's noise_model.loss_scale, else 3)")
    ap.add_argument('--covariance', choices=list(COVARIANCES),
                    help="MAP posterior covariance (default: the robot description's, else 'sandwich')")
    ap.add_argument('--change-probability', type=float, help='MAP change detection (0: off)')
    ap.add_argument('--iterations', type=int, help='EKF linearisations per update')
    ap.add_argument('--gate-probability', type=float)
    ap.add_argument('--gate-warmup', type=int)
    ap.add_argument('--camera-prior', help="MAP: the camera pose estimated with the table, prior '<m> <deg>'")
    ap.add_argument('--marker-prior', help="MAP: the marker offset estimated with the table, prior '<m> <deg>'")
    ap.add_argument('--parallel-std', type=float,
                    help="MAP: prior [m] holding what only parallel axes hide (negative: the initial guess's "
                         'spread; 0: pinned, as before)')
    ap.add_argument('--noise-law', type=Path,
                    help="a YAML with a 'noise_model:' block (what tools.fit_noise prints): its law's covariance "
                         'replaces each recorded one (a fixed camera only), and its covariance and loss_scale '
                         "keys are the estimator's, as if it were the description's")
    ap.add_argument('--no-plots', action='store_true', help='write the CSV only')
    return ap


_OVERRIDES = ('robot', 'initial_seed', 'noise_model', 'cn_sigma_pos', 'cn_sigma_rot_deg', 'estimator', 'loss',
              'loss_scale', 'covariance', 'change_probability', 'iterations', 'gate_probability', 'gate_warmup',
              'camera_prior', 'marker_prior', 'parallel_std')


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``evaluate``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        values = dict(read_params_file(args.params_file, 'dh_estimator')) if args.params_file else {}
        values.update({k: getattr(args, k) for k in _OVERRIDES if getattr(args, k) is not None})
        settings = EvaluationSettings.from_parameters(values, initial=args.initial)
        if args.noise_law is not None:
            settings = with_noise_law(settings, read_noise_block(args.noise_law))
        ev = evaluate_bag(args.bag, settings)
    except (FileNotFoundError, ValueError) as exc:
        print(f'evaluate: {exc}', file=sys.stderr)
        return 2
    out = args.output or args.bag.parent
    paths = [write_csv(ev.rows, out / 'metrics.csv')]
    if not args.no_plots:
        paths += plot_rows(ev.rows, out, title=f'{args.bag.name}: {ev.strategy}, noise {settings.noise.noise_model}')
    print(summary_text(ev))
    print('wrote ' + ' '.join(str(p) for p in paths))
    return 0


if __name__ == '__main__':
    sys.exit(main())
