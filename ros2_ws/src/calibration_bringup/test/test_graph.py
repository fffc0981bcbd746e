"""The in-process graph assembly: parameter layering and callback timing (the whole graph runs in
tests/test_closed_loop.py and the experiment tests)."""
from __future__ import annotations

import inspect
import os
import time

import pytest
from std_msgs.msg import String

from calibration_bringup.graph import (PARAMS_FILES, CallbackTimer, InProcessGraph, config_dir, default_parameters,
                                       merge_parameters, ros_session, with_detector_eyes)
from calibration_interfaces.parameters import read_params_file


def test_later_layers_win_per_parameter_and_defaults_are_not_shared() -> None:
    merged = merge_parameters({'sim': {'a': 1, 'b': 2}}, {'sim': {'b': 3}, 'selector': {'iterations': 3}})
    assert merged == {'sim': {'a': 1, 'b': 3}, 'selector': {'iterations': 3}}
    defaults = default_parameters()
    defaults['detector']['x'] = 1
    assert 'x' not in default_parameters()['detector']


def test_the_graph_runs_with_the_parameter_files_of_the_launcher() -> None:
    params = default_parameters()
    for key, (name, node) in PARAMS_FILES.items():
        from_file = read_params_file(config_dir() / name, node)
        kept = {k: v for k, v in from_file.items() if k not in ('cameras', 'use_sim_time')}
        assert kept.items() <= params[key].items(), key
    assert params['estimator']['iterations'] == 5            # the iterated EKF every run uses
    # In process: sim as fast as possible, left eye, everything else on its clock, no export.
    assert params['sim']['real_time_factor'] == 0.0 and params['sim']['cameras'] == ['left']
    assert all(params[k]['use_sim_time'] for k in ('detector', 'estimator', 'selector'))
    assert params['estimator']['export_on_shutdown'] is False


def test_the_simulator_renders_the_eyes_the_detector_reads() -> None:
    left = {'sim': {'cameras': ['left']}, 'detector': {'use_right_eye': False}}
    assert with_detector_eyes(merge_parameters(left))['sim']['cameras'] == ['left']
    stereo = merge_parameters(left, {'detector': {'use_right_eye': True}})
    assert with_detector_eyes(stereo)['sim']['cameras'] == ['left', 'right']
    # A fixed camera's description (no cameras listed: the description's own) is left alone, and
    # a robot without eyes renders its one camera.
    fixed = {'sim': {'cameras': []}, 'detector': {'use_right_eye': True}}
    assert with_detector_eyes(fixed)['sim']['cameras'] == []
    ur5e = {'sim': {'cameras': ['left'], 'robot': 'ur5e'}, 'detector': {'use_right_eye': True}}
    assert with_detector_eyes(ur5e)['sim']['cameras'] == ['left']


def test_parameters_for_a_node_the_graph_lacks_are_refused(ros) -> None:
    with pytest.raises(ValueError, match='selectr'):
        InProcessGraph(ros.context, ros.executor, {'selectr': {'iterations': 3}})


def test_a_parameter_no_node_declares_is_refused(ros) -> None:
    # rclpy would keep the override unused: a misspelt --set ran with the default.
    with pytest.raises(ValueError, match='estimator has no parameter verdict_nfv'):
        InProcessGraph(ros.context, ros.executor, {'estimator': {'verdict_nfv': 200}})


def test_callbacks_created_later_are_timed_and_keep_their_signature(ros) -> None:
    node = ros.node('timed')
    timer = CallbackTimer()
    timer.watch('n', node)
    infos = []
    # Created after watch(), like the recorder's subscriptions on discovery; two arguments: rclpy
    # passes the message info only if the wrapper still shows that signature.
    sub = node.create_subscription(String, 'chatter', lambda msg, info: infos.append(info), 10)
    timer.refresh()
    with pytest.raises(TypeError):
        inspect.signature(sub.callback).bind(object())
    pub = ros.node('pub').create_publisher(String, 'chatter', 10)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, 10.0, 'discovery')
    pub.publish(String(data='x'))
    ros.spin_until(lambda: infos, 5.0, 'message')
    assert 'source_timestamp' in infos[0]
    assert timer.totals['n'] > 0
    timer.refresh()                                   # wrapped once, not again
    assert not hasattr(sub.callback.__wrapped__, '_timed')


def test_a_session_without_qos_events_delivers_but_never_waits_on_event_handlers() -> None:
    from rclpy.node import Node

    domain = 180 + os.getpid() % 10      # clear of the fixture's 1..100 and the experiment's
    for qos_events in (True, False):
        with ros_session(domain, qos_events) as (ctx, executor):
            node = Node('session_probe', context=ctx)
            executor.add_node(node)
            got: list[String] = []
            node.create_subscription(String, 'chatter', got.append, 10)
            pub = node.create_publisher(String, 'chatter', 10)
            handlers = list(node.waitables)       # rclpy's default incompatible-QoS/type handlers
            assert handlers and all(executor.can_execute(h) is qos_events for h in handlers)
            deadline = time.monotonic() + 10.0
            while not got and time.monotonic() < deadline:
                pub.publish(String(data='x'))
                executor.spin_once(timeout_sec=0.01)
            executor.remove_node(node)
            node.destroy_node()
        assert got and got[0].data == 'x', f'qos_events={qos_events}: no message within 10 s'


_TALKER = """
import sys, time, rclpy
from rclpy.context import Context
from std_msgs.msg import String
ctx = Context(); rclpy.init(context=ctx, domain_id=int(sys.argv[1]))
node = rclpy.create_node('other_graph', context=ctx)
pub = node.create_publisher(String, 'chatter', 10)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    pub.publish(String(data='other')); time.sleep(0.02)
"""


def test_a_session_without_discovery_hears_only_its_own_process() -> None:
    import subprocess
    import sys

    from rclpy.node import Node

    domain = 190 + os.getpid() % 10      # clear of the fixture's 1..100 and the experiment's
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    talker = subprocess.Popen([sys.executable, '-c', _TALKER, str(domain), '60'], env=env)
    try:
        heard = {}
        for discovery in ('LOCALHOST', 'OFF'):
            with ros_session(domain, discovery=discovery) as (ctx, executor):
                node = Node('listener', context=ctx)
                executor.add_node(node)
                got: set[str] = set()
                node.create_subscription(String, 'chatter', lambda m: got.add(m.data), 10)
                pub = node.create_publisher(String, 'chatter', 10)
                # LOCALHOST must meet the talker (the control); OFF gets 5 s to wrongly do so.
                deadline = time.monotonic() + (20.0 if discovery == 'LOCALHOST' else 5.0)
                while time.monotonic() < deadline and not (discovery == 'LOCALHOST' and 'other' in got):
                    pub.publish(String(data='own'))
                    executor.spin_once(timeout_sec=0.01)
                executor.remove_node(node)
                node.destroy_node()
            heard[discovery] = got
    finally:
        talker.kill()
        talker.wait()
    assert 'other' in heard['LOCALHOST'], 'control: the other process never reached a LOCALHOST session'
    assert heard['OFF'] == {'own'}, heard['OFF']
    # Processes started afterwards must not inherit OFF (the session's nodes were created after init).
    assert os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') == 'LOCALHOST'


def test_a_session_refuses_an_unknown_discovery_range() -> None:
    with pytest.raises(ValueError, match='SUBNET'):
        with ros_session(1, discovery='SUBNET'):
            pass
