"""Fault injection on the calibration graph: the scenarios and the fault table of docs/faults.md.

Each scenario runs the in-process graph (:mod:`calibration_bringup.graph`; random strategy, a
few iterations, MCAP recorder on) and injects one fault mid-run:

* ``kill <node>``: the node stops dead after the first accepted observation (removed from the
  executor and destroyed without its own shutdown hook, which is what SIGKILL leaves to the
  others); ``kill recorder`` SIGKILLs a recorder running as its own process;
* ``burst``: 10,000 bad messages on every input topic of every node (NaN and wrong-sized
  joint states, bad commands, garbage images, unusable camera_info, NaN poses, malformed
  estimates and statuses), interleaved with the run;
* ``clock back``: the simulator's clock (and with it /clock and every stamp) jumps back 3 s.

Every scenario returns a :class:`FaultRow`: what was injected, whether every node survived and
the run ended (finished, or stopped with a named condition instead of hanging), how many
accepted observations the estimator had made that the bag does not hold, and silent wrong
answers (a run that finished without a failed outcome but whose estimate did not improve, or an
iteration recorded ``accepted`` that the estimator never accepted).

``python -m tools.fault_table`` runs them all and prints the Markdown table; ``tests/test_faults.py``
asserts on the same rows.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ['FaultRow', 'KILLABLE', 'run_kill', 'run_kill_recorder_process', 'run_burst', 'run_clock_back',
           'SCENARIOS', 'markdown', 'main']

#: Nodes of the in-process graph a scenario can kill.
KILLABLE = ('sim', 'detector', 'estimator', 'selector')
ITERATIONS = 4
BURST = 10_000
#: Wall seconds a run may take before it counts as hung.
DEADLINE = 60.0
#: Wall seconds after killing the sim or the selector before the run counts as stalled (nothing
#: in process notices either death: the sim's clock stops the selector's timeouts, and nothing
#: else drives the loop; the launcher notices a dead process instead).
STALL = 5.0


@dataclass
class FaultRow:
    """One line of the fault table.

    Attributes
    ----------
    fault : str
    injected : int
        Faulty messages or events injected.
    survived : bool
        Every node not deliberately killed is alive (its context is ok, it raised nothing).
    ended : bool
        The run finished within the deadline (False: it stalled, see ``note``).
    accepted_lost : int
        Observations the estimator kept (accepted, or flagged as outliers and kept; up to the fault,
        for a kill) whose verdicts the bag does not hold.
    silent_wrong : int
        Wrong answers without a failure signal (see the module docstring).
    outcomes : list of str
        The selector's iteration outcomes.
    fault_at : int
        Iterations ended when the fault was injected (``outcomes[fault_at:]`` came after it).
    note : str
        How the run ended.
    """

    fault: str
    injected: int
    survived: bool
    ended: bool
    accepted_lost: int
    silent_wrong: int
    outcomes: list[str]
    fault_at: int
    note: str


def _params(iterations: int = ITERATIONS) -> dict[str, dict[str, Any]]:
    return {'sim': {'perturb_seed': 7}, 'estimator': {'initial_seed': 3},
            'selector': {'strategy': 'random', 'iterations': iterations, 'seed': 1}}


def _updates_in_bag(bag: Path) -> tuple[int, str]:
    """Estimator verdicts of kept observations the bag holds (accepted, or flagged as outliers and
    kept: what the estimator counts as updates), read with the project's reader, and the reader's
    complaint if it stopped early."""
    from calibration_interfaces.outcome import recorded_statuses

    n, err = 0, ''
    try:
        for status in recorded_statuses(bag, skip_malformed=True):
            n += status.outcome.value in ('accepted', 'outlier')
    except Exception as exc:  # noqa: BLE001 (what the reader does on a damaged bag is measured)
        err = f'{type(exc).__name__}: {exc}'
    return n, err


def _accepted_iterations(selector: Any) -> int:
    return sum(a.outcome.value == 'accepted' for a in selector.planner.history)


def _drain(graph: Any, quiet: float = 0.5, timeout: float = 5.0) -> None:
    """Spin until the in-process recorder has written nothing new for ``quiet`` seconds, so the
    bag holds what was published before the graph closes."""
    rec = graph.recorder
    end = time.monotonic() + timeout
    last, since = None, time.monotonic()
    while rec is not None and time.monotonic() < end:
        graph.spin_once()
        total = sum(rec.counts.values())
        if total != last:
            last, since = total, time.monotonic()
        elif time.monotonic() - since > quiet:
            return


def _silent_wrong(sim: Any, estimator: Any, selector: Any, x0: np.ndarray) -> int:
    """Iterations recorded accepted beyond the estimator's accepted updates, plus one if the run
    finished with only successful outcomes but the estimate is no better than the initial guess
    (the node objects may be dead: their state is read, not their topics)."""
    from body_schema.metrics import PoseErrorEvaluator

    outcomes = [a.outcome.value for a in selector.planner.history]
    wrong = max(0, outcomes.count('accepted') - estimator.estimator.counters['updates'])
    ev = PoseErrorEvaluator(sim.robot.base, sim.true_dh, sim.robot.calibration_box)
    if selector.done and set(outcomes) <= {'accepted', 'outlier', 'failed'} and \
            ev(estimator.estimator.dh).position_m >= ev(x0).position_m:
        wrong += 1
    return wrong


def _session(domain_id: int | None):
    from calibration_bringup.graph import ros_session

    return ros_session(domain_id if domain_id is not None else 1 + (os.getpid() * 7 + int(time.time())) % 100)


def run_kill(node: str, workdir: Path, domain_id: int | None = None) -> FaultRow:
    """Kill ``node`` (one of :data:`KILLABLE`) after the first accepted observation."""
    from rclpy.node import Node

    from calibration_bringup.graph import InProcessGraph

    bag = workdir / f'kill_{node}.mcap'
    with _session(domain_id) as (ctx, ex), InProcessGraph(ctx, ex, _params(), record_path=bag) as g:
        sim, est, sel = g.sim, g.estimator, g.selector
        x0 = est.estimator.dh.copy()
        g.spin_until(lambda: _accepted_iterations(sel) >= 1, DEADLINE, 'a first accepted iteration')
        accepted_before = est.estimator.counters['updates']
        g.wait_for_recorder('/body_schema/update_status', 1)
        fault_at = len(sel.planner.history)
        victim = g.nodes.pop(node)
        ex.remove_node(victim)
        Node.destroy_node(victim)              # no subclass shutdown hook: what SIGKILL allows
        deadline = STALL if node in ('sim', 'selector') else DEADLINE
        end = time.monotonic() + deadline
        while not sel.done and time.monotonic() < end:
            g.spin_once()
        note = 'finished' if sel.done else (f'stalled: not finished {deadline:.0f} s after the kill '
                                            f'(selector phase: {sel.phase.value})')
        outcomes = [a.outcome.value for a in sel.planner.history]
        alive = all(n.context.ok() for n in g.nodes.values())
        wrong = _silent_wrong(sim, est, sel, x0)
        g.close()
    in_bag, err = _updates_in_bag(bag)
    return FaultRow(f'kill {node} mid-run', 1, alive, sel.done, max(0, accepted_before - in_bag), wrong, outcomes,
                    fault_at, note + (f'; reader: {err}' if err else ''))


def run_kill_recorder_process(workdir: Path, domain_id: int | None = None) -> FaultRow:
    """SIGKILL a recorder running as its own process after two accepted observations; the graph
    runs on, and the bag it leaves is read back with the project's reader."""
    from calibration_bringup.graph import InProcessGraph
    from calibration_interfaces.contract import CONTRACT, IMAGE_TOPICS

    bag = workdir / 'kill_recorder.mcap'
    topics = [t.name for t in CONTRACT if t.name not in IMAGE_TOPICS and not t.name.startswith('/camera/right/')]
    domain = domain_id if domain_id is not None else 1 + (os.getpid() * 11 + int(time.time())) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = (workdir / 'recorder.log').open('w')
    proc = subprocess.Popen([sys.executable, '-c', 'from calibration_bringup.recorder_node import main; main()',
                             '--ros-args', '-p', f'output:={bag}', '-p', f'topics:={topics!r}'.replace("'", '"'),
                             '-p', 'use_sim_time:=true'], env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        with _session(domain) as (ctx, ex):
            # The recorder process first (it takes seconds to start; the graph would be done).
            from diagnostic_msgs.msg import DiagnosticStatus
            from rclpy.node import Node

            from calibration_interfaces.node_util import qos_profile

            probe = Node('fault_recorder_probe', context=ctx)
            pub = probe.create_publisher(DiagnosticStatus, '/body_schema/update_status',
                                         qos_profile('/body_schema/update_status'))
            end = time.monotonic() + DEADLINE
            while pub.get_subscription_count() < 1 and time.monotonic() < end and proc.poll() is None:
                time.sleep(0.05)          # nothing to spin: the recorder is another process
            subscribed = pub.get_subscription_count() >= 1
            probe.destroy_node()
            if not subscribed:
                raise RuntimeError(f'the recorder process did not subscribe within {DEADLINE:.0f} s (exit {proc.poll()})')
            with InProcessGraph(ctx, ex, _params(10)) as g:
                g.spin_until(lambda: g.estimator.pub_status.get_subscription_count() >= 2, DEADLINE, 'the recorder process')
                g.spin_until(lambda: _accepted_iterations(g.selector) >= 2, DEADLINE, 'two accepted iterations')
                # The graph is not spun now, so nothing new is published; the recorder (another
                # process) takes the verdicts already sent and flushes each one as it comes. Kill
                # it once its bag holds them (or after 5 s): what it had written must survive. A
                # fixed pause instead let a third verdict, published just before the kill, count
                # as lost (one fresh-clone run in three).
                accepted_before = g.estimator.estimator.counters['updates']
                fault_at = len(g.selector.planner.history)
                deadline = time.monotonic() + 5.0
                while _updates_in_bag(bag)[0] < accepted_before and time.monotonic() < deadline:
                    time.sleep(0.05)      # nothing to spin: the recorder is another process
                proc.send_signal(signal.SIGKILL)
                proc.wait(10)
                g.spin_until(lambda: g.selector.done, DEADLINE, 'the run to finish without its recorder')
                outcomes = [a.outcome.value for a in g.selector.planner.history]
                alive = all(n.context.ok() for n in g.nodes.values())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        log.close()
    in_bag, err = _updates_in_bag(bag)
    return FaultRow('kill recorder (SIGKILL, own process)', 1, alive, True, max(0, accepted_before - in_bag), 0, outcomes,
                    fault_at, f'recorder exit {proc.returncode}; bag {bag.stat().st_size if bag.exists() else 0} bytes'
                    + (f'; reader: {err}' if err else ''))


def _bad_messages() -> dict[str, tuple[type, Callable[[int], Any]]]:
    """Every input topic of every node and a maker of its i-th bad message."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped
    from sensor_msgs.msg import CameraInfo, Image, JointState
    from std_msgs.msg import Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from calibration_interfaces.outcome import DETECTOR_DIAGNOSTIC

    names = ['r_shoulder_pitch', 'r_shoulder_roll', 'r_shoulder_yaw', 'r_elbow', 'r_wrist_prosup',
             'r_wrist_pitch', 'r_wrist_yaw']
    nan = float('nan')

    def joint_state(i: int) -> JointState:
        # Alternately wrong-sized and NaN, stamped in the past (never ahead of the run's clock).
        return JointState(name=names, position=[0.1] * 3) if i % 2 else JointState(name=names, position=[nan] * 7)

    def command(i: int) -> JointTrajectory:
        return JointTrajectory(joint_names=names if i % 2 else ['nobody'],
                               points=[JointTrajectoryPoint(positions=[nan] * 7)])

    def image(i: int) -> Image:
        return Image(height=240, width=320, encoding='32FC1' if i % 2 else 'rgb8', step=960, data=bytes(i % 97))

    def info(i: int) -> CameraInfo:
        return CameraInfo(width=320, height=240, d=[nan] * 5, k=[0.0] * 9 if i % 2 else [nan] * 9)

    def pose(i: int) -> PoseStamped:
        p = PoseStamped()
        p.pose.orientation.w = nan
        return p

    def hand(i: int) -> PoseWithCovarianceStamped:
        h = PoseWithCovarianceStamped()
        h.pose.pose.position.x = nan
        h.pose.covariance = [-1.0] * 36
        return h

    def markers(i: int) -> PoseArray:
        return PoseArray(poses=[Pose()] * (i % 3))                    # stamped 0: long before any attempt

    def table(i: int) -> Float64MultiArray:
        return Float64MultiArray(data=[nan] * (i % 30))

    def status(i: int) -> DiagnosticStatus:
        return DiagnosticStatus(values=[KeyValue(key='outcome', value='bogus')])

    def diagnostics(i: int) -> DiagnosticArray:
        return DiagnosticArray(status=[DiagnosticStatus(name=DETECTOR_DIAGNOSTIC,
                                                        values=[KeyValue(key='status', value='garbage')])])

    return {'/joint_states': (JointState, joint_state), '/arm/command': (JointTrajectory, command),
            '/camera/left/image_raw': (Image, image), '/camera/left/camera_info': (CameraInfo, info),
            '/camera/left/pose': (PoseStamped, pose), '/hand_pose': (PoseWithCovarianceStamped, hand),
            '/markers': (PoseArray, markers), '/body_schema/estimate': (Float64MultiArray, table),
            '/body_schema/covariance': (Float64MultiArray, table),
            '/body_schema/update_status': (DiagnosticStatus, status), '/diagnostics': (DiagnosticArray, diagnostics)}


def run_burst(workdir: Path, count: int = BURST, domain_id: int | None = None,
              topics: list[str] | None = None) -> FaultRow:
    """``count`` bad messages on every input topic (or on ``topics``), sent in slices between the
    run's callbacks from the first accepted observation on; the run must still finish and improve
    the estimate."""
    from calibration_bringup.graph import InProcessGraph
    from calibration_interfaces.node_util import qos_profile

    bag = workdir / 'burst.mcap'
    makers = {t: m for t, m in _bad_messages().items() if topics is None or t in topics}
    with _session(domain_id) as (ctx, ex), InProcessGraph(ctx, ex, _params(), record_path=bag) as g:
        from rclpy.node import Node

        x0 = g.estimator.estimator.dh.copy()
        probe = g.add('burst', Node('fault_burst', context=ctx))
        pubs = {t: probe.create_publisher(cls, t, qos_profile(t)) for t, (cls, _) in makers.items()}
        g.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), DEADLINE, 'burst discovery')
        g.spin_until(lambda: _accepted_iterations(g.selector) >= 1, DEADLINE, 'a first accepted iteration')
        sent, fault_at = 0, len(g.selector.planner.history)
        for start in range(0, count, 200):
            for topic, (_, make) in makers.items():
                for i in range(start, min(count, start + 200)):
                    pubs[topic].publish(make(i))
            sent += min(count, start + 200) - start
            for _ in range(20):
                g.spin_once(0.0)
        return _finish(g, bag, x0, f'{count:,} bad messages on each of {len(makers)} input topics',
                       sent * len(makers), fault_at, 'the burst')


def _finish(g: Any, bag: Path, x0: np.ndarray, fault: str, injected: int, fault_at: int, what: str) -> FaultRow:
    """Run ``g`` to its end after the fault, close it and measure the row."""
    g.spin_until(lambda: g.selector.done, DEADLINE * 2, f'the run to finish after {what}')
    outcomes = [a.outcome.value for a in g.selector.planner.history]
    alive = all(n.context.ok() for n in g.nodes.values())
    wrong = _silent_wrong(g.sim, g.estimator, g.selector, x0)
    updates = g.estimator.estimator.counters['updates']
    _drain(g)
    g.close()
    in_bag, err = _updates_in_bag(bag)
    return FaultRow(fault, injected, alive, True, max(0, updates - in_bag), wrong, outcomes, fault_at,
                    f'finished, {outcomes[fault_at:].count("accepted")} accepted after {what}'
                    + (f'; reader: {err}' if err else ''))


def run_clock_back(workdir: Path, jump_s: float = 1.2, domain_id: int | None = None) -> FaultRow:
    """The simulator's clock jumps back ``jump_s`` after the first accepted iteration, as after a
    simulator reset: /clock, joint states and images restart from the earlier time. The selector's
    outcome timeout is 1 s here (a verdict takes about 0.2 s), shorter than the jump, so a node
    that ignores the repeated times for the length of the jump loses the next attempts. The run
    goes on for three iterations (seed 1's random targets 2 and 4 are seen without a fault)."""
    from calibration_bringup.graph import InProcessGraph

    bag = workdir / 'clock_back.mcap'
    params = _params(100)
    params['selector']['outcome_timeout'] = 1.0
    with _session(domain_id) as (ctx, ex), InProcessGraph(ctx, ex, params, record_path=bag) as g:
        x0 = g.estimator.estimator.dh.copy()
        g.spin_until(lambda: _accepted_iterations(g.selector) >= 1, DEADLINE, 'a first accepted iteration')
        # A stamp before 0 is another fault (rclpy refuses a negative /clock): jump from later on.
        g.spin_until(lambda: g.sim.sim_ns > (jump_s + 0.1) * 1e9, DEADLINE, f'sim time past {jump_s + 0.1:g} s')
        sim, back = g.sim, int(jump_s * 1e9)
        fault_at = len(g.selector.planner.history)
        g.selector.loop.settings = dataclasses.replace(g.selector.loop.settings, iterations=fault_at + 3)
        sim.sim_ns -= back
        sim._next_js -= back
        sim._next_img -= back
        return _finish(g, bag, x0, f'clock jumps back {jump_s:g} s', 1, fault_at, 'the jump')


SCENARIOS: dict[str, Callable[[Path], FaultRow]] = {
    **{f'kill_{n}': (lambda d, n=n: run_kill(n, d)) for n in KILLABLE},
    'kill_recorder': run_kill_recorder_process,
    'burst': run_burst,
    'clock_back': run_clock_back,
}


def markdown(rows: list[FaultRow]) -> str:
    """The fault table of docs/faults.md."""
    lines = ['| fault | injected | nodes survived | run ended | kept observations lost | silent wrong answers '
             '| outcomes before \\| after the fault; notes |', '|---|---:|---|---|---:|---:|---|']
    for r in rows:
        lines.append(f'| {r.fault} | {r.injected:,} | {"yes" if r.survived else "no"} | '
                     f'{"yes" if r.ended else "stalled"} | {r.accepted_lost} | {r.silent_wrong} | '
                     f'{" ".join(r.outcomes[:r.fault_at])} \\| {" ".join(r.outcomes[r.fault_at:]) or "none"}; '
                     f'{r.note} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('scenarios', nargs='*', default=[], help=f'which to run (default: all of {list(SCENARIOS)})')
    args = parser.parse_args(argv)
    unknown = set(args.scenarios) - set(SCENARIOS)
    if unknown:
        parser.error(f'unknown scenarios {sorted(unknown)}; choose from {list(SCENARIOS)}')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('AMENT_PREFIX_PATH', str(Path(sys.executable).parents[1]))   # the venv
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenarios or SCENARIOS:
            t0 = time.monotonic()
            rows.append(SCENARIOS[name](Path(tmp)))
            print(f'{name}: {time.monotonic() - t0:.1f} s: {rows[-1]}', file=sys.stderr)
    print(markdown(rows))


if __name__ == '__main__':
    main()
