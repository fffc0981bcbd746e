"""Nearby views: are their detection errors independent, and how often do a selector's runs revisit?

A selector that pays for movement (UCSAL) can spend its iterations a hair away from where the arm
already is. Two questions decide what such observations are worth:

1. **Are the detector's errors at two nearby views independent?** ``--n N`` renders ``N``
   uniform configurations of the calibration box and the same configurations moved by each
   ``--deltas`` (degrees, max-abs over the joints, along a seeded random direction), runs the
   detector on each, and prints, for the left eye alone, for both images' corners refined
   together (where both eyes see the hand) and for the estimate the detector publishes (that,
   else the eye that sees), ``median |e_d - e_0| / median |e_0|`` in position and rotation over the
   configurations where both views were detected: about 1.41 when the two errors are
   independent with one spread, 0 when the second view repeats the first one's error.
2. **How often does a run revisit?** ``--runs DIR`` reads the targets (``/arm/command``) of an
   experiment's recorded runs (``runs/<method>/repNN.mcap``) and prints per method how many
   targets per run lie within 1 and 5 deg (max-abs) of an earlier one, and the median distance
   to the nearest earlier target.

Usage (from the repository root)::

    python -m tools.nearby_views --n 800 --seed 7
    python -m tools.nearby_views --runs results/experiment-ours --methods AL UCSAL CCSAL --repetitions 20

Exit status 1 when a requested run has no recording (the table then covers fewer runs), 2 when
no requested run has one.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from body_schema import load_robot
from body_schema.map_estimator import pose_residuals
from body_schema.noise import PoseDependentNoise
from body_schema.robot import ArmModel
from body_schema.sampling import uniform_configs

__all__ = ['difference_ratio', 'nearest_earlier', 'detection_errors', 'views_table', 'runs_table', 'main']

#: Resolution the graph renders at.
SIZE = (320, 240)


def difference_ratio(e0: NDArray[np.float64], ed: NDArray[np.float64]) -> float:
    """``median |ed - e0| / median |e0|`` over the rows where both are finite.

    Parameters
    ----------
    e0, ed : ndarray, shape (N, k)
        Error vectors of the same N configurations seen twice.

    Returns
    -------
    float
        About sqrt(2) for independent errors of one spread, 0 for a repeated error; NaN when no
        row has both.
    """
    ok = np.isfinite(e0).all(axis=1) & np.isfinite(ed).all(axis=1)
    if not ok.any():
        return float('nan')
    return float(np.median(np.linalg.norm(ed[ok] - e0[ok], axis=1)) / np.median(np.linalg.norm(e0[ok], axis=1)))


def nearest_earlier(targets: NDArray[np.float64]) -> NDArray[np.float64]:
    """Max-abs distance of each target to the nearest earlier one.

    Parameters
    ----------
    targets : ndarray, shape (N, L)
        Joint targets in the order commanded (any unit).

    Returns
    -------
    ndarray, shape (N - 1,)
        For targets 1 .. N - 1, in the unit of ``targets``.
    """
    t = np.asarray(targets, dtype=float)
    return np.array([np.abs(t[:i] - t[i]).max(axis=1).min() for i in range(1, len(t))])


def detection_errors(model: ArmModel, world: Any, configs: NDArray[np.float64]
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The detector's hand-pose errors at each configuration, left eye alone and as published.

    Parameters
    ----------
    model : ArmModel
        A robot with eyes.
    world : icub_sim_bridge.world.SimWorld
        Built from ``model``'s nominal table.
    configs : ndarray, shape (N, L)

    Returns
    -------
    left, stereo, published : ndarray, shape (N, 6)
        Position [m] and rotation vector [rad] of estimate minus truth (root frame) of the left
        eye's estimate, of the both-image refinement (where both eyes see the hand) and of what
        the detector publishes (that, else the eye that sees); NaN rows where there is none.
    """
    from marker_detector.detection import DetectorConfig, HandPoseEstimator
    from marker_detector.stereo import EyeResult, combine

    from .detector_accuracy import collect, eye_result

    est = HandPoseEstimator(model, PoseDependentNoise.for_robot(model), DetectorConfig())
    frames = collect(model, world, configs, [('left', SIZE), ('right', SIZE)])
    left = np.full((len(configs), 6), np.nan)
    stereo = np.full((len(configs), 6), np.nan)
    published = np.full((len(configs), 6), np.nan)
    for i in range(len(configs)):
        fl, fr = frames[2 * i], frames[2 * i + 1]
        views = {f.eye: EyeResult(f.eye, None, *eye_result(f, est), 0.0) for f in (fl, fr)}
        if views['left'].result.hand is not None:
            left[i] = pose_residuals(views['left'].result.hand.pose[None], fl.truth[None])[0]
        hand = combine(views, estimator=est)[2]       # what the detector node publishes for the stamp
        if hand is not None:
            published[i] = pose_residuals(hand.pose[None], fl.truth[None])[0]
            if all(v.result.hand is not None for v in views.values()):
                stereo[i] = published[i]
    return left, stereo, published


