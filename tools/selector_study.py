"""A ROS-free replica of the calibration loop, for choosing the selector's constants.

The same pieces as the node graph, called directly: the PyBullet world renders the left eye at
the selected configuration, the detector's pure module estimates the hand pose, the estimator's
pure module updates, the planner learns the outcome. No motion is simulated (the arm is placed),
so one iteration costs a render, a detection, an update and a selection. Used to choose gamma,
delta, the arctan penalty and the occlusion kernel by measurement (``python -m
tools.selector_study --help``); the reported results always come from the real node graph.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import cv2
import numpy as np

from body_schema import ArmModel, load_robot, sampling
from body_schema.acquisition import CRITERIA, OCCLUSION_MODES, OPTIMIZERS, SelectorConfig
from body_schema.metrics import PoseErrorEvaluator
from body_schema.noise import ConstantNoise, NoiseModel, PoseDependentNoise
from calibration_interfaces.outcome import Outcome
from dh_estimator.estimator import EstimatorSettings, OnlineEstimator

from active_selector.loop import CalibrationLoop, LoopSettings
from active_selector.planner import OCCLUSION_PRIORS, Planner, PlannerSettings

__all__ = ['EpisodeResult', 'run_episode', 'run_seed', 'main']

_DEF = PlannerSettings()


@dataclass(frozen=True)
class EpisodeResult:
    position_mm: list[float]          # after each iteration (index 0: initial guess)
    orientation_deg: list[float]
    movement_deg: list[float]
    discarded: int
    seconds: float
    #: (q, pose, R) of every observation the estimator used, in order.
    observations: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    #: The estimator at the end of the run.
    estimator: OnlineEstimator | None = None


class _StepClock:
    """Simulated seconds that pass only when the harness says so."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float = 0.05) -> float:
        self.t += dt
        return self.t


def run_episode(model: ArmModel, world: object, x0: np.ndarray,
                settings: PlannerSettings, noise: NoiseModel, iterations: int,
                start: np.ndarray, evaluator: PoseErrorEvaluator,
                estimator_settings: EstimatorSettings = EstimatorSettings(),
                on_select: Callable[[Planner, np.ndarray, np.ndarray], None] | None = None) -> EpisodeResult:
    """One calibration run of ``iterations`` attempts; errors scored after each.

    ``on_select(planner, dh, P)``, if given, sees the selection state before each selection
    (the acquisition benchmark records states with it).
    """
    from marker_detector.detection import HandPoseEstimator

    cam = model.camera_pose('left')
    k = model.camera.K
    detector = HandPoseEstimator(model, noise)
    est = OnlineEstimator(model, x0, sampling.initial_covariance(model.n_joints), estimator_settings)
    planner = Planner(model, noise, settings)
    planner.start = start
    clock = _StepClock()
    loop = CalibrationLoop(planner, LoopSettings(iterations=iterations), clock)
    loop.joint_state(clock(), start)
    pos, rot, mov = [evaluator(x0).position_mm], [evaluator(x0).orientation_deg], [0.0]
    used = []
    t0 = time.perf_counter()
    while not loop.done:
        if on_select is not None:
            on_select(planner, est.dh, est.P)
        theta = loop.select(est.dh, est.P, cam)
        world.set_joint_positions(theta)            # placed, not moved: it settles at once
        for _ in range(2):
            loop.joint_state(clock.advance(), theta)
        gray = cv2.cvtColor(world.render(cam, model.camera), cv2.COLOR_RGB2GRAY)
        res = detector.process(gray, k, None, cam)
        it = loop.markers(clock.advance(loop.settings.settle_time), res.success)
        if it is None:
            outcome = est.offer(theta, res.hand.pose, res.hand.covariance)
            if outcome in (Outcome.ACCEPTED, Outcome.OUTLIER):
                used.append((theta, res.hand.pose, res.hand.covariance))
            it = loop.estimator_outcome(outcome.value, theta)
        if it is None:                              # not a final verdict (duplicate): the node times out
            clock.advance(2 * loop.settings.outcome_timeout)
            it = loop.tick()
        e = evaluator(est.dh)
        pos.append(e.position_mm)
        rot.append(e.orientation_deg)
        mov.append(it.attempt.movement_deg)
    return EpisodeResult(pos, rot, mov, planner.discarded, time.perf_counter() - t0, used, est)


def true_table(model: ArmModel, seed: int) -> np.ndarray:
    """The real robot of run ``seed``: the nominal table perturbed by 4 mm / 2 deg (seed ``1000 + seed``)."""
    return sampling.perturb_dh(model.dh, 1000 + seed, 0.004, np.radians(2.0))


