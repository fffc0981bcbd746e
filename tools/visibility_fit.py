"""Fit the geometric visibility prior (:class:`body_schema.occlusion.VisibilityPrior`) to rendered detections.

For each seed's real robot (:func:`tools.selector_study.true_table`), ``--configs`` uniform
configurations of the calibration box are rendered in the left eye and run through the detector;
the prior's angle and margin constants are then chosen by maximum likelihood on a grid, with the
markers placed by the true table (no estimate error: the acquisition widens the prior by the
estimate's own uncertainty). Prints the fit and how well calibrated it is, per probability bin::

    python -m tools.visibility_fit --seeds 3 --configs 400
"""
from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import replace
from typing import Sequence

import cv2
import numpy as np

from body_schema import load_robot, kinematics
from body_schema.noise import PoseDependentNoise
from body_schema.occlusion import VisibilityPrior
from body_schema.robot import ArmModel
from body_schema.sampling import uniform_configs

from .selector_study import true_table

__all__ = ['seen_by_eye', 'detections', 'fit', 'main']

#: Grid of the fit: (max angle deg, angle softness deg, margin, margin softness, ceiling).
GRID = {'max_view_angle_deg': (55.0, 60.0, 65.0, 70.0, 75.0, 80.0), 'angle_softness_deg': (3.0, 5.0, 8.0, 12.0),
        'margin': (0.0, 0.02, 0.04, 0.06, 0.08, 0.1), 'margin_softness': (0.01, 0.02, 0.04),
        'ceiling': (0.85, 0.9, 0.95)}


def seen_by_eye(model: ArmModel, dh: np.ndarray, configs: np.ndarray,
                eyes: Sequence[str] = ('left',)) -> np.ndarray:
    """Whether the detector finds the hand (K, E) in each eye's rendering of the arm with table
    ``dh`` (L, 4) at ``configs`` (K, L)."""
    from icub_sim_bridge.world import SimWorld
    from marker_detector.detection import HandPoseEstimator

    detector = HandPoseEstimator(model, PoseDependentNoise())
    seen = np.zeros((len(configs), len(eyes)), dtype=bool)
    with SimWorld(model, dh, head_pose=model.eyes.head_pose) as world:
        for i, theta in enumerate(configs):
            world.set_joint_positions(theta)
            for j, eye in enumerate(eyes):
                cam = model.camera_pose(eye)
                gray = cv2.cvtColor(world.render(cam, model.camera), cv2.COLOR_RGB2GRAY)
                seen[i, j] = detector.process(gray, model.camera.K, None, cam).success
    return seen


def detections(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Marker poses (n, M, 4, 4) under the true table of ``seed`` and whether the detector saw the hand (n,)."""
    model = load_robot()
    dh = true_table(model, seed)
    q = uniform_configs(model.calibration_box, n, seed)
    markers = np.stack([m.hand_T_marker for m in model.markers])
    return kinematics.chain_frames(model.base, dh, q)[:, -1, None] @ markers, seen_by_eye(model, dh, q)[:, 0]


def fit(camera_pose: np.ndarray, marker_poses: np.ndarray, seen: np.ndarray,
        start: VisibilityPrior) -> tuple[VisibilityPrior, float]:
    """The grid point of :data:`GRID` with the highest mean log-likelihood, and that likelihood."""
    best, best_ll = start, -np.inf
    for values in itertools.product(*GRID.values()):
        prior = replace(start, **dict(zip(GRID, values)))
        p = prior.probability(camera_pose, marker_poses)
        ll = float(np.mean(np.where(seen, np.log(p), np.log1p(-p))))
        if ll > best_ll:
            best, best_ll = prior, ll
    return best, best_ll


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, default=3, help='real robots (seeds 0 .. N-1)')
    ap.add_argument('--configs', type=int, default=400, help='rendered configurations per robot')
    args = ap.parse_args(argv)
    model = load_robot()
    data = [detections(s, args.configs) for s in range(args.seeds)]
    poses = np.concatenate([d[0] for d in data])
    seen = np.concatenate([d[1] for d in data])
    cam = model.camera_pose('left')
    default = VisibilityPrior(model.camera)
    prior, ll = fit(cam, poses, seen, default)
    rate = seen.mean()
    p = default.probability(cam, poses)
    ll_default = float(np.mean(np.where(seen, np.log(p), np.log1p(-p))))
    print(f'{seen.size} configurations, {100 * rate:.1f} % detected; mean log-likelihood: best fit {ll:.3f}, '
          f'defaults {ll_default:.3f}, constant rate {rate * np.log(rate) + (1 - rate) * np.log1p(-rate):.3f}')
    for name, v in (('best fit', prior), ('defaults', default)):
        print(f'{name}: ' + ', '.join(f'{k} = {getattr(v, k):g}' for k in GRID))
    print('\nthe defaults, calibration:\n\n| predicted | configurations | detected |\n|---|---|---|')
    for lo, hi in ((0.0, 0.1), (0.1, 0.5), (0.5, 0.8), (0.8, 1.0)):
        sel = (p >= lo) & (p < hi) if hi < 1.0 else p >= lo
        print(f'| {lo:.1f}-{hi:.1f} | {sel.sum()} | '
              + (f'{100 * seen[sel].mean():.0f} % |' if sel.any() else '- |'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
