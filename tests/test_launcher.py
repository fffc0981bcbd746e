"""scripts/run_calibration.sh under faults: bad options, Ctrl-C at any moment, two runs at once, resume.

Bad options must fail before any process starts; every exit path must stop every node (checked
in /proc by the run id the launcher passes to each node); a SIGINT a moment after the nodes
start must stop the graph within seconds (a node used to lose it while importing); two runs get
different domains, a run forced onto a taken domain is refused; an interrupted run resumed with
``--resume`` loses no accepted observation. Few and short process-level runs (2-5 iterations
at rtf 2 without images, as in tests/test_end_to_end.py).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / 'scripts' / 'run_calibration.sh'
FAST = ['--rtf', '2', '--no-images', '--seed', '3', '--timeout', '240']


def _env() -> dict[str, str]:
    env = dict(os.environ, PATH=f'{Path(sys.executable).parent}:{os.environ["PATH"]}')
    env.pop('ROS_DOMAIN_ID', None)
    return env


def _processes_with(marker: str) -> list[str]:
    """Command lines of the live processes whose command line contains ``marker``."""
    found = []
    for proc in Path('/proc').iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            cmdline = (proc / 'cmdline').read_bytes().replace(b'\0', b' ').decode(errors='replace')
            state = next((ln for ln in (proc / 'status').read_text().splitlines() if ln.startswith('State:')), '')
        except OSError:
            continue
        if marker in cmdline and 'zombie' not in state:
            found.append(f'{proc.name}: {cmdline}')
    return found


def _run_id(out: Path) -> str:
    return dict(line.split('=', 1) for line in (out / 'run.ids').read_text().split())['run_id']


def _wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f'timed out after {timeout} s waiting for {what}')
        time.sleep(0.05)


def _start(out: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([str(SCRIPT), '--output', str(out), *args], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize('args, named', [
    (['--timeout', 'abc'], '--timeout'),
    (['--image-size', '0x0'], '--image-size'),
    (['--seed'], '--seed'),
    (['--iterations', '3', '--seed'], '--seed'),
    (['--output', '--seed', '2'], '--output'),
    (['--frobnicate'], '--frobnicate'),
    (['--rtf', 'fast'], '--rtf'),
    (['--domain-id', '233'], '--domain-id'),
    (['--max-timeouts', '1.5'], '--max-timeouts'),
    (['--max-dh-difference', 'small'], '--max-dh-difference'),
    (['--resume', '/nonexistent-run-dir'], '--resume'),
    (['--rtf', '2', '--resume', '/nonexistent-run-dir'], '--rtf'),   # run.env's rtf would silently win
    (['--transport', 'theora'], '--transport'),
    (['--image-encoding', 'nv24'], '--image-encoding'),
    (['--demosaicing', 'nearest'], '--demosaicing'),
    (['--camera-info', '/nonexistent/ost.yaml'], '--camera-info'),
    (['--margin', '0.05', '--no-collision-check'], '--no-collision-check'),
    (['--eyes', 'three'], '--eyes'),
    (['--robot', 'ur5e', '--eyes', 'both'], '--eyes both'),          # a fixed camera has no second eye
    (['--eyes', 'both', '--camera-error', '0.01 1'], '--eyes both'),  # the estimated extrinsics are one camera's
])
def test_a_bad_option_exits_2_with_one_line_naming_it_and_starts_nothing(tmp_path: Path, args, named) -> None:
    out = tmp_path / 'run'
    argv = [str(SCRIPT), *args] if '--output' in args else [str(SCRIPT), '--output', str(out), *args]
    proc = subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count('\n') == 1 and named in proc.stderr, proc.stderr
    assert 'Traceback' not in proc.stderr and 'unbound' not in proc.stderr
    assert not out.exists()                                          # nothing started, nothing written
    assert not _processes_with(str(out))


def test_a_malformed_camera_info_file_is_refused_naming_the_field(tmp_path: Path) -> None:
    bad = tmp_path / 'ost.yaml'
    bad.write_text('image_height: 240\ncamera_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n')
    proc = subprocess.run([str(SCRIPT), '--output', str(tmp_path / 'run'), '--camera-info', str(bad)], env=_env(),
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and proc.stderr.count('\n') == 1, proc.stderr
    assert '--camera-info' in proc.stderr and 'image_width' in proc.stderr and str(bad) in proc.stderr
    assert not (tmp_path / 'run').exists()


def test_a_non_empty_output_is_refused_and_overwrite_clears_the_previous_run(tmp_path: Path) -> None:
    (tmp_path / 'report.md').write_text('an old report')
    proc = subprocess.run([str(SCRIPT), '--output', str(tmp_path), '--iterations', '1', '--domain-id', '233x'],
                          env=_env(), capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and '--domain-id' in proc.stderr      # options first
    proc = subprocess.run([str(SCRIPT), '--output', str(tmp_path)], env=_env(), capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode == 2 and 'not empty' in proc.stderr and '--overwrite' in proc.stderr, proc.stderr
    assert (tmp_path / 'report.md').read_text() == 'an old report'


def test_sigint_right_after_the_nodes_start_stops_the_whole_graph_within_seconds(tmp_path: Path) -> None:
    """Ctrl-C at several moments of the nodes' start-up (while they import, while they build):
    each time every node stops on SIGINT (none SIGKILLed after 15 s) and none is left behind."""
    for k, delay in enumerate((0.2, 0.8, 2.0)):
        out = tmp_path / f'run{k}'
        launcher = _start(out, '--iterations', '2', *FAST)
        _wait_for(lambda: (out / 'logs' / 'estimator.log').exists() or launcher.poll() is not None, 60,
                  'the estimator to start')
        assert launcher.poll() is None, launcher.communicate()
        time.sleep(delay)                     # the moment of the Ctrl-C is the point of the test
        run_id = _run_id(out)
        t0 = time.monotonic()
        launcher.send_signal(signal.SIGINT)
        _, err = launcher.communicate(timeout=30)
        took = time.monotonic() - t0
        logs = {f.stem: f.read_text()[-1500:] for f in (out / 'logs').glob('*.log')}
        assert launcher.returncode == 130, err
        assert 'did not stop on SIGINT' not in err, (delay, err, logs)
        assert took < 10.0, (delay, took, err)
        assert not _processes_with(run_id), (delay, _processes_with(run_id))


def test_a_node_failure_after_start_leaves_no_process_behind(tmp_path: Path) -> None:
    # 8 px is below the simulator's image_width range: the sim exits at start, the others run.
    proc = subprocess.run([str(SCRIPT), '--iterations', '2', '--image-size', '8x8', '--output', str(tmp_path),
                           '--timeout', '120'], env=_env(), capture_output=True, text=True, timeout=180)
    assert proc.returncode == 1 and 'sim exited early' in proc.stderr, proc.stderr
    assert not _processes_with(_run_id(tmp_path))


def test_two_runs_at_once_get_their_own_domains_and_a_forced_shared_domain_is_refused(tmp_path: Path) -> None:
    # Two graphs at once on 2 loaded cores: the offline re-run can then pair the recorded data
    # differently from the live estimator (the joint buffer's handling of time, another part of
    # issue 17) and the health check rightly fails the run; here only the isolation is checked.
    lenient = ['--max-dh-difference', '1000']
    a = _start(tmp_path / 'a', '--iterations', '2', *FAST, *lenient)
    b = _start(tmp_path / 'b', '--iterations', '2', *FAST, *lenient)
    _wait_for(lambda: (tmp_path / 'a' / 'run.ids').exists(), 60, 'run a to take its domain')
    domain_a = dict(ln.split('=', 1) for ln in (tmp_path / 'a' / 'run.ids').read_text().split())['domain_id']
    c = subprocess.run([str(SCRIPT), '--output', str(tmp_path / 'c'), '--iterations', '2', '--domain-id', domain_a],
                       env=_env(), capture_output=True, text=True, timeout=60)
    assert c.returncode == 2 and f'ROS_DOMAIN_ID {domain_a} is used by another run' in c.stderr, c.stderr
    for name, p in (('a', a), ('b', b)):
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, f'run {name}:\n{out}\n{err}'
    domain_b = dict(ln.split('=', 1) for ln in (tmp_path / 'b' / 'run.ids').read_text().split())['domain_id']
    assert domain_a != domain_b


def test_a_forced_domain_where_a_graph_talks_is_refused(ros, tmp_path: Path) -> None:
    """A graph not started by the launcher (here this test's node) is found by discovery."""
    from std_msgs.msg import String

    node = ros.node('someone_elses_node')
    node.create_publisher(String, '/chatter', 10)
    proc = subprocess.Popen([str(SCRIPT), '--output', str(tmp_path / 'run'), '--iterations', '2',
                             '--domain-id', str(ros.domain_id)], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ros.spin_until(lambda: proc.poll() is not None, 60.0, 'the launcher to decide')   # spinning: discoverable
    err = proc.stderr.read()
    if proc.returncode != 2:
        err += proc.stdout.read()
    assert proc.returncode == 2 and f'ROS_DOMAIN_ID {ros.domain_id} already has a ROS graph' in err, err
    assert '/chatter' in err
    assert not (tmp_path / 'run' / 'logs').exists()


def test_a_node_that_sees_another_run_id_stops_taking_input(ros) -> None:
    """Two runs on one domain: a run that sees the other's latched id stops, naming it."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from calibration_interfaces.node_util import RunGuard

    mine = RunGuard(ros.node('node_of_run_a'), 'run-a')
    other_context = Context()
    rclpy.init(context=other_context, domain_id=ros.domain_id)
    other_node = Node('node_of_run_b', context=other_context)
    other_exec = SingleThreadedExecutor(context=other_context)
    other_exec.add_node(other_node)
    try:
        same = RunGuard(ros.node('another_node_of_run_a'), 'run-a')
        ros.spin_until(lambda: mine._sub.get_publisher_count() >= 2, 10.0, 'the run-a nodes to match')
        ros.spin_for(0.3)
        assert mine.conflict is None and same.conflict is None           # one run: no conflict
        theirs = RunGuard(other_node, 'run-b')              # a second run joins the domain
        sides = ((ros.context, ros.executor, (mine, same)), (other_context, other_exec, (theirs,)))
        deadline = time.monotonic() + 20.0
        # At least one run stops (takes no input, exits after lingering): never a silent mix.
        while all(context.ok() for context, _, _ in sides):
            assert time.monotonic() < deadline, ('a run to notice the other', mine.conflict, theirs.conflict)
            for context, executor, _ in sides:
                if context.ok():
                    executor.spin_once(timeout_sec=0.01)
        for context, _, guards in sides:
            noticed = [g.conflict for g in guards if g.conflict]
            assert context.ok() or noticed                    # a stopped run says why
        assert all("'run-b'" in g.conflict for g in (mine, same) if g.conflict)
        assert theirs.conflict is None or "'run-a'" in theirs.conflict
    finally:
        other_exec.shutdown()
        other_node.destroy_node()
        rclpy.try_shutdown(context=other_context)


def test_an_interrupted_run_resumed_loses_no_accepted_observation(tmp_path: Path) -> None:
    iterations = 5
    first = _start(tmp_path, '--iterations', str(iterations), *FAST)
    progress = tmp_path / 'progress.jsonl'
    _wait_for(lambda: progress.exists() and len(progress.read_text().splitlines()) >= 2, 200,
              'two iterations of the first part')
    first.send_signal(signal.SIGINT)
    _, err = first.communicate(timeout=60)
    assert first.returncode == 130, err
    before = [json.loads(ln) for ln in progress.read_text().splitlines() if ln.strip()]
    with np.load(tmp_path / 'checkpoint.npz') as d:
        updates_before = int(d['map_n_updates'])
    assert 0 < len(before) < iterations
    # (The estimator may have taken the observation of the iteration the selector had not recorded.)
    assert updates_before >= sum(r['outcome'] in ('accepted', 'outlier') for r in before) > 0

    proc = subprocess.run([str(SCRIPT), '--resume', str(tmp_path), '--timeout', '240'], env=_env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f'{proc.stdout}\n{proc.stderr}'
    assert (tmp_path / 'run.1.mcap').is_file() and (tmp_path / 'calibration.mcap').is_file()
    records = [json.loads(ln) for ln in progress.read_text().splitlines()]
    assert [r['iteration'] for r in records] == list(range(1, iterations + 1))
    assert records[:len(before)] == before
    with np.load(tmp_path / 'checkpoint.npz') as d:
        updates_after = int(d['map_n_updates'])
    # Every accepted observation of both parts is in the final estimate: before + after.
    after = sum(r['outcome'] in ('accepted', 'outlier') for r in records[len(before):])
    assert after > 0 and updates_after == updates_before + after
    assert 'resumed after iteration' in (tmp_path / 'logs' / 'selector.log').read_text()
    assert 'resumed from checkpoint' in (tmp_path / 'logs' / 'estimator.log').read_text()


def test_a_graph_without_run_ids_is_seen_by_its_node_names(ros) -> None:
    """An old launcher's graph publishes no run id: a second node of the same name gives it away."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    from calibration_interfaces.node_util import RunGuard

    guard = RunGuard(ros.node('dh_estimator'), 'run-a', period=0.1)
    ros.spin_for(0.5)
    assert guard.conflict is None                                  # alone: its own name once
    other_context = Context()
    rclpy.init(context=other_context, domain_id=ros.domain_id)
    other = Node('dh_estimator', context=other_context)            # no guard, no run id
    try:
        ros.spin_until(lambda: guard.conflict is not None, 15.0, 'the guard to see the second dh_estimator')
        assert "another node named '/dh_estimator'" in guard.conflict
        ros.spin_until(lambda: not ros.context.ok(), 10.0, 'the guarded node to stop')
    finally:
        other.destroy_node()
        rclpy.try_shutdown(context=other_context)


@pytest.mark.parametrize('mutate, field', [
    (lambda d: d.pop('H0'), 'H0: missing'),
    (lambda d: d['obstacles'][0].__setitem__('shape', 'cone'), 'obstacles[0] (table).shape'),
    (lambda d: d['collision'].__setitem__('allowed_pairs', [['hand', 'tabel']]), 'collision.allowed_pairs[0]'),
])
def test_a_bad_robot_description_exits_2_in_seconds_with_one_line_naming_file_and_field(tmp_path: Path, mutate,
                                                                                         field) -> None:
    import yaml

    from body_schema.robot import robot_path

    doc = yaml.safe_load(robot_path('ur5e').read_text())
    mutate(doc)
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump(doc))
    out = tmp_path / 'run'
    t0 = time.monotonic()
    proc = subprocess.run([str(SCRIPT), '--robot', str(bad), '--output', str(out)], env=_env(), capture_output=True,
                          text=True, timeout=60)
    took = time.monotonic() - t0
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count('\n') == 1 and str(bad) in proc.stderr and field in proc.stderr, proc.stderr
    assert 'Traceback' not in proc.stderr and not out.exists()
    assert took < 10.0, took          # the 5 s on an idle machine; this one is shared


def test_a_bad_pose_list_exits_2_naming_it(tmp_path: Path) -> None:
    poses = tmp_path / 'poses.yaml'
    poses.write_text('joint_names: [a, b]\nposes: [[0, 0]]\n')
    proc = subprocess.run([str(SCRIPT), '--robot', 'ur5e', '--poses', str(poses), '--output', str(tmp_path / 'run')],
                          env=_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.count('\n') == 1, proc.stderr
    assert str(poses) in proc.stderr and 'joint_names' in proc.stderr, proc.stderr


def test_plan_only_without_the_collision_check_says_so_and_records_no_margin(tmp_path: Path) -> None:
    import yaml

    proc = subprocess.run([str(SCRIPT), '--robot', 'ur5e', '--plan-only', '--no-collision-check', '--iterations', '2',
                           '--output', str(tmp_path)], env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert 'NOT checked against the obstacles' in proc.stdout, proc.stdout
    plan = yaml.safe_load((tmp_path / 'plan.yaml').read_text())
    assert len(plan['poses']) == 2 and plan['clearance'] == []
    assert plan['planned']['margin_m'] is None and plan['planned']['refused'] == 0


def test_plan_only_moves_nothing_and_a_run_visits_the_reviewed_poses_first(tmp_path: Path) -> None:
    """--plan-only writes a pose list (no node starts); --poses visits it first, then AL takes over,
    with every command timed at the scaled speed and the simulator reporting no contact."""
    import yaml

    plan_dir = tmp_path / 'plan'
    proc = subprocess.run([str(SCRIPT), '--robot', 'icub_right_arm', '--plan-only', '--iterations', '2', '--seed', '3',
                           '--output', str(plan_dir)], env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert not (plan_dir / 'logs').exists() and not (plan_dir / 'run.ids').exists()   # nothing started
    plan = yaml.safe_load((plan_dir / 'plan.yaml').read_text())
    assert len(plan['poses']) == 2 and len(plan['clearance']) == 2
    assert all(c['path_clearance_m'] > 0.0 for c in plan['clearance'])
    out = tmp_path / 'run'
    proc = subprocess.run([str(SCRIPT), '--poses', str(plan_dir / 'plan.yaml'), '--iterations', '3',
                           '--speed-scale', '0.5', '--output', str(out), *FAST,
                           # Neither the re-run's agreement nor the estimator keeping up at --rtf 2 is this
                           # test's subject (under the whole suite's load one of the 3 verdicts came late).
                           '--max-dh-difference', '1000', '--max-timeouts', '1.0'],
                          env=_env(), capture_output=True,
                          text=True, timeout=400)
    assert proc.returncode == 0, proc.stderr + (out / 'logs' / 'selector.log').read_text()[-2000:]
    records = [json.loads(line) for line in (out / 'progress.jsonl').read_text().splitlines()]
    assert [r['source'] for r in records] == ['pose_list', 'pose_list', 'batch:BOBYQA']
    np.testing.assert_allclose([r['target_deg'] for r in records[:2]], plan['poses'], atol=1e-6)
    assert all(r['command_s'] > 0 for r in records)
    sim_log = (out / 'logs' / 'sim.log').read_text()
    assert 'contact at' not in sim_log
