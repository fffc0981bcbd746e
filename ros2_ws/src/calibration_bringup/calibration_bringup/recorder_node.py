"""MCAP recorder node: records topics to one rosbag2-compatible ``.mcap`` file.

The file opens in ``ros2 bag play FILE.mcap``, the ``mcap`` and ``rosbags`` libraries and
Foxglove (format: :mod:`calibration_bringup.mcap_writer`). Messages are taken raw (the CDR bytes
as received) and written with their receive time as log time and the publisher's source
timestamp as publish time (metadata ``publish_time: source``: sorted by it, a bag's topics come
in the order they were published, whatever order the recorder took them in). With
``use_sim_time`` (as ``ros2 bag record --use-sim-time``; the launcher's ``config/recorder.yaml``
sets it) the receive time is read on the simulation clock, so log times and ``header.stamp``
agree (log time = the latest ``/clock`` received, plus a nanosecond per message already logged
in that tick so that log-time order is arrival order; a ``/clock`` message is logged at its own
time). The file's ``recording`` metadata says which clock it is (``log_time: sim`` or ``system``).

With ``record_tf`` the recorder also writes ``/tf`` and ``/tf_static`` (tf2_msgs/msg/TFMessage)
computed from what it records, as a robot state publisher would publish them
(:mod:`calibration_bringup.tf_recording`; there is no tf2_msgs wheel to publish them with).

Contract topics are subscribed at start with the contract's QoS, so nothing published before
discovery notices a new publisher is lost; other topics are subscribed when they have publishers
(checked every ``discovery_period``). QoS is adapted to what the publishers offer, as rosbag2 does: reliable if all of them are reliable,
transient local if all of them are (so latched facts published before the recorder started are
recorded), best effort otherwise. Types come from discovery; the publishers' QoS is stored in
the file so that the player offers it again.

On SIGINT or SIGTERM the recorder first takes what its queues still hold (until nothing arrived
for ``DRAIN_QUIET_S``, at most ``DRAIN_DEADLINE_S``; a second signal cuts it short): the launcher
stops it after every other node, and a recorder behind on the joint states held the last seconds
of them, which rclpy's handlers, shutting the context down at once, threw away. On
``destroy_node`` and on ``close()`` the file is finished (summary, indexes). After a SIGKILL it is readable up to its last
complete chunk; ``flush_period`` bounds how much is lost, and a record of the run (a topic with
the contract's HISTORY QoS: the estimator's verdicts, the selector's progress) is flushed to the
file as it arrives, with everything before it, so a SIGKILL never loses an accepted observation
the recorder had received (one accepted verdict in about one SIGKILL in two was lost).

Subscriptions
-------------
``topics`` (default: every topic of the contract, :mod:`calibration_interfaces.contract`)
    Any type; raw.

Parameters
----------
output : str
    Path of the ``.mcap`` file (parent directories created). Default: ``recording_<time>.mcap``.
overwrite : bool
    Replace an existing ``output`` (default true, with a warning: a re-run replaces its bag;
    false refuses, as rosbag2 does).
topics : string array
    Topics to record (default: the contract); others may be added, their type is discovered.
exclude : string array
    Topics left out.
exclude_images : bool
    Leave out the camera image topics (their bandwidth dominates a bag).
compression : 'zstd' | 'lz4' | 'none'
    Chunk compression.
chunk_size : int
    Uncompressed bytes per chunk.
flush_period : float
    Seconds after which a partial chunk is written anyway (0: only when full).
discovery_period : float
    Seconds between checks for new publishers.
queue_depth : int
    Subscription queue depth (keep last) of best-effort topics (the images).
reliable_queue_depth : int
    Subscription queue depth (keep last) of reliable topics (default
    :data:`calibration_interfaces.contract.RECORD_DEPTH`): the executor takes one message per topic
    per wait, so the fast streams back up while it is busy, and what overflows is lost.
record_tf : bool
    Write ``/tf`` and ``/tf_static`` derived from the joint states, the real and estimated DH
    tables and the camera poses.
robot : str
    Robot description of those frames (packaged name or YAML path); contract camera topics of
    cameras it does not have are left out.
use_sim_time : bool
    Log times on ``/clock`` (the standard parameter of every node).
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import functools
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy

from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from rclpy.serialization import deserialize_message
from rclpy.signals import uninstall_signal_handlers
from geometry_msgs.msg import PoseStamped
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from body_schema.robot import load_robot

from calibration_interfaces.contract import BY_NAME, HISTORY, IMAGE_TOPICS, PUBLISH_TIME_SOURCE, ContractTopic
from calibration_interfaces.mcap_reader import QosOffer
from calibration_interfaces.messages import MessageFormatError, msg_to_table, pose_msg_to_matrix
from calibration_interfaces.node_util import WarnOnce, declare_settings, message_class, qos_profile, spin_node

from .mcap_writer import McapBagWriter
from .node_settings import RecorderSettings
from .tf_recording import TF_STATIC_TOPIC, TF_TOPIC, TF_TYPE, TfBook, TfRecord

#: What a tf2 broadcaster offers: /tf a reliable stream, /tf_static latched (depth 1).
_TF_QOS = {TF_TOPIC: QosOffer('keep_last', 100, 'reliable', 'volatile'),
           TF_STATIC_TOPIC: QosOffer('keep_last', 1, 'reliable', 'transient_local')}


#: After SIGINT / SIGTERM: the queues are drained once nothing arrived for this long [s] ...
DRAIN_QUIET_S = 0.25
#: ... or after this long at most [s] (the launcher kills a node 15 s after its SIGINT).
DRAIN_DEADLINE_S = 10.0


def qos_offer(profile: QoSProfile) -> QosOffer:
    """An endpoint's rclpy QoS as the plain :class:`QosOffer` the writer stores."""
    return QosOffer(
        history=HistoryPolicy(profile.history).name.lower(),
        depth=int(profile.depth),
        reliability=ReliabilityPolicy(profile.reliability).name.lower(),
        durability=DurabilityPolicy(profile.durability).name.lower(),
        deadline_ns=profile.deadline.nanoseconds,
        lifespan_ns=profile.lifespan.nanoseconds,
        liveliness=LivelinessPolicy(profile.liveliness).name.lower(),
        liveliness_lease_duration_ns=profile.liveliness_lease_duration.nanoseconds,
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def request_qos(offers: list[QoSProfile], depth: int, reliable_depth: int | None = None) -> QoSProfile:
    """rosbag2's subscription QoS for a set of publishers (compatible with all of them).

    ``depth`` is the queue of a best-effort subscription, ``reliable_depth`` (default ``depth``)
    that of a reliable one.
    """
    reliable = bool(offers) and all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    latched = bool(offers) and all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    return QoSProfile(depth=reliable_depth if reliable and reliable_depth is not None else depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _stamp_ns(stamp: Any) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class RecorderNode(Node):
    """Records topics into one MCAP file (see the module docstring).

    Attributes
    ----------
    output : Path
        The file being written.
    counts : dict of str to int
        Messages written per topic (topics with a channel).
    wanted : list of str
        Topics this recorder records once they are published.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('mcap_recorder', **kwargs)
        s = self.settings = declare_settings(self, RecorderSettings)
        output = s.output or time.strftime('recording_%Y%m%d-%H%M%S.mcap')
        self.output = Path(output).expanduser().resolve()
        if self.output.exists():
            if not s.overwrite:
                raise FileExistsError(f'output {str(self.output)!r} exists (overwrite is false)')
            self.get_logger().warning(f'replacing {self.output}')
        excluded = set(s.exclude) | (set(IMAGE_TOPICS) if s.exclude_images else set())
        self.wanted = [self.resolve_topic_name(t) for t in s.topics if t]
        self.wanted = [t for t in dict.fromkeys(self.wanted) if t not in excluded]
        # Camera topics of cameras the robot does not have (the UR5e's one fixed camera: no
        # /camera/right/...) would never be published: not waited for, not listed.
        cameras = load_robot(s.robot).camera_names
        self.wanted = [t for t in self.wanted if not (t.startswith('/camera/') and t.split('/')[2] not in cameras)]
        self._depth = s.queue_depth
        self._reliable_depth = s.reliable_queue_depth
        self._writer = McapBagWriter(self.output, compression=s.compression, chunk_size=s.chunk_size)
        self.counts = self._writer.counts
        self._subs_by_topic: dict[str, Any] = {}
        self._early: dict[str, tuple[Any, QoSProfile]] = {}
        self._closed = False
        self._warn = WarnOnce(self)
        self._sim_time = bool(self.get_parameter('use_sim_time').value)
        self._clock_ns = 0
        self._last_log_ns = -1
        self._writer.add_metadata('recording', {'log_time': 'sim' if self._sim_time else 'system',
                                                'tf': 'derived' if s.record_tf else 'none',
                                                'publish_time': PUBLISH_TIME_SOURCE})
        self._tf = TfBook(load_robot(s.robot)) if s.record_tf else None
        for topic in self.wanted:
            if topic in BY_NAME:
                self._subscribe_early(BY_NAME[topic])

        self._discovery = self.create_timer(s.discovery_period, self._discover)
        self._flusher = (self.create_timer(s.flush_period, self._writer.flush)
                         if s.flush_period > 0 else None)
        self.get_logger().info(f'recording {len(self.wanted)} topics to {self.output}')
        self._discover()

    @property
    def closed(self) -> bool:
        """True once the file is finished."""
        return self._closed

    def _subscribe_early(self, topic: ContractTopic) -> None:
        """Subscribe a contract topic before its publisher appears, with the contract's QoS.

        A node that publishes right after it starts (the selector's first command, a latched
        estimate updated before discovery) would otherwise lose its first messages to the
        discovery period. :meth:`_discover` re-subscribes if a publisher offers less.
        """
        try:
            cls = message_class(topic.type)
        except ImportError:
            return                              # discovery will report it
        qos = qos_profile(topic.qos, depth=self._depth if topic.sensor else self._reliable_depth)
        sub = self.create_subscription(cls, topic.name, functools.partial(self._on_message, topic.name), qos, raw=True)
        self._early[topic.name] = (sub, qos)

    def _add_channel(self, topic: str, type_name: str, endpoints: list[Any]) -> list[QoSProfile]:
        offers = [e.qos_profile for e in endpoints if e.topic_type == type_name]
        hashes = [str(e.topic_type_hash) for e in endpoints if e.topic_type == type_name]
        if not self._writer.has_channel(topic):
            self._writer.add_channel(topic, type_name, [qos_offer(o) for o in offers],
                                     next((h for h in hashes if h.startswith('RIHS')), ''))
        return offers

    def _confirm_early(self, topic: str, types: list[str], endpoints: list[Any]) -> None:
        """A publisher of an early-subscribed topic appeared: keep the subscription if it matches."""
        sub, qos = self._early[topic]
        offers = [e.qos_profile for e in endpoints if e.topic_type == BY_NAME[topic].type]
        need = request_qos(offers, self._depth)
        too_strict = (qos.reliability == ReliabilityPolicy.RELIABLE and need.reliability != qos.reliability) or \
            (qos.durability == DurabilityPolicy.TRANSIENT_LOCAL and need.durability != qos.durability)
        if not offers or too_strict:            # another type, or a publisher offering less
            del self._early[topic]
            self.destroy_subscription(sub)
            self._subscribe(topic, types, endpoints)
            return
        del self._early[topic]
        self._subs_by_topic[topic] = sub
        self._add_channel(topic, BY_NAME[topic].type, endpoints)
        self.get_logger().info(f'recording {topic} ({BY_NAME[topic].type}, '
                               f'{qos.reliability.name.lower()}, {qos.durability.name.lower()})')

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for topic in self.wanted:
            if topic in self._subs_by_topic or topic not in types:
                continue
            endpoints = self.get_publishers_info_by_topic(topic)
            if not endpoints:       # a subscriber alone makes a topic visible; wait for a publisher
                continue
            if topic in self._early:
                self._confirm_early(topic, types[topic], endpoints)
            else:
                self._subscribe(topic, types[topic], endpoints)
        if len(self._subs_by_topic) == len(self.wanted):
            self._discovery.cancel()   # nothing left to wait for

    def _subscribe(self, topic: str, types: list[str], endpoints: list[Any]) -> None:
        expected = BY_NAME[topic].type if topic in BY_NAME else None
        type_name = expected if expected in types else types[0]
        if expected is not None and expected not in types:
            self.get_logger().warning(f'{topic} is published as {types}, not {expected} as the '
                                      f'contract says; recording {type_name}')
        try:
            cls = message_class(type_name)
        except ImportError as exc:
            self.get_logger().error(f'cannot record {topic}: {exc}')
            self._subs_by_topic[topic] = None   # do not retry every period
            return
        offers = self._add_channel(topic, type_name, endpoints)
        qos = request_qos(offers, self._depth, self._reliable_depth)
        self._subs_by_topic[topic] = self.create_subscription(
            cls, topic, functools.partial(self._on_message, topic), qos, raw=True)
        self.get_logger().info(f'recording {topic} ({type_name}, '
                               f'{qos.reliability.name.lower()}, {qos.durability.name.lower()})')

    def _on_message(self, topic: str, data: bytes, info: dict[str, Any]) -> None:
        if self._closed:
            return
        if not self._writer.has_channel(topic):     # early subscription, before discovery saw the publisher
            self._add_channel(topic, BY_NAME[topic].type, self.get_publishers_info_by_topic(topic))
        if self._sim_time:
            # The latest /clock among the recorded messages: the node's own clock (its time
            # source's subscription) ran 40-320 ms behind or ahead of the recorded streams.
            if topic == '/clock':
                self._clock_ns = _stamp_ns(deserialize_message(data, ClockMsg).clock)
            now = self._clock_ns if '/clock' in self.wanted else self.get_clock().now().nanoseconds
            # One nanosecond apart within a clock tick: log-time order stays arrival order (the
            # player replays it; the offline evaluation replays publication order, see below).
            log_time = self._last_log_ns = max(now, self._last_log_ns + 1)
        else:
            # rmw's reception time when it has one (Fast DDS does), else now; both are system time.
            log_time = info.get('received_timestamp') or time.time_ns()
        # Publish time on the graph's wall clock always (metadata publish_time: source): the
        # source timestamp, else the receive time, the nearest bound a receiver has.
        publish_time = info.get('source_timestamp') or info.get('received_timestamp') or time.time_ns()
        self._writer.write(topic, data, log_time, publish_time,
                           info.get('publication_sequence_number') or 0)
        if topic in BY_NAME and BY_NAME[topic].qos is HISTORY:
            self._writer.flush()            # a run's record is on disk before the next message
        if self._tf is not None:
            for record in self._derive_tf(topic, data, log_time):
                if not self._writer.has_channel(record.topic):
                    self._writer.add_channel(record.topic, TF_TYPE, [_TF_QOS[record.topic]])
                self._writer.write(record.topic, record.data, record.log_time_ns)

    def _derive_tf(self, topic: str, data: bytes, log_time: int) -> list[TfRecord]:
        """Feed the TF book from a recorded message; the TF records it makes due."""
        try:
            if topic == '/joint_states':
                js = deserialize_message(data, JointState)
                return self._tf.on_joint_state(js.name, js.position, _stamp_ns(js.header.stamp), log_time)
            if topic == '/body_schema/true':
                self._tf.set_true(msg_to_table(deserialize_message(data, Float64MultiArray), self._tf.model.n_joints))
            elif topic == '/body_schema/estimate':
                self._tf.set_estimate(msg_to_table(deserialize_message(data, Float64MultiArray),
                                                   self._tf.model.n_joints))
            elif topic.startswith('/camera/') and topic.endswith('/pose'):
                self._tf.set_camera(topic.split('/')[2], pose_msg_to_matrix(deserialize_message(data, PoseStamped).pose))
        except (MessageFormatError, ValueError) as exc:
            self._warn(topic, f'no TF from {topic}: {exc}')
        return []

    def drain(self, spin_once: Callable[[float], None], quiet: float = DRAIN_QUIET_S,
              deadline: float = DRAIN_DEADLINE_S, cut: Callable[[], bool] = lambda: False) -> int:
        """Record what the subscriptions still hold; returns how many messages that wrote.

        Parameters
        ----------
        spin_once : callable
            ``spin_once(timeout)``: one turn of the executor this node is spun by.
        quiet : float
            Drained once nothing was written for ``quiet`` seconds.
        deadline : float
            At most this long [s].
        cut : callable
            Stops the drain when it returns true (a second signal).
        """
        start = last = time.monotonic()
        before = sum(self.counts.values())
        written = 0
        while self.context.ok() and not self._closed and not cut():
            spin_once(quiet)
            now, total = time.monotonic(), sum(self.counts.values()) - before
            if total > written:
                written, last = total, now
            elif now - last >= quiet:       # quiet since the last message (a timer's turn aside)
                break
            if now - start >= deadline:
                break
        return written

    def close(self) -> None:
        """Stop recording and finish the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for t in (self._discovery, self._flusher):
            if t is not None:
                self.destroy_timer(t)
        for sub in [*self._subs_by_topic.values(), *(s for s, _ in self._early.values())]:
            if sub is not None:
                self.destroy_subscription(sub)
        self._writer.close()
        total = sum(self.counts.values())
        per_topic = ', '.join(f'{t} {n}' for t, n in self.counts.items()) or 'no topic was published'
        # After SIGINT/SIGTERM the context is already shut down and /rosout cannot take the line.
        logger = self.get_logger() if self.context.ok() else get_logger(self.get_name())
        logger.info(f'closed {self.output}: {total} messages ({per_topic})')

    def destroy_node(self) -> None:
        """Finish the file, then destroy the node."""
        self.close()
        super().destroy_node()


def _run_then_drain(node: RecorderNode) -> None:
    """Spin until SIGINT or SIGTERM, then :meth:`RecorderNode.drain` (the context still up)."""
    signals: list[int] = []
    uninstall_signal_handlers()         # rclpy's would shut the context down with messages queued
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda s, _frame: signals.append(s))
    while rclpy.ok(context=node.context) and not signals:
        rclpy.spin_once(node, timeout_sec=0.1)
    t0 = time.monotonic()
    n = node.drain(lambda timeout: rclpy.spin_once(node, timeout_sec=timeout), cut=lambda: len(signals) > 1)
    node.get_logger().info(f'stopping: {n} queued messages recorded in {time.monotonic() - t0:.2f} s')


def main(args: list[str] | None = None) -> None:
    # SIGINT / SIGTERM end the spin, the queues are drained, destroy_node() finishes the file.
    spin_node(RecorderNode, args, _run_then_drain)


if __name__ == '__main__':
    main(sys.argv)
