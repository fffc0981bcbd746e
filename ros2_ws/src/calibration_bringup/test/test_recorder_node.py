"""The MCAP recorder: in-process round trip through two readers, late topics, SIGTERM, SIGKILL."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from mcap.exceptions import McapError
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray, String

from calibration_interfaces import mcap_reader as bag
from calibration_bringup.recorder_node import RecorderNode
from calibration_interfaces.node_util import qos_profile

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
N = 20


def _recorder(ros: Any, path: Path, **params: Any) -> RecorderNode:
    # TF is derived from the iCub's topics; these tests publish other data (test_tf_recording.py covers TF).
    overrides = [Parameter(k, value=v) for k, v in {'output': str(path), 'discovery_period': 0.1,
                                                    'record_tf': False, **params}.items()]
    return ros.add(RecorderNode(context=ros.context, parameter_overrides=overrides))


def _joint_state(i: int) -> JointState:
    m = JointState(name=['r_elbow'], position=[0.01 * i])
    m.header.stamp.sec = i
    return m


def test_records_contract_topics_readable_by_mcap_and_rosbags(ros: Any, tmp_path: Path) -> None:
    probe = ros.node('probe')
    # A fact published (and latched) before the recorder exists must still be recorded.
    truth = probe.create_publisher(Float64MultiArray, '/body_schema/true', LATCHED)
    truth.publish(Float64MultiArray(data=[1.0, 2.0, 3.0]))
    js = probe.create_publisher(JointState, '/joint_states', 10)
    hand = probe.create_publisher(PoseWithCovarianceStamped, '/hand_pose', 10)
    img = probe.create_publisher(Image, '/camera/left/image_raw', qos_profile_sensor_data)

    path = tmp_path / 'rec' / 'run.mcap'
    rec = _recorder(ros, path)
    pubs = (truth, js, hand, img)
    ros.spin_until(lambda: all(p.get_subscription_count() for p in pubs), 15.0, 'the recorder subscribing')
    ros.spin_until(lambda: rec.counts.get('/body_schema/true') == 1, 10.0, 'the latched fact')
    for i in range(N):
        js.publish(_joint_state(i))
        hand.publish(PoseWithCovarianceStamped())
        img.publish(Image(height=2, width=3, encoding='rgb8', step=9, data=bytes(range(i, i + 18))))
        ros.executor.spin_once(timeout_sec=0.001)
    want = {'/body_schema/true': 1, '/joint_states': N, '/hand_pose': N, '/camera/left/image_raw': N}
    ros.spin_until(lambda: rec.counts == want, 10.0, f'{want} recorded (have {rec.counts})')
    rec.close()
    rec.close()   # idempotent
    assert rec.closed and rec.counts == want

    # mcap + mcap_ros2 (through the package's reader)
    s = bag.summary(path)
    assert s.complete and s.profile == 'ros2' and s.message_count == sum(want.values())
    assert {t: i.count for t, i in s.topics.items()} == want
    assert s.topics['/joint_states'].type == 'sensor_msgs/msg/JointState'
    assert all(i.type_hash.startswith('RIHS01_') for i in s.topics.values())
    assert s.topics['/body_schema/true'].offered_qos[0].durability == 'transient_local'
    assert s.topics['/camera/left/image_raw'].offered_qos[0].reliability == 'best_effort'
    msgs = list(bag.read_messages(path, ['/joint_states', '/body_schema/true', '/camera/left/image_raw']))
    assert [m.header.stamp.sec for t, _, m in msgs if t == '/joint_states'] == list(range(N))
    assert [list(m.data) for t, _, m in msgs if t == '/body_schema/true'] == [[1.0, 2.0, 3.0]]
    assert [bytes(m.data) for t, _, m in msgs if t.endswith('image_raw')][-1] == bytes(range(N - 1, N + 17))
    assert msgs[0][0] == '/body_schema/true'   # log-time order: the fact came first

    # rosbags, with its own Jazzy type store; it also checks the recorded RIHS01 type hashes.
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        assert {c.topic: (c.msgtype, c.msgcount) for c in r.connections} == {
            t: (s.topics[t].type, n) for t, n in want.items()}
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in r.connections}
        assert qos['/body_schema/true'].durability.name == 'TRANSIENT_LOCAL'
        conns = [c for c in r.connections if c.topic == '/joint_states']
        positions = [r.deserialize(raw, c.msgtype).position[0] for c, _, raw in r.messages(conns)]
    assert positions == pytest.approx([0.01 * i for i in range(N)])


def test_a_stalled_recorder_loses_no_joint_state_and_keeps_their_publication_order(ros: Any, tmp_path: Path) -> None:
    """Three seconds of joint states at rtf 2 (300) wait while the recorder's executor is busy.

    On main its reliable queue was 100 deep (one second of them): a launched run under load lost
    a fifth of its joint states and the offline re-run lacked what the estimator had used.
    """
    probe = ros.node('probe')
    js = probe.create_publisher(JointState, '/joint_states', qos_profile('/joint_states'))
    hand = probe.create_publisher(PoseWithCovarianceStamped, '/hand_pose', qos_profile('/hand_pose'))
    path = tmp_path / 'stalled.mcap'
    rec = _recorder(ros, path)
    ros.spin_until(lambda: js.get_subscription_count() and hand.get_subscription_count(), 15.0,
                   'the recorder subscribing')
    n = 300
    for i in range(n):              # nobody spins: the recorder's executor is stalled meanwhile
        js.publish(_joint_state(i))
        if i % 10 == 5:
            hand.publish(PoseWithCovarianceStamped())
    ros.spin_until(lambda: rec.counts.get('/joint_states') == n and rec.counts.get('/hand_pose') == n // 10, 20.0,
                   f'{n} joint states and {n // 10} hand poses recorded (have {rec.counts})')
    rec.close()
    assert bag.recording_metadata(path)['publish_time'] == 'source'
    assert [m.header.stamp.sec for _, _, m in bag.read_messages(path, ['/joint_states'])] == list(range(n))
    # Read by publish time, each hand pose follows the joint state published before it, as the
    # executor took them (one per topic per wait) or not.
    order = [(t, m.header.stamp.sec) for t, _, m in bag.read_messages(path, ['/joint_states', '/hand_pose'],
                                                                     order='publication')]
    hand_after = [order[k - 1][1] for k, (t, _) in enumerate(order) if t == '/hand_pose']
    assert hand_after == list(range(5, n, 10))


def test_a_stopped_recorder_first_records_what_its_queues_hold(ros: Any, tmp_path: Path) -> None:
    """What a busy recorder holds when it is told to stop is recorded before the file is finished.

    On main SIGINT shut the context down at once: a launched run's recorder, seconds behind on
    the joint states, closed its bag without the last 3 s of them (67 hand poses re-run without
    joint states).
    """
    probe = ros.node('probe')
    js = probe.create_publisher(JointState, '/joint_states', qos_profile('/joint_states'))
    path = tmp_path / 'drained.mcap'
    rec = _recorder(ros, path, flush_period=0.05)       # a timer turn on the way must not end the drain
    ros.spin_until(lambda: js.get_subscription_count(), 15.0, 'the recorder subscribing')
    for i in range(200):
        js.publish(_joint_state(i))
    t0 = time.monotonic()
    assert rec.drain(lambda timeout: ros.executor.spin_once(timeout_sec=timeout)) == 200
    assert time.monotonic() - t0 < 5.0
    assert rec.drain(lambda timeout: ros.executor.spin_once(timeout_sec=timeout)) == 0   # drained
    rec.close()
    assert [m.header.stamp.sec for _, _, m in bag.read_messages(path, ['/joint_states'])] == list(range(200))


def test_late_topics_extra_topics_and_excluded_images(ros: Any, tmp_path: Path) -> None:
    path = tmp_path / 'late.mcap'
    rec = _recorder(ros, path, topics=['/joint_states', '/camera/left/image_raw', 'extra'],
                    exclude_images=True, compression='lz4')
    assert rec.wanted == ['/joint_states', '/extra']   # relative names resolve; images left out
    ros.spin_for(0.3)   # nothing published yet: nothing subscribed
    assert rec.counts == {}
    probe = ros.node('probe')
    extra = probe.create_publisher(String, '/extra', 10)     # not in the contract: type discovered
    img = probe.create_publisher(Image, '/camera/left/image_raw', qos_profile_sensor_data)
    js = probe.create_publisher(JointState, '/joint_states', 10)
    ros.spin_until(lambda: extra.get_subscription_count() and js.get_subscription_count(), 15.0,
                   'the recorder subscribing to topics that appeared')
    for i in range(5):
        extra.publish(String(data=f'e{i}'))
        js.publish(_joint_state(i))
        img.publish(Image())
    ros.spin_until(lambda: rec.counts == {'/extra': 5, '/joint_states': 5}, 10.0, 'late topics recorded')
    assert img.get_subscription_count() == 0
    rec.destroy_node()   # finishes the file too (the fixture's second destroy is harmless)
    s = bag.summary(path)
    assert s.complete and s.topics['/extra'].type == 'std_msgs/msg/String'
    assert [m.data for _, _, m in bag.read_messages(path, ['/extra'])] == [f'e{i}' for i in range(5)]


def test_refuses_to_overwrite_when_told(ros: Any, tmp_path: Path) -> None:
    path = tmp_path / 'x.mcap'
    path.write_bytes(b'keep me')
    with pytest.raises(FileExistsError, match='x.mcap'):
        RecorderNode(context=ros.context, parameter_overrides=[
            Parameter('output', value=str(path)), Parameter('overwrite', value=False)])
    assert path.read_bytes() == b'keep me'


# --- the recorder as a process ---------------------------------------------------------------

@pytest.fixture
def start_recorder(ros: Any) -> Iterator[Callable[..., subprocess.Popen]]:
    """Starts recorder processes; kills any still running when the test ends (a failed wait
    would otherwise leave one recording for the rest of the session)."""
    procs: list[subprocess.Popen] = []

    def start(path: Path, *params: str) -> subprocess.Popen:
        procs.append(_start_recorder(ros, path, *params))
        return procs[-1]

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=15)


def _start_recorder(ros: Any, path: Path, *params: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    exe = Path(sys.executable).parent / 'recorder_node'
    args = ['--ros-args', '-p', f'output:={path}', '-p', 'topics:=[/chatter]', '-p', 'discovery_period:=0.1']
    for p in params:
        args += ['-p', p]
    return subprocess.Popen([str(exe), *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _on_disk(path: Path) -> int:
    """Messages in the chunks written so far (the file is unfinished while recording)."""
    try:
        return bag.summary(path).message_count
    except (OSError, McapError):   # not created yet, or its header not written yet
        return 0


def _wait_on_disk(ros: Any, path: Path, n: int, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + 15.0
    while _on_disk(path) < n:
        if proc.poll() is not None:
            pytest.fail(f'recorder exited early ({proc.returncode}):\n{proc.stdout.read()}')
        if time.monotonic() > deadline:
            pytest.fail(f'only {_on_disk(path)} of {n} messages on disk after 15 s')
        ros.spin_for(0.05)


def _publish_chatter(ros: Any, proc: subprocess.Popen, texts: list[str]) -> None:
    pub = ros.node('probe').create_publisher(String, '/chatter', 100)
    ros.spin_until(lambda: pub.get_subscription_count() or proc.poll() is not None, 20.0,
                   'the recorder process subscribing')
    assert proc.poll() is None, proc.stdout.read()
    for text in texts:
        pub.publish(String(data=text))


def _stop(proc: subprocess.Popen, sig: int) -> str:
    proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f'recorder did not exit on signal {sig}:\n{out}')
    return out


def test_sigterm_finishes_the_file(ros: Any, tmp_path: Path, start_recorder: Callable[..., subprocess.Popen]) -> None:
    path = tmp_path / 'term.mcap'
    proc = start_recorder(path, 'flush_period:=0.05')
    _publish_chatter(ros, proc, [f'm{i}' for i in range(10)])
    _wait_on_disk(ros, path, 10, proc)
    out = _stop(proc, signal.SIGTERM)
    assert proc.returncode == 0, out
    assert '10 messages' in out   # the counts are logged at close
    s = bag.summary(path)
    assert s.complete and s.topics['/chatter'].count == 10, s
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as r:   # the schema stored in the file is enough for rosbags
        assert [r.deserialize(raw, c.msgtype).data for c, _, raw in r.messages()] == [f'm{i}' for i in range(10)]


def test_sigkill_leaves_every_complete_chunk_readable(ros: Any, tmp_path: Path,
                                                     start_recorder: Callable[..., subprocess.Popen]) -> None:
    from mcap.exceptions import EndOfFile
    from mcap.reader import NonSeekingReader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / 'killed.mcap'
    # Small chunks, written only when full: the kill must lose exactly the chunk being built.
    proc = start_recorder(path, 'chunk_size:=4096', 'flush_period:=0.0')
    texts = [f'{i:03d}' + 'x' * 1000 for i in range(30)]   # about 4 messages per chunk
    _publish_chatter(ros, proc, texts)
    _wait_on_disk(ros, path, 20, proc)
    proc.kill()
    proc.communicate(timeout=15)

    got = []
    with open(path, 'rb') as f:   # mcap's own non-seeking reader, up to where the file ends
        try:
            for _, _, _, msg in NonSeekingReader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                    log_time_order=False):
                got.append(msg.data)
        except EndOfFile:
            pass
    assert 20 <= len(got) < 30 and got == texts[:len(got)]
    s = bag.summary(path)
    assert not s.complete and s.message_count == len(got)
    assert [m.data for _, _, m in bag.read_messages(path)] == got
    assert s.loss.startswith(f'bag truncated (killed.mcap was not finished): recovered {len(got)} messages')

    # recover makes it a complete bag that rosbags and mcap's default reader open whole.
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    whole = tmp_path / 'whole.mcap'
    bag.recover(path, whole)
    with whole.open('rb') as f:
        assert [m.data for _, _, _, m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()] \
            == got
    with AnyReader([whole]) as r:
        assert [r.deserialize(raw, c.msgtype).data for c, _, raw in r.messages()] == got
    assert bag.recording_metadata(whole) == bag.recording_metadata(path)


def test_contract_topics_are_recorded_before_discovery_notices_their_publisher(ros: Any, tmp_path: Path) -> None:
    # The selector commands right after it starts; a recorder that waited for its discovery period
    # lost that first command (and with it the first measurement of an offline re-run).
    path = tmp_path / 'early.mcap'
    rec = _recorder(ros, path, discovery_period=60.0)       # discovery never runs after start
    probe = ros.node('probe')
    cmd = probe.create_publisher(String, '/calibration/progress', qos_profile('/calibration/progress'))  # as the selector
    best_effort_js = probe.create_publisher(JointState, '/joint_states', qos_profile_sensor_data)
    ros.spin_until(lambda: cmd.get_subscription_count() == 1, 10.0, 'the early subscription matching')
    cmd.publish(String(data='first'))
    ros.spin_until(lambda: rec.counts.get('/calibration/progress') == 1, 10.0, 'the first message')
    # A best-effort publisher cannot reach the early reliable subscription: discovery re-subscribes.
    assert best_effort_js.get_subscription_count() == 0
    rec._discover()
    ros.spin_until(lambda: best_effort_js.get_subscription_count() == 1, 10.0, 'the re-subscription')
    best_effort_js.publish(_joint_state(3))
    ros.spin_until(lambda: rec.counts.get('/joint_states') == 1, 10.0, 'the best-effort joint state')
    rec.close()
    s = bag.summary(path)
    assert s.topics['/calibration/progress'].count == 1
    assert s.topics['/calibration/progress'].offered_qos[0].reliability == 'reliable'
    assert s.topics['/joint_states'].offered_qos[0].reliability == 'best_effort'
