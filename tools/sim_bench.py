"""Benchmark of the simulator (``make bench`` / ``python -m tools.bench icub_sim_bridge``).

Measures camera frames per second (render + bytes, as the node publishes them) at 320x240 and
640x480, physics steps per second (motion update + step), the sim-time / wall-time factor of the
node at real-time factor 0 during a move with both cameras at 10 Hz, the visibility of the
markers over the calibration box. (The corner projection error is a test, ``test_world.py``.)
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from body_schema.robot import load_robot
from body_schema.sampling import uniform_configs

from icub_sim_bridge.motion import TrajectoryFollower, Waypoints
from icub_sim_bridge.world import SimWorld

__all__ = ['ROWS', 'main']

VIS_CONFIGS, VIS_SEED = 400, 0
#: The table's rows (measure, target) in order; the README's table has the same rows (a test checks).
ROWS: tuple[tuple[str, str], ...] = (
    ('camera frames/s at 320x240 (per camera)', '>= 100'),
    ('camera frames/s at 640x480 (per camera)', ''),
    ('camera frames/s at 320x240, supersample 2', ''),
    ('physics steps/s (motion update + stepSimulation)', ''),
    ('sim/wall factor, RTF 0, arm moving, 2 cameras at 10 Hz', '>= 5x'),
    ('same, per CPU-second the process got', ''),
    (f'left-eye visibility over the calibration box ({VIS_CONFIGS} configs, seed {VIS_SEED})', '60-85%'),
)


def _rate(fn, min_time: float = 1.0, min_calls: int = 20) -> float:
    """Calls per second of ``fn`` over at least ``min_time`` seconds."""
    fn()
    n, t0 = 0, time.perf_counter()
    while n < min_calls or time.perf_counter() - t0 < min_time:
        fn()
        n += 1
    return n / (time.perf_counter() - t0)


def _node_factor(seconds: float = 4.0) -> tuple[float, int, float]:
    """Sim/wall factor of the node (RTF 0, both cameras at 10 Hz) while the arm moves.

    Returns the factor, whether the arm was still moving at the end, and the share of one CPU
    the process got (below 1 when other processes compete for the cores).
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from icub_sim_bridge.sim_node import SimNode

    robot = load_robot()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=77)
    node = SimNode(context=ctx, parameter_overrides=[
        Parameter('real_time_factor', value=0.0), Parameter('image_rate', value=10.0),
        Parameter('max_joint_speed_deg', value=30.0)])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        msg = JointTrajectory(joint_names=list(robot.joint_names))
        # A long move through random configurations of the calibration box (as the selector asks).
        msg.points = [JointTrajectoryPoint(positions=q.tolist())
                      for q in uniform_configs(robot.calibration_box, 20, 2)]
        node._on_command(msg)
        s0, t0, c0 = node.sim_ns, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            ex.spin_once(timeout_sec=0.01)
        wall = time.perf_counter() - t0
        factor = (node.sim_ns - s0) / 1e9 / wall
        cpu_share = (time.process_time() - c0) / wall
        moving = int(node.follower.moving)
    finally:
        ex.remove_node(node)
        node.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
    return factor, moving, cpu_share


def main(argv: list[str] | None = None) -> str:
    """Measure and return the Markdown section (``--help``: it takes no options)."""
    argparse.ArgumentParser(prog='python -m tools.sim_bench', description=__doc__.split('\n\n')[0]).parse_args(argv)
    from icub_sim_bridge.visibility import measure_visibility

    robot = load_robot()
    values = []                         # one per ROWS entry, in order
    with SimWorld(robot) as w:
        cam = robot.camera_pose('left')
        # Rendering cost grows with the pixels the arm covers: cycle through box configurations.
        configs = uniform_configs(robot.calibration_box, 16, 1)
        state = {'k': 0}

        def frame(intr, supersample: int = 1) -> None:
            w.set_joint_positions(configs[state['k'] % len(configs)])
            state['k'] += 1
            w.render(cam, intr, supersample=supersample).tobytes()
        for res in ((320, 240), (640, 480)):
            intr = robot.camera.scaled(*res)
            values.append(f'{_rate(lambda: frame(intr)):.0f}')
        values.append(f'{_rate(lambda: frame(robot.camera, 2)):.0f}')
        f = TrajectoryFollower(robot.calibration_box[:, 0], 1.0)
        f.start(Waypoints(robot.calibration_box[:, 1][None], np.zeros(1)))

        def step() -> None:
            f.advance(w.physics_step)
            w.step()
        values.append(f'{_rate(step):.0f}')
        vis = measure_visibility(robot, VIS_CONFIGS, VIS_SEED, world=w)
    factor, moving, share = _node_factor()
    values.append(f'{factor:.1f}x')
    values.append(f'{factor / max(share, 1e-9):.1f}x ({100 * share:.0f}% of a core)')
    values.append(f'{100 * vis.fraction:.1f}% +- {100 * vis.stderr():.1f}')
    rows = [(label, value, target) for (label, target), value in zip(ROWS, values, strict=True)]
    import os

    load = os.getloadavg()[0] if hasattr(os, 'getloadavg') else float('nan')
    lines = ['## icub_sim_bridge', '', f'({os.cpu_count()} CPUs, load average {load:.1f} at the end)', '',
             '| measure | value | target |', '|---|---|---|']
    lines += [f'| {a} | {b} | {c} |' for a, b, c in rows]
    lines += ['', f'(the arm was {"still moving" if moving else "done moving"} at the end of the '
              f'factor measurement; visibility per marker: '
              + ', '.join(f'id {i} {100 * p:.1f}%' for i, p in zip(vis.marker_ids, vis.per_marker)) + ')', '']
    return '\n'.join(lines)


if __name__ == '__main__':
    print(main())