def views_table(n: int, seed: int, deltas: Sequence[float], robot: str = 'icub_right_arm') -> list[str]:
    """Markdown lines: the difference ratio per delta, for each estimate of :func:`detection_errors`."""
    from icub_sim_bridge.world import SimWorld

    model = load_robot(robot)
    base = uniform_configs(model.calibration_box, n, seed)
    rng = np.random.default_rng(seed + 1)
    direction = rng.uniform(-1.0, 1.0, base.shape)
    direction /= np.abs(direction).max(axis=1, keepdims=True)             # max-abs 1 per configuration
    with SimWorld(model) as world:
        errs = {d: detection_errors(model, world, base + np.radians(d) * direction) for d in (0.0, *deltas)}
    lines = [f'{robot}: {n} uniform configurations of the box (seed {seed}), each seen again moved by delta '
             f'(max-abs over the joints); median |e_d - e_0| / median |e_0| (independent errors of one spread: '
             f'1.41; one error repeated: 0)', '',
             '| delta [deg] | left eye: n | position | rotation | both eyes: n | position | rotation '
             '| published: n | position | rotation |', '|---|---|---|---|---|---|---|---|---|---|']
    for d in deltas:
        row = [f'{d:g}']
        for k in (0, 1, 2):
            e0, ed = errs[0.0][k], errs[d][k]
            both = int((np.isfinite(e0).all(axis=1) & np.isfinite(ed).all(axis=1)).sum())
            row += [str(both), f'{difference_ratio(e0[:, :3], ed[:, :3]):.2f}',
                    f'{difference_ratio(e0[:, 3:], ed[:, 3:]):.2f}']
        lines.append('| ' + ' | '.join(row) + ' |')
    return lines


def _targets(path: Path) -> NDArray[np.float64]:
    from calibration_interfaces.mcap_reader import read_messages

    return np.array([list(m.points[-1].positions) for _, _, m in read_messages(path, ['/arm/command'])
                     if m.points])


def runs_table(root: Path, methods: Sequence[str], repetitions: int) -> tuple[list[str], int, int]:
    """Markdown lines: revisits per run for each method; how many requested runs were read, and
    how many had no recording."""
    lines = [f'{root}: targets per run (`/arm/command`) within 1 and 5 deg (max-abs) of an earlier target',
             '', '| method | runs | within 1 deg | within 5 deg | targets per run | median nearest earlier [deg] |',
             '|---|---|---|---|---|---|']
    read, missing = 0, 0
    for method in methods:
        near1, near5, count, median = [], [], [], []
        for rep in range(repetitions):
            path = root / 'runs' / method / f'rep{rep:02d}.mcap'
            if not path.exists():
                missing += 1
                continue
            t = np.degrees(_targets(path))
            d = nearest_earlier(t) if len(t) > 1 else np.zeros(0)
            near1.append(int((d < 1.0).sum()))
            near5.append(int((d < 5.0).sum()))
            count.append(len(t))
            median.append(float(np.median(d)) if d.size else float('nan'))
        read += len(count)
        if count:
            lines.append(f'| {method} | {len(count)} | {np.mean(near1):.1f} | {np.mean(near5):.1f} | '
                         f'{np.mean(count):.1f} | {np.nanmean(median):.1f} |')
        else:
            lines.append(f'| {method} | 0 | | | | |')
    return lines, read, missing


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.nearby_views', description=__doc__.split('\n')[0])
    ap.add_argument('--n', type=int, default=0, help='configurations to render (0: none)')
    ap.add_argument('--seed', type=int, default=7)
    ap.add_argument('--deltas', type=float, nargs='+', default=[0.12, 0.25, 0.5, 1.0, 2.0, 5.0],
                    help='moves [deg, max-abs over the joints]')
    ap.add_argument('--robot', default='icub_right_arm', help='a robot with eyes')
    ap.add_argument('--runs', type=Path, help='an experiment output directory with recordings')
    ap.add_argument('--methods', nargs='+', default=['AL', 'UCSAL', 'CCSAL'])
    ap.add_argument('--repetitions', type=int, default=20)
    args = ap.parse_args(argv)
    if not args.n and args.runs is None:
        ap.error('give --n (render) or --runs (count revisits), or both')
    status = 0
    if args.n:
        print('\n'.join(views_table(args.n, args.seed, args.deltas, args.robot)), '', sep='\n')
    if args.runs is not None:
        lines, read, missing = runs_table(args.runs, args.methods, args.repetitions)
        print('\n'.join(lines))
        if missing:
            print(f'nearby_views: {missing} requested run(s) have no recording', file=sys.stderr)
            status = 1 if read else 2
    return status


if __name__ == '__main__':
    sys.exit(main())
