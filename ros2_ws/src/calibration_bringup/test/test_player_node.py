"""The bag player: record -> play gives the recorded bytes back, with /clock and the recorded QoS."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray, String

from calibration_bringup.mcap_writer import McapBagWriter
from calibration_interfaces import mcap_reader as bag
from calibration_interfaces.contract import PUBLISH_TIME_SOURCE
from calibration_interfaces.mcap_reader import QosOffer
from calibration_bringup.player_node import BagPlayerNode, playback_qos
from calibration_bringup.recorder_node import RecorderNode

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
N = 15


def _player(ros: Any, path: Path, **params: Any) -> BagPlayerNode:
    overrides = [Parameter(k, value=v) for k, v in {'bag': str(path), **params}.items()]
    return ros.add(BagPlayerNode(context=ros.context, parameter_overrides=overrides))


def _record(ros: Any, path: Path) -> None:
    probe = ros.node('source')
    truth = probe.create_publisher(Float64MultiArray, '/body_schema/true', LATCHED)
    truth.publish(Float64MultiArray(data=[4.0, 5.0]))
    js = probe.create_publisher(JointState, '/joint_states', 10)
    img = probe.create_publisher(Image, '/camera/left/image_raw', qos_profile_sensor_data)
    # image_transport's compressed topic is recorded and played like the raw one.
    jpeg = probe.create_publisher(CompressedImage, '/camera/left/image_raw/compressed', qos_profile_sensor_data)
    rec = ros.add(RecorderNode(context=ros.context, parameter_overrides=[
        Parameter('output', value=str(path)), Parameter('discovery_period', value=0.1),
        Parameter('record_tf', value=False)]))   # this test's joint states are not the iCub's
    ros.spin_until(lambda: all(p.get_subscription_count() for p in (truth, js, img, jpeg)), 15.0, 'recorder')
    ros.spin_until(lambda: rec.counts.get('/body_schema/true') == 1, 10.0, 'the latched fact')
    for i in range(N):
        js.publish(JointState(name=['a'], position=[float(i)]))
        img.publish(Image(height=1, width=i + 1, encoding='mono8', step=i + 1, data=bytes(i + 1)))
        jpeg.publish(CompressedImage(format='rgb8; jpeg compressed bgr8', data=bytes([i]) * (i + 3)))
        ros.spin_for(0.01)   # spread the log times a little: the player reproduces the spacing
    want = {'/body_schema/true': 1, '/joint_states': N, '/camera/left/image_raw': N,
            '/camera/left/image_raw/compressed': N}
    ros.spin_until(lambda: rec.counts == want, 10.0, f'{want} recorded')
    rec.close()
    for p in (truth, js, img, jpeg):   # the player must be the only source from here on
        probe.destroy_publisher(p)


def test_record_then_play_gives_the_recorded_bytes_and_clock(ros: Any, tmp_path: Path) -> None:
    path = tmp_path / 'rec.mcap'
    _record(ros, path)
    recorded = {t: [m.data for m in bag.read_raw(path, [t])] for t in bag.summary(path).topics}
    s = bag.summary(path)

    jpeg = '/camera/left/image_raw/compressed'
    got: dict[str, list[bytes]] = {'/joint_states': [], '/camera/left/image_raw': [], jpeg: [], '/clock': []}
    sink = ros.node('sink')
    sink.create_subscription(JointState, '/joint_states', got['/joint_states'].append, 100, raw=True)
    sink.create_subscription(Image, '/camera/left/image_raw', got['/camera/left/image_raw'].append,
                             qos_profile_sensor_data, raw=True)
    sink.create_subscription(CompressedImage, jpeg, got[jpeg].append, qos_profile_sensor_data, raw=True)
    sink.create_subscription(Clock, '/clock', got['/clock'].append, CLOCK_QOS)

    player = _player(ros, path, start_paused=True)
    pubs = player.publishers_by_topic
    assert pubs['/camera/left/image_raw'].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert pubs[jpeg].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert pubs['/body_schema/true'].qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert pubs['/joint_states'].qos_profile.reliability == ReliabilityPolicy.RELIABLE
    ros.spin_until(lambda: pubs['/joint_states'].get_subscription_count() and pubs[jpeg].get_subscription_count()
                   and pubs['/camera/left/image_raw'].get_subscription_count(), 15.0, 'player <-> sink')
    ros.spin_for(0.2)
    assert got['/joint_states'] == [] and not player.done   # paused until resumed
    t0 = time.monotonic()
    assert player.resume() and not player.resume()
    ros.spin_until(lambda: player.done, 15.0, 'the end of the bag')
    assert time.monotonic() - t0 >= 0.9 * s.duration_s   # rate 1 keeps the recorded spacing
    ros.spin_until(lambda: len(got['/joint_states']) == N and len(got['/camera/left/image_raw']) == N
                   and len(got[jpeg]) == N, 10.0, 'every played message')

    assert got['/joint_states'] == recorded['/joint_states']   # byte for byte
    assert got['/camera/left/image_raw'] == recorded['/camera/left/image_raw']
    assert got[jpeg] == recorded[jpeg]
    assert player.published == {t: len(v) for t, v in recorded.items()}
    def stamps() -> list[int]:
        return [c.clock.sec * 10**9 + c.clock.nanosec for c in got['/clock']]
    # /clock runs on the log times, from the first message's to the last message's.
    ros.spin_until(lambda: stamps() and stamps()[-1] == s.end_ns, 10.0, 'the final /clock')
    assert stamps() == sorted(stamps()) and stamps()[0] >= s.start_ns

    # The fact is still there for a subscriber that comes late (transient local, as recorded).
    late: list[bytes] = []
    sink.create_subscription(Float64MultiArray, '/body_schema/true', late.append, LATCHED, raw=True)
    ros.spin_until(lambda: late, 10.0, 'the latched fact on a late subscriber')
    assert late == recorded['/body_schema/true']


def test_fast_filtered_looping_playback_replaces_the_recorded_clock(ros: Any, tmp_path: Path) -> None:
    path = tmp_path / 'synthetic.mcap'
    with McapBagWriter(path) as w:
        w.add_channel('/clock', 'rosgraph_msgs/msg/Clock')
        w.add_channel('/chatter', 'std_msgs/msg/String', [QosOffer()])
        w.add_channel('/other', 'std_msgs/msg/String')
        for i in range(5):   # 100 s of log time: rate 0 must not wait for it
            t = (1000 + 20 * i) * 10**9
            w.write('/clock', serialize_message(Clock()), t)
            w.write('/chatter', serialize_message(String(data=f'c{i}')), t)
            w.write('/other', serialize_message(String(data='o')), t)
    got: list[String] = []
    clock: list[Clock] = []
    sink = ros.node('sink')
    sink.create_subscription(String, '/chatter', got.append, 100)
    sink.create_subscription(Clock, '/clock', clock.append, CLOCK_QOS)
    player = _player(ros, path, rate=0.0, topics=['/chatter', '/missing'], loop=True, start_paused=True)
    assert set(player.publishers_by_topic) == {'/chatter'}   # filtered; /clock is the player's own
    ros.spin_until(lambda: player.publishers_by_topic['/chatter'].get_subscription_count(), 15.0, 'discovery')
    player.resume()
    ros.spin_until(lambda: player.published['/chatter'] >= 15, 10.0, 'three loops at full speed')
    assert not player.done   # looping never ends
    ros.spin_until(lambda: len(got) >= 10, 10.0, 'played messages')
    assert [m.data for m in got[:10]] == [f'c{i % 5}' for i in range(10)]
    assert clock and all(c.clock.sec >= 1000 for c in clock)   # from log times, not the recorded zeros


def test_a_bag_logged_behind_on_one_topic_is_played_in_publication_order(ros: Any, tmp_path: Path) -> None:
    """The recorder logged /hand_pose-like messages 1.5 s before the /joint_states-like ones
    published before them; the player sends them in the order they were published.

    On main it played log order: a fresh estimator fed a launched run's bag made 1 of its 5
    updates (each hand pose came before its joint states, and the next command before both).
    """
    path = tmp_path / 'lagging.mcap'
    sent = []              # (publish time, topic, text): what the publishers did, in order
    for i in range(6):
        sent += [(10 * i, '/first', f'f{i}'), (10 * i + 5, '/second', f's{i}')]
    with McapBagWriter(path) as w:
        w.add_metadata('recording', {'log_time': 'sim', 'tf': 'none', 'publish_time': PUBLISH_TIME_SOURCE})
        for topic in ('/first', '/second'):
            w.add_channel(topic, 'std_msgs/msg/String', [QosOffer()])
        # Log time: publication + 1.5 s for /first (the topic the recorder is behind on).
        logged = sorted(sent, key=lambda e: e[0] * 10**6 + (1_500_000_000 if e[1] == '/first' else 0))
        last = 0
        for pub_ms, topic, text in logged:
            last = max(last + 1, pub_ms * 10**6 + (1_500_000_000 if topic == '/first' else 0))
            w.write(topic, serialize_message(String(data=text)), last, pub_ms * 10**6)
    player = _player(ros, path, rate=0.0, start_paused=True)
    # The order of the publish calls (a subscriber's executor takes one message per topic per wait,
    # so what it receives across topics interleaves whatever the order sent).
    got: list[str] = []
    for pub in player.publishers_by_topic.values():
        pub.publish = lambda data, _publish=pub.publish: (got.append(deserialize_message(data, String).data),
                                                           _publish(data))
    player.resume()
    ros.spin_until(lambda: player.done, 10.0, f'the bag played (have {got})')
    assert got == [text for _, _, text in sent]


def test_playback_qos_and_bad_parameters(ros: Any, tmp_path: Path) -> None:
    latched = playback_qos((QosOffer(durability='transient_local'),), '/x')
    assert (latched.durability, latched.depth) == (DurabilityPolicy.TRANSIENT_LOCAL, 1)
    mixed = playback_qos((QosOffer(), QosOffer(reliability='best_effort')), '/camera/left/pose')
    assert mixed.durability == DurabilityPolicy.TRANSIENT_LOCAL   # falls back to the contract
    assert playback_qos((), '/y').reliability == ReliabilityPolicy.RELIABLE
    with pytest.raises(ValueError, match="'bag'"):
        BagPlayerNode(context=ros.context)
    with pytest.raises(FileNotFoundError):
        BagPlayerNode(context=ros.context, parameter_overrides=[Parameter('bag', value=str(tmp_path / 'no.mcap'))])


def test_console_script_plays_to_the_end_and_exits(tmp_path: Path) -> None:
    path = tmp_path / 'tiny.mcap'
    with McapBagWriter(path) as w:
        w.add_channel('/chatter', 'std_msgs/msg/String')
        for i in range(3):
            w.write('/chatter', serialize_message(String(data=str(i))), 10**9 + i * 10**7)
    exe = Path(sys.executable).parent / 'bag_player'
    out = subprocess.run([str(exe), '--ros-args', '-p', f'bag:={path}'], capture_output=True, text=True,
                         timeout=30, check=False)
    assert out.returncode == 0, out.stderr
    assert '3 messages published' in out.stderr


@pytest.mark.parametrize('content, says', [(b'', 'is empty'), (b'not a bag at all', 'is not an MCAP file')])
def test_console_script_refuses_an_empty_or_foreign_file_in_one_line(tmp_path: Path, content: bytes,
                                                                      says: str) -> None:
    # On main both printed a raw traceback (EndOfFile, InvalidMagic).
    path = tmp_path / 'x.mcap'
    path.write_bytes(content)
    exe = Path(sys.executable).parent / 'bag_player'
    out = subprocess.run([str(exe), '--ros-args', '-p', f'bag:={path}'], capture_output=True, text=True,
                         timeout=30, check=False)
    assert out.returncode == 1
    assert out.stderr.startswith(f'bag_player: {path} {says}') and 'Traceback' not in out.stderr, out.stderr
