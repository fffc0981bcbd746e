"""Per-iteration time budget of the closed loop (``make bench``).

Runs the in-process graph (:mod:`calibration_bringup.graph`: sim, detector, estimator and
selector on one SingleThreadedExecutor, sim as fast as it can) for a few AL iterations at the
default joint speed and DIRECT budget, then reports medians per iteration: the simulated move and the wait for the outcome (sim seconds), and the
compute (wall): capture (render), detect, update, select. Target: compute <= 5% of the move (issue 14).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import cv2
import numpy as np
import rclpy


def run(iterations: int = 8) -> dict[str, float]:
    from diagnostic_msgs.msg import DiagnosticStatus
    from std_msgs.msg import String

    from body_schema.noise import PoseDependentNoise
    from calibration_bringup.graph import InProcessGraph, ros_session
    from icub_sim_bridge.world import SimWorld
    from marker_detector.detection import HandPoseEstimator

    progress, updates = [], []
    with ros_session(domain_id=90 + os.getpid() % 10) as (ctx, executor):
        with InProcessGraph(ctx, executor, {'sim': {'perturb_seed': 7},
                                            'selector': {'iterations': iterations}}) as graph:
            probe = graph.add('probe', rclpy.create_node('bench_probe', context=ctx))
            probe.create_subscription(String, '/calibration/progress',
                                      lambda m: progress.append(json.loads(m.data)), 100)
            probe.create_subscription(DiagnosticStatus, '/body_schema/update_status',
                                      lambda m: updates.append({v.key: v.value for v in m.values}), 100)
            wall0 = time.perf_counter()
            graph.spin_until(lambda: len(progress) >= iterations, 600.0, f'{iterations} AL iterations')
            wall = time.perf_counter() - wall0
            search = graph.selector.planner.settings.selector.search
            est = graph.estimator.estimator.settings
            update = (f'MAP update ({est.loss} loss)' if est.estimator == 'map' else
                      f'EKF update ({est.iterations} linearisations)')
            model, true_dh = graph.sim.robot, graph.sim.true_dh
    reached = [np.radians(p['reached_deg']) for p in progress]

    # Capture and detection, timed on the same configurations outside the executor.
    cam = model.camera_pose('left')
    det = HandPoseEstimator(model, PoseDependentNoise())
    cap, dt = [], []
    with SimWorld(model, true_dh, head_pose=model.eyes.head_pose) as world:
        for q in reached:
            world.set_joint_positions(q)
            t0 = time.perf_counter()
            img = world.render(cam, model.camera)
            cap.append(time.perf_counter() - t0)
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            t0 = time.perf_counter()
            det.process(gray, model.camera.K, None, cam)
            dt.append(time.perf_counter() - t0)
    upd = [float(u['update_s']) for u in updates if u.get('outcome') in ('accepted', 'outlier')]
    move = float(np.median([p['move_sim_s'] for p in progress]))
    select = float(np.median([p['selection_s'] for p in progress]))
    compute = float(np.median(dt)) + (float(np.median(upd)) if upd else 0.0) + select
    return {'iterations': len(progress), 'move_sim_s': move,
            'outcome_sim_s': float(np.median([p['outcome_sim_s'] for p in progress])),
            'capture_ms': 1e3 * float(np.median(cap)), 'detect_ms': 1e3 * float(np.median(dt)),
            'update_ms': 1e3 * float(np.median(upd)) if upd else float('nan'),
            'select_s': select, 'compute_s': compute, 'compute_over_move': compute / move,
            'wall_s_per_iteration': wall / max(len(progress), 1),
            'accepted': sum(p['outcome'] in ('accepted', 'outlier') for p in progress), 'search': search,
            'update': update}


def main(argv: list[str] | None = None) -> str:
    """Run the loop and return the Markdown table (``--help`` lists the options)."""
    parser = argparse.ArgumentParser(prog='python -m tools.loop_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--iterations', type=int, default=8, help='AL iterations of the in-process graph (default 8)')
    args = parser.parse_args(argv)
    r = run(args.iterations)
    rows = [
        ('move to target (sim, 30 deg/s)', f"{r['move_sim_s']:.2f} s", ''),
        ('wait for the outcome after settling (sim)', f"{r['outcome_sim_s']:.2f} s", ''),
        ('capture: one 320x240 render', f"{r['capture_ms']:.1f} ms", ''),
        ('detect + pose, one frame', f"{r['detect_ms']:.1f} ms", ''),
        (r['update'], f"{r['update_ms']:.2f} ms", ''),
        (f"select (AL, {r['search']})", f"{r['select_s']:.3f} s", ''),
        ('compute = detect + update + select', f"{r['compute_s']:.3f} s", ''),
        ('compute / move', f"{100 * r['compute_over_move']:.1f} %", '<= 5 %'),
        ('wall time per iteration, in-process graph, sim as fast as possible', f"{r['wall_s_per_iteration']:.2f} s", ''),
    ]
    lines = ['## Closed loop: per-iteration budget (medians over '
             f"{r['iterations']} AL iterations, {r['accepted']} accepted)", '',
             '| step | time | target |', '|---|---|---|']
    lines += [f'| {a} | {b} | {c} |' for a, b, c in rows]
    return '\n'.join(lines) + '\n'


if __name__ == '__main__':
    print(main(sys.argv[1:]))