def initial_guess(model: ArmModel, seed: int) -> np.ndarray:
    """The initial guess of run ``seed``: a draw with the paper's widths around the nominal table."""
    return sampling.perturb_dh(model.dh, seed)


def run_seed(model: ArmModel, noise: NoiseModel, settings: PlannerSettings, seed: int, iterations: int,
             ekf_iterations: int = 5,
             on_select: Callable[[Planner, np.ndarray, np.ndarray], None] | None = None,
             estimator: str = 'map') -> EpisodeResult:
    """One seeded run: a real robot perturbed by 4 mm / 2 deg (seed ``1000 + seed``), an initial
    guess with the paper's widths (``seed``), the selector seeded with ``seed``, start at the box centre."""
    from icub_sim_bridge.world import SimWorld

    true_dh = true_table(model, seed)
    x0 = initial_guess(model, seed)
    evaluator = PoseErrorEvaluator(model.base, true_dh, model.calibration_box)
    with SimWorld(model, true_dh, head_pose=model.eyes.head_pose) as world:
        s = replace(settings, selector=replace(settings.selector, seed=seed))
        return run_episode(model, world, x0, s, noise, iterations, model.calibration_box.mean(axis=1),
                           evaluator, EstimatorSettings(estimator=estimator, iterations=ekf_iterations), on_select)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--strategy', default='al')
    ap.add_argument('--iterations', type=int, default=50)
    ap.add_argument('--seeds', type=int, default=3)
    ap.add_argument('--gamma', type=float, default=_DEF.selector.gamma)
    ap.add_argument('--delta', type=float, default=_DEF.selector.delta)
    ap.add_argument('--penalty-a', type=float, default=_DEF.penalty_a)
    ap.add_argument('--penalty-b', type=float, default=_DEF.penalty_b)
    ap.add_argument('--length-scale', type=float, default=_DEF.occlusion_length_scale)
    ap.add_argument('--a0', type=float, default=_DEF.occlusion_a0)
    ap.add_argument('--b0', type=float, default=_DEF.occlusion_b0)
    ap.add_argument('--occlusion-prior', default=_DEF.occlusion_prior, choices=OCCLUSION_PRIORS)
    ap.add_argument('--occlusion-mode', default=_DEF.occlusion_mode, choices=OCCLUSION_MODES)
    ap.add_argument('--criterion', default=_DEF.criterion, choices=CRITERIA)
    ap.add_argument('--optimizer', default=_DEF.selector.optimizer, choices=OPTIMIZERS)
    ap.add_argument('--max-evals', type=int, default=_DEF.selector.max_evals)
    ap.add_argument('--n-candidates', type=int, default=_DEF.selector.n_candidates)
    ap.add_argument('--repeat-tolerance', type=float, default=_DEF.selector.repeat_tolerance)
    ap.add_argument('--noise', default='pose_dependent')
    ap.add_argument('--estimator', default='map', choices=['map', 'ekf'])
    ap.add_argument('--ekf-iterations', type=int, default=5)
    args = ap.parse_args(argv)

    model = load_robot()
    noise = PoseDependentNoise() if args.noise == 'pose_dependent' else ConstantNoise()
    settings = PlannerSettings(SelectorConfig(strategy=args.strategy, gamma=args.gamma, delta=args.delta,
                                              optimizer=args.optimizer, max_evals=args.max_evals,
                                              n_candidates=args.n_candidates,
                                              repeat_tolerance=args.repeat_tolerance),
                               penalty_a=args.penalty_a, penalty_b=args.penalty_b,
                               occlusion_length_scale=args.length_scale, occlusion_a0=args.a0,
                               occlusion_b0=args.b0, occlusion_mode=args.occlusion_mode,
                               occlusion_prior=args.occlusion_prior,
                               criterion=args.criterion)
    results = [run_seed(model, noise, settings, seed, args.iterations, args.ekf_iterations, estimator=args.estimator)
               for seed in range(args.seeds)]
    pos = np.array([r.position_mm for r in results])
    rot = np.array([r.orientation_deg for r in results])
    out = {'args': vars(args),
           'position_mm_final': float(np.mean(pos[:, -1])), 'orientation_deg_final': float(np.mean(rot[:, -1])),
           'position_mm_median_final': float(np.median(pos[:, -1])),
           'movement_deg': float(np.mean([r.movement_deg[-1] for r in results])),
           'discarded': float(np.mean([r.discarded for r in results])),
           'seconds_per_episode': float(np.mean([r.seconds for r in results]))}
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
