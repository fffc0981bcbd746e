"""Benchmark of the body_schema core (``make bench``): median wall times on this machine.

``python -m tools.kinematics_bench`` prints a Markdown table of: batched FK of 1000 configurations,
one pose Jacobian w.r.t. the 28 parameters, one EKF update (plain and iterated), one AL
selection with DIRECT-L at 2000 evaluations and the cost of one evaluation inside it, and one
evaluation of the iCub's default stereo cost (both eyes, the whole-marker visibility prior,
v-optimality, the occlusion-discounted gain; built by the selector's planner with its default
settings) at one configuration, as the selector's local search makes about 90 of them per
selection.
"""
from __future__ import annotations

import argparse
import sys
import time
from typing import Callable

import numpy as np

from active_selector.planner import Planner
from body_schema import ekf, load_robot, sampling
from body_schema.acquisition import AcquisitionCost, JointSelector, SelectorConfig
from body_schema.noise import PoseDependentNoise
from body_schema.occlusion import OcclusionModel


def _median_time(fn: Callable[[], object], repeat: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def measure(scale: float = 1.0) -> list[tuple[str, float, str, str]]:
    """Rows ``(what, seconds, target, unit)``; ``scale`` multiplies every repeat count (at least 1)."""
    arm = load_robot()
    rng = np.random.default_rng(0)
    q1000 = sampling.uniform_configs(arm.calibration_box, 1000, rng)
    q = q1000[0]
    dh = sampling.perturb_dh(arm.dh, rng)
    P = sampling.initial_covariance(7)  # noqa: N806
    model = ekf.HandPoseModel(arm.base, 7)
    z = arm.forward_kinematics(q)
    R = np.diag([1e-5] * 3 + [1e-3] * 3)  # noqa: N806

    def one_update(iterations: int) -> Callable[[], object]:
        def run() -> object:
            f = ekf.ExtendedKalmanFilter.__new__(ekf.ExtendedKalmanFilter)
            f.__dict__.update(filt.__dict__)     # same state every repeat, no constructor checks
            return model.update(f, q, z, R, iterations=iterations)
        return run

    filt = ekf.ExtendedKalmanFilter(dh.ravel(), P)
    occ = OcclusionModel(arm.calibration_box)
    for t in sampling.uniform_configs(arm.calibration_box, 50, rng):   # a 50-iteration history
        occ.add(t, bool(rng.random() < 0.7))
    cost = AcquisitionCost(arm.base, dh, P, PoseDependentNoise(), arm.camera_pose('left'),
                           arm.markers, occlusion=occ, penalty_a=0.01, penalty_b=10.0)
    selector = JointSelector(arm.calibration_box, SelectorConfig(strategy='al', optimizer='direct', max_evals=2000))
    # The selector's own cost for a stereo pair, built by its planner with the default settings
    # after the same 50-attempt history.
    planner = Planner(arm, PoseDependentNoise.for_robot(arm), eyes=('left', 'right'))
    planner.start = q
    for t, seen in zip(*occ.attempts):
        planner.record(t, t, 'accepted' if seen else 'failed', bool(seen), 0.0)
    stereo = planner.cost(dh, P, np.stack([arm.camera_pose('left'), arm.camera_pose('right')]))

    def _n(repeat: int) -> int:
        return max(1, int(repeat * scale))

    return [
        ('batched FK, 1000 configurations', _median_time(lambda: arm.forward_kinematics(q1000), _n(50)), '<= 5 ms', 'ms'),
        ('pose Jacobian w.r.t. 28 DH parameters', _median_time(lambda: arm.jacobian_dh(q), _n(500)), '<= 100 us', 'us'),
        ('EKF update (paper: 1 linearisation)', _median_time(one_update(1), _n(300)), '<= 200 us', 'us'),
        ('EKF update, iterated (5 linearisations)', _median_time(one_update(5), _n(100)), '-', 'us'),
        ('acquisition cost, one evaluation (50 occlusion samples)', _median_time(lambda: cost(q), _n(500)), '-', 'us'),
        ('acquisition cost, one stereo evaluation (the local search: both eyes, visibility prior)',
         _median_time(lambda: stereo(q), _n(500)), '-', 'us'),
        ('AL selection, DIRECT-L, 2000 evaluations', _median_time(lambda: selector.select(cost), _n(5), 1), '<= 0.5 s', 's'),
    ]


def main(argv: list[str] | None = None) -> str:
    """Measure and return the Markdown table (``--help`` lists the options)."""
    parser = argparse.ArgumentParser(prog='python -m tools.kinematics_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--scale', type=float, default=1.0,
                        help='multiply every repeat count by this (0.1: a quick, noisier run; default 1)')
    args = parser.parse_args(argv)
    rows = measure(args.scale)
    scale = {'ms': 1e3, 'us': 1e6, 's': 1.0}
    lines = ['## body_schema', '', '| operation | median | target |', '|---|---|---|']
    for what, sec, target, unit in rows:
        lines.append(f'| {what} | {sec * scale[unit]:.3g} {unit} | {target} |')
    return '\n'.join(lines) + '\n'


if __name__ == '__main__':
    print(main(sys.argv[1:]))
