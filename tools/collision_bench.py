"""Benchmark of the selector's collision check (``make bench``): time and agreement with the simulator.

``python -m tools.collision_bench`` prints a Markdown table per description: for each geometry the
check can use (the links drawn from the DH table; for a description read from a URDF, that URDF's
own collision meshes, the one it uses), the pairs checked, the time per configuration and per
straight path between box configurations, the share of the box it calls clear, and the time of an AL
selection with the check and the part of it the checks took (the selection records'
``safety_seconds``, as the safety audit reads them from a run). For a URDF description a second
table compares the check (Pinocchio and Coal) with the simulator's contact monitor (Bullet) on
configurations across the joint limits: the largest Coal distance of a pair Bullet reports in
contact, and the smallest of a pair it reports free (a pair Coal finds overlapping must be a
contact).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from body_schema import load_robot, sampling
from body_schema.arm_visuals import drawn_arm_urdf
from body_schema.collision import CollisionModel
from body_schema.noise import PoseDependentNoise
from body_schema.robot import ArmModel

__all__ = ['main']


def _per_call(fn, items) -> float:
    t0 = time.perf_counter()
    for it in items:
        fn(it)
    return (time.perf_counter() - t0) / max(len(items), 1)


def _selection_seconds(robot: ArmModel, safety: CollisionModel, n: int) -> tuple[float, float]:
    """Mean seconds per planned AL selection and the part the checks took (from the selection records)."""
    from active_selector.planner import Planner, PlannerSettings

    planner = Planner(robot, PoseDependentNoise(), PlannerSettings(), safety=safety)
    planner.start = robot.calibration_box.mean(axis=1)
    cam = robot.camera_pose(robot.camera_names[0])
    t0 = time.perf_counter()
    sels = planner.plan(sampling.perturb_dh(robot.dh, 1), sampling.initial_covariance(robot.n_joints), cam, n)
    return (time.perf_counter() - t0) / n, sum(s.safety_seconds for s in sels) / n


def timing_rows(robot: ArmModel, configs: int, selections: int) -> list[str]:
    """One row per geometry: the DH-drawn links, and for a URDF description its own (the one used)."""
    urdfs = [('drawn from the DH table', drawn_arm_urdf(robot)), ('its URDF', None)] if robot.urdf else \
        [('drawn from the DH table', None)]
    q = sampling.uniform_configs(robot.calibration_box, configs, seed=11)
    rows = []
    for label, urdf in urdfs:
        t0 = time.perf_counter()
        c = CollisionModel(robot, urdf=urdf)
        build = time.perf_counter() - t0
        clear = _per_call(c.clear, list(q))
        paths = _per_call(lambda i: c.path_clear(q[i], q[i + 1]), list(range(min(configs - 1, 100))))
        sel, checks = _selection_seconds(robot, c, selections)
        used = 'used; ' if urdf is None else ''
        rows.append(f'| {robot.name} | {label} ({used}built in {build:.2f} s) | '
                    f'{len(c.pairs)} | {clear * 1e3:.3f} | {paths * 1e3:.1f} | {float(np.mean(c.clear(q))):.1%} | '
                    f'{sel:.2f} | {checks:.3f} | x{sel / (sel - checks):.2f} |')
    return rows


def agreement_row(robot: ArmModel, configs: int) -> str:
    from icub_sim_bridge.contacts import ContactMonitor

    mon = ContactMonitor(robot, probe_configs=16)
    col = CollisionModel(robot, margin=0.0, self_margin=0.0, probe_configs=16)
    in_contact, worst_contact, least_free, wrong = 0, -np.inf, np.inf, 0
    try:
        for q in sampling.uniform_configs(robot.limits, configs, seed=4):
            contacts = {frozenset(p) for p in mon.check(q)}
            in_contact += bool(contacts)
            for pair, d in col.pair_distances(q).items():
                if frozenset(pair) in contacts:
                    worst_contact = max(worst_contact, d)
                    wrong += d > 0.0025
                elif frozenset(pair) not in mon.unchecked:
                    least_free = min(least_free, d)
                    wrong += d <= 0.0
    finally:
        mon.close()
    return (f'| {robot.name} | {configs} | {in_contact} | {worst_contact * 1e3:.1f} | {least_free * 1e3:.1f} | '
            f'{wrong} |')


def main(argv: list[str] | None = None) -> str:
    """The Markdown section (also printed)."""
    ap = argparse.ArgumentParser(prog='python -m tools.collision_bench', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robots', nargs='+', default=['ur5e', 'panda', 'kuka_iiwa'], help='descriptions to measure')
    ap.add_argument('--configs', type=int, default=400, help='box configurations timed (default 400)')
    ap.add_argument('--selections', type=int, default=8, help='AL selections planned with the check')
    ap.add_argument('--agreement', type=int, default=300,
                    help='configurations across the limits compared with the simulator (URDF descriptions)')
    args = ap.parse_args(argv)
    robots = [load_robot(r) for r in args.robots]
    lines = ['## Collision check', '',
             '| robot | geometry | pairs | per configuration [ms] | per path [ms] | box clear | AL selection [s] '
             '| of it the checks [s] | x the search alone |', '|---|---|---|---|---|---|---|---|---|']
    for r in robots:
        lines += timing_rows(r, args.configs, args.selections)
    urdf = [r for r in robots if r.urdf is not None]
    if urdf and args.agreement > 0:
        lines += ['', 'The check against the simulator\'s contact monitor (Bullet), margins 0, configurations across '
                  'the limits:', '',
                  '| robot | configurations | in contact (Bullet) | largest Coal distance of a contact [mm] '
                  '| least Coal distance of a free pair [mm] | disagreements (> 2.5 mm, or overlap called free) |',
                  '|---|---|---|---|---|---|']
        lines += [agreement_row(r, args.agreement) for r in urdf]
    text = '\n'.join(lines) + '\n'
    print(text)
    return text


if __name__ == '__main__':
    main(sys.argv[1:])
    sys.exit(0)
