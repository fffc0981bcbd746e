"""Replay the detector's real errors through the online estimator under several settings (no ROS).

Consistency is a property of the estimator *and* the detector's error distribution, which a
synthetic study draws from the noise law and so cannot test. This command renders ``--n``
uniform configurations of the description's box once (the nominal table, camera and marker: the
truth), keeps every hand pose the detector accepts with its published covariance, then for each
of ``--trials`` trials offers a random ``--observations`` of them to a fresh
:class:`dh_estimator.estimator.OnlineEstimator` from the paper's wide initial guess, under each
``--variant`` of its settings, and scores the final estimate: NEES over the identifiable
subspace against its 95 % band, body changes detected (all false: the body does not change),
outliers flagged and the mean flange error over the box. Every variant meets the same trials.

Usage (from the repository root)::

    python -m tools.error_replay --robot ur5e --camera-prior "0.02 2" --marker-prior "0.005 5" \\
        --pool results/replay/ur5e-600-7.npz \\
        --variant covariance=gauss_newton --variant covariance=sandwich --variant ""

A variant is comma-separated ``name=value`` pairs of
:class:`dh_estimator.estimator.EstimatorSettings` fields (typed by their defaults); an empty one
is the defaults (the covariance the robot description names). Each variant's row also says
whether the trials' average NEES lies in its own band (:func:`body_schema.identifiability.average_nees_band`).
``--pool`` keeps the rendered detections, so that a later comparison skips the rendering.

``--true-body perturbed`` makes each trial's real arm a perturbed table (4 mm / 2 deg, as the
simulator's), each detection its error on the nominal arm carried onto that arm's hand pose
(:func:`carry_errors`): the estimator then meets what a live run meets, including axes that are
parallel only nominally (a UR's joints 2-4 are a fraction of a degree apart on the perturbed
arm, so holding their ``d`` at a wrong guess biases the rest), which the nominal truth hides.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from body_schema import sampling
from body_schema.identifiability import average_nees_band, subspace_nees
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import PoseDependentNoise
from body_schema.robot import ArmModel, load_robot

from dh_estimator.estimator import EstimatorSettings, OnlineEstimator
from dh_estimator.evaluate import true_state
from marker_detector.detection import DetectorConfig, HandPoseEstimator, gate_marker
from tools.fit_noise import views_of

__all__ = ['parse_variant', 'observations', 'cached_observations', 'carry_errors', 'replay', 'main']

Observation = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]     # q, pose, R


def parse_variant(text: str) -> dict[str, Any]:
    """``"covariance=sandwich,change_window=4"`` -> EstimatorSettings overrides, typed by the defaults.

    Raises
    ------
    ValueError
        If a pair is not ``name=value``, the name is not a setting, or the value does not parse.
    """
    defaults = {f.name: f.default for f in dataclasses.fields(EstimatorSettings)}
    out: dict[str, Any] = {}
    for pair in filter(None, (p.strip() for p in text.split(','))):
        name, sep, value = pair.partition('=')
        if not sep or name not in defaults:
            raise ValueError(f'variant {text!r}: {pair!r} is not name=value of an EstimatorSettings field')
        kind = type(defaults[name])
        try:
            out[name] = kind(value)
        except ValueError:
            raise ValueError(f'variant {text!r}: {name} takes a {kind.__name__}, got {value!r}') from None
    return out


def observations(model: ArmModel, n: int, seed: int) -> list[Observation]:
    """Render ``n`` configurations of the box; the accepted hand poses with their covariance."""
    from icub_sim_bridge.world import SimWorld
    from tools.detector_accuracy import collect

    configs = sampling.uniform_configs(model.calibration_box, n, seed)
    with SimWorld(model) as world:
        frames = collect(model, world, configs, views_of(model)[:1], seed=seed)
    detector = HandPoseEstimator(model, PoseDependentNoise.for_robot(model), DetectorConfig())
    out = []
    for f in frames:
        hand = detector.combine([gate_marker(p, detector.config) for p in f.poses], f.k, None, f.root_T_cam)
        if hand is not None:
            out.append((configs[f.config], hand.pose, hand.covariance))
    return out


def cached_observations(model: ArmModel, n: int, seed: int, path: Path | None) -> list[Observation]:
    """:func:`observations`, read from / written to ``path`` (an .npz keyed by robot, n and seed).

    Raises
    ------
    ValueError
        If ``path`` holds the detections of another robot, ``n`` or ``seed``.
    """
    key = f'{model.name}/{n}/{seed}'
    if path is not None and path.exists():
        with np.load(path) as d:
            if str(d['key']) != key:
                raise ValueError(f'{path} holds the detections of {d["key"]}, not {key} (robot/n/seed)')
            return list(zip(d['q'], d['pose'], d['R']))
    pool = observations(model, n, seed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, key=key, q=np.array([o[0] for o in pool]), pose=np.array([o[1] for o in pool]),
                 R=np.array([o[2] for o in pool]))
    return pool


#: Full widths (length [m], angle [rad]) of the real arm's perturbation: the simulator's (``sim.yaml``).
TRUE_BODY_WIDTHS = (0.004, float(np.radians(2.0)))


def carry_errors(model: ArmModel, pool: Sequence[Observation], true_dh: NDArray[np.float64]) -> list[Observation]:
    """The detections as if the arm had table ``true_dh``: each one's error on the nominal arm
    (position difference, rotation ``R_z R_h^T``; the estimator's residual) applied to the hand
    pose of ``true_dh`` at the same joints, its covariance kept."""
    real = model.with_dh(true_dh)
    out = []
    for q, pose, R in pool:  # noqa: N806
        nominal, hand = model.forward_kinematics(q), real.forward_kinematics(q)
        moved = np.eye(4)
        moved[:3, :3] = pose[:3, :3] @ nominal[:3, :3].T @ hand[:3, :3]
        moved[:3, 3] = hand[:3, 3] + pose[:3, 3] - nominal[:3, 3]
        out.append((q, moved, R))
    return out


def replay(model: ArmModel, pool: Sequence[Observation], settings: EstimatorSettings, trials: int,
           n_obs: int, perturbed: bool = False) -> dict[str, NDArray[np.float64]]:
    """Per trial: NEES, changes, outliers, flange error [mm] of the final estimate; the NEES's band and dof.

    With ``perturbed`` each trial's real arm is ``sampling.perturb_dh(model.dh, 1000 + trial, *TRUE_BODY_WIDTHS)``
    and the detections are carried onto it (:func:`carry_errors`)."""
    rows: dict[str, list[float]] = {k: [] for k in ('nees', 'changes', 'outliers', 'position_mm')}
    for t in range(trials):
        idx = np.random.default_rng(100 + t).choice(len(pool), n_obs, replace=False)
        true_dh = sampling.perturb_dh(model.dh, 1000 + t, *TRUE_BODY_WIDTHS) if perturbed else model.dh
        chosen = [pool[i] for i in idx]
        if perturbed:
            chosen = carry_errors(model, chosen, true_dh)
        est = OnlineEstimator(model, sampling.perturb_dh(model.dh, t + 1), sampling.initial_covariance(model.n_joints),
                              settings)
        for obs in chosen:
            est.offer(*obs)
        zero = (np.zeros(6), np.zeros(6)) if est.extrinsics is not None else None
        true_x, _ = true_state(est, true_dh, zero)
        basis = est.identifiability.identifiable_basis
        rows['nees'].append(subspace_nees(est.x - true_x, est.P, basis))
        rows['changes'].append(est.counters['changes'])
        rows['outliers'].append(est.counters['outliers'])
        rows['position_mm'].append(
            PoseErrorEvaluator(model.base, true_x[:model.n_params].reshape(model.dh.shape),
                               model.calibration_box)(est.dh).position_mm)
    dof = int(basis.shape[1])
    return {**{k: np.array(v) for k, v in rows.items()}, 'band': np.asarray(average_nees_band([dof])), 'dof': dof}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.error_replay', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', default='ur5e')
    ap.add_argument('--n', type=int, default=600, help='configurations rendered')
    ap.add_argument('--seed', type=int, default=7)
    ap.add_argument('--trials', type=int, default=24)
    ap.add_argument('--observations', type=int, default=50)
    ap.add_argument('--camera-prior', default='', help='as the estimator parameter, e.g. "0.02 2"')
    ap.add_argument('--marker-prior', default='', help='e.g. "0.005 5"')
    ap.add_argument('--variant', action='append', default=[],
                    help='name=value[,name=value]; repeatable; "" is the defaults (the description\'s covariance)')
    ap.add_argument('--true-body', choices=('nominal', 'perturbed'), default='nominal',
                    help='the real arm: the nominal table, or per trial a perturbed one (4 mm / 2 deg) carrying '
                         'the same detection errors')
    ap.add_argument('--pool', type=Path, default=None,
                    help='.npz of the accepted detections: loaded if it exists (for the same --robot, '
                         '--n and --seed), else rendered and saved there')
    args = ap.parse_args(argv)
    try:
        variants = [parse_variant(v) for v in (args.variant or [''])]
    except ValueError as exc:
        ap.error(str(exc))
    if args.trials < 1 or args.observations < 1:
        ap.error(f'--trials and --observations must be >= 1, got {args.trials} and {args.observations}')
    model = load_robot(args.robot)
    t0 = time.perf_counter()
    try:
        pool = cached_observations(model, args.n, args.seed, args.pool)
    except ValueError as exc:
        ap.error(str(exc))
    if len(pool) < args.observations:
        print(f'error_replay: only {len(pool)} accepted detections, fewer than --observations '
              f'{args.observations}', file=sys.stderr)
        return 1
    lines = [f'{len(pool)} accepted detections of {args.n} configurations ({model.name}, seed {args.seed}), '
             f'{args.trials} trials of {args.observations}; priors camera {args.camera_prior or "known"}, '
             f'marker {args.marker_prior or "known"}; real arm {args.true_body}.', '',
             '| variant | NEES median (mean) | in the 95% band | average NEES in its 95% band | trials with a (false) '
             'change | outliers / trial | flange error [mm] mean / median / max |', '|---|---|---|---|---|---|---|']
    for v in variants:
        settings = EstimatorSettings(camera_prior=args.camera_prior, marker_prior=args.marker_prior, **v)
        r = replay(model, pool, settings, args.trials, args.observations, args.true_body == 'perturbed')
        inside = int(np.sum((r['nees'] >= r['band'][0]) & (r['nees'] <= r['band'][1])))
        lo, hi = average_nees_band([r['dof']] * args.trials)
        mean = float(np.mean(r['nees']))
        name = ', '.join(f'{k}={val}' for k, val in v.items()) or 'defaults'
        lines.append(f'| {name} | {np.median(r["nees"]):.1f} ({np.mean(r["nees"]):.3g}) | {inside} of {args.trials} '
                     f'({r["band"][0]:.1f}-{r["band"][1]:.1f}) | '
                     f'{"yes" if lo <= mean <= hi else "no"} ({lo:.1f}-{hi:.1f}) | '
                     f'{int(np.sum(r["changes"] > 0))} | '
                     f'{np.mean(r["outliers"]):.1f} | {np.mean(r["position_mm"]):.2f} / '
                     f'{np.median(r["position_mm"]):.2f} / {np.max(r["position_mm"]):.2f} |')
        print(lines[-1], flush=True)
    lines.append(f'\n_{time.perf_counter() - t0:.0f} s._')
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main())
