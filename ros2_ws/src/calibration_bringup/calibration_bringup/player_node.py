"""Bag player node: republishes a recorded MCAP bag on its topics, like ``ros2 bag play``.

Messages are published as the recorded CDR bytes, at their recorded log-time spacing divided by
``rate``, in the order they were published when the bag says its publish times are the
publishers' (``publish_time: source``; a recorder behind on the joint states logged the hand
poses that follow them seconds earlier, and a replaying estimator then drops them): a message
logged earlier than the one published before it is played at that one's time (other bags: in
log order). They go out with the QoS their publishers offered when recorded (latched topics:
reliable, transient local, so late subscribers still get the facts). With ``publish_clock`` the player
also publishes ``/clock`` from the log times (``ros2 bag play --clock``); a recorded ``/clock`` is
then not replayed, so that there is one time source. To replay a simulation in its own sim time,
set ``publish_clock:=false``: the recorded ``/clock`` is then played like any topic.

The node finishes (``done``; ``main`` returns) when the bag ends, unless ``loop``.
A bag cut short by a crash is played up to its last complete record, with a warning that says
what was lost; an empty, missing or non-MCAP file ends ``main`` with one line and exit status 1.

Publications
------------
Every recorded topic (or ``topics``), its recorded type and QoS.
/clock : rosgraph_msgs/Clock
    With ``publish_clock``: the playback time at ``clock_rate`` Hz.

Services
--------
~/resume : std_srvs/Trigger
    Starts a player created with ``start_paused``.

Parameters
----------
bag : str
    The ``.mcap`` file.
rate : float
    Speed factor (1 = recorded speed; 0 = as fast as possible).
topics : string array
    Topics to play (empty: all).
publish_clock : bool
    Publish /clock from the message log times.
clock_rate : float
    /clock frequency [Hz] (at rate 0, /clock goes with every message instead).
loop : bool
    Start again at the end.
start_offset : float
    Skip the first seconds of the bag [s].
delay : float
    Wall time to wait before playing, e.g. for subscribers to connect [s].
start_paused : bool
    Wait for ~/resume (or ``resume()``) before playing.
"""
from __future__ import annotations

# First: a SIGINT during the slow imports below is not lost (see calibration_interfaces.startup).
from calibration_interfaces import startup  # noqa: F401,I001

import sys
import time
from collections.abc import Iterator
from typing import Any

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from std_srvs.srv import Trigger

from calibration_interfaces import mcap_reader
from calibration_interfaces.contract import BY_NAME, PUBLISH_TIME_SOURCE
from calibration_interfaces.mcap_reader import QosOffer
from calibration_interfaces.node_util import declare_settings, message_class, spin_node

from .node_settings import PlayerSettings

CLOCK_TOPIC = '/clock'
_MIN_WAIT_NS = 100_000          # 0.1 ms: shorter waits are not worth a timer round trip
_MAX_WAIT_NS = 100_000_000      # 0.1 s: wake up at least this often (pause, shutdown)
_BATCH_NS = 20_000_000          # rate 0: publish for at most 20 ms per callback


def playback_qos(offers: tuple[QosOffer, ...], topic: str) -> QoSProfile:
    """The QoS to offer for a recorded topic (rosbag2's rule, plus the contract as fallback).

    The recorded publishers' reliability and durability when they all agree; otherwise (or with
    nothing recorded) reliable volatile, or the contract's policy for contract topics. DDS
    discovery does not carry history depth: latched topics keep the last message (what their
    publishers keep), streams keep 10 (rosbag2's default).
    """
    pairs = {(o.reliability, o.durability) for o in offers}
    if len(pairs) == 1:
        rel, dur = pairs.pop()
    elif topic in BY_NAME:
        rel, dur = BY_NAME[topic].qos.reliability.value, BY_NAME[topic].qos.durability.value
    else:
        rel, dur = 'reliable', 'volatile'
    latched = dur == 'transient_local'
    depth = max((o.depth for o in offers), default=0) or (1 if latched else 10)
    return QoSProfile(
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if rel == 'best_effort' else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _monotone(messages: Iterator[mcap_reader.RawMessage]) -> Iterator[mcap_reader.RawMessage]:
    """The messages with log times made non-decreasing (each at least the one before it)."""
    last = None
    for m in messages:
        if last is not None and m.log_time_ns < last:
            m = m._replace(log_time_ns=last)
        last = m.log_time_ns
        yield m


class BagPlayerNode(Node):
    """Plays one MCAP bag (see the module docstring).

    Attributes
    ----------
    summary : calibration_interfaces.mcap_reader.BagSummary
        What the bag holds.
    published : dict of str to int
        Messages published per topic (over all loops).
    finished : rclpy.task.Future
        Done when the bag has been played to its end (never with ``loop``).
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('bag_player', **kwargs)
        s = self.settings = declare_settings(self, PlayerSettings)
        path = s.bag
        if not path:
            raise mcap_reader.BagError("parameter 'bag' is empty: give the .mcap file to play")
        self.summary = mcap_reader.summary(path)
        if not self.summary.complete:
            self.get_logger().warning(f'{self.summary.loss}; playing them in file order')
        self._rate = s.rate
        self._loop = s.loop
        self._publish_clock = s.publish_clock
        wanted = [t for t in s.topics if t]
        missing = [t for t in wanted if t not in self.summary.topics]
        if missing:
            self.get_logger().warning(f'not in the bag, not played: {missing}')

        self.publishers_by_topic: dict[str, Any] = {}
        for name, info in self.summary.topics.items():
            if wanted and name not in wanted:
                continue
            if name == CLOCK_TOPIC and self._publish_clock:
                self.get_logger().info('the recorded /clock is not played: publish_clock makes the clock')
                continue
            try:
                cls = message_class(info.type)
            except ImportError as exc:
                self.get_logger().error(f'cannot play {name}: {exc}')
                continue
            self.publishers_by_topic[name] = self.create_publisher(cls, name, playback_qos(info.offered_qos, name))
        self.published = {t: 0 for t in self.publishers_by_topic}
        self._clock_pub = self.create_publisher(ClockMsg, CLOCK_TOPIC, 10) if self._publish_clock else None

        self._offset_ns = int(s.start_offset * 1e9)
        self._t0_bag = self.summary.start_ns + self._offset_ns   # bag time played at _t0_wall
        self._t0_wall = 0
        self._messages: Iterator[mcap_reader.RawMessage] | None = None
        self._next: mcap_reader.RawMessage | None = None
        self._last_log_ns = self._t0_bag
        self._last_clock_ns = self._t0_bag
        self._clock_period_ns = int(1e9 / s.clock_rate)
        self._playing = False
        self.finished = Future()

        # Steady timers: the player keeps wall time even if the node is told to use sim time.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(0.001, self._tick, clock=steady, autostart=False)
        self._clock_timer = (self.create_timer(1.0 / s.clock_rate, self._tick_clock, clock=steady,
                                               autostart=False)
                             if self._clock_pub is not None and self._rate > 0 else None)
        self.create_service(Trigger, '~/resume', self._on_resume)
        self._paused = s.start_paused
        self._delay_timer = None
        if not self._paused:
            self._start_after(s.delay)
        self.get_logger().info(
            f'{path}: {len(self.publishers_by_topic)} topics, {self.summary.message_count} messages, '
            f'{self.summary.duration_s:.1f} s, rate {self._rate:g}' + (', paused' if self._paused else ''))

    @property
    def done(self) -> bool:
        """True once the whole bag has been played (never with ``loop``)."""
        return self.finished.done()

    def resume(self) -> bool:
        """Start a paused player (after ``delay``); False if it was not paused."""
        if not self._paused:
            return False
        self._paused = False
        self._start_after(self.settings.delay)
        return True

    def _on_resume(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        res.success = self.resume()
        res.message = 'playing' if res.success else 'not paused'
        return res

    def _start_after(self, delay: float) -> None:
        if delay <= 0:
            self._start()
            return

        def fire() -> None:
            self.destroy_timer(self._delay_timer)
            self._start()
        self._delay_timer = self.create_timer(delay, fire, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _start(self) -> None:
        order = ('publication' if mcap_reader.recording_metadata(self.summary.path)['publish_time']
                 == PUBLISH_TIME_SOURCE else 'log')
        self._messages = _monotone(mcap_reader.read_raw(self.summary.path, list(self.publishers_by_topic),
                                                        self._t0_bag if self._offset_ns else None, order))
        self._next = next(self._messages, None)
        self._t0_wall = time.monotonic_ns()
        self._playing = True
        self._publish_clock_at(self._t0_bag)
        if self._clock_timer is not None:
            self._clock_timer.reset()
        self._wake_in(0)

    def _due_ns(self, msg: mcap_reader.RawMessage) -> int:
        return self._t0_wall + int((msg.log_time_ns - self._t0_bag) / self._rate)

    def _wake_in(self, ns: int) -> None:
        # One timer, re-armed for the next message: no busy polling between sparse messages.
        self._timer.timer_period_ns = min(max(ns, _MIN_WAIT_NS), _MAX_WAIT_NS)
        self._timer.reset()

    def _tick(self) -> None:
        if not self._playing:
            return
        now = time.monotonic_ns()
        if self._rate == 0:
            while self._next is not None and time.monotonic_ns() - now < _BATCH_NS:
                if self._next.log_time_ns - self._last_clock_ns >= self._clock_period_ns:
                    self._publish_clock_at(self._next.log_time_ns)   # time first, then its data
                self._publish(self._next)
            wait = 0
        else:
            while self._next is not None and self._due_ns(self._next) <= now:
                self._publish(self._next)
            wait = self._due_ns(self._next) - time.monotonic_ns() if self._next is not None else 0
        if self._next is None:
            self._end_of_bag()
        if self._playing:
            self._wake_in(wait)

    def _publish(self, msg: mcap_reader.RawMessage) -> None:
        self.publishers_by_topic[msg.topic].publish(msg.data)
        self.published[msg.topic] += 1
        self._last_log_ns = msg.log_time_ns
        self._next = next(self._messages, None)

    def _end_of_bag(self) -> None:
        if self._loop:
            self.get_logger().info('end of bag: looping')
            self._start()
            return
        self._playing = False
        self._timer.cancel()
        if self._clock_timer is not None:
            self._clock_timer.cancel()
        self._publish_clock_at(self._last_log_ns)
        self.get_logger().info(f'end of bag: {sum(self.published.values())} messages published')
        if not self.finished.done():
            self.finished.set_result(True)

    def _tick_clock(self) -> None:
        if self._playing:
            now_bag = self._t0_bag + int((time.monotonic_ns() - self._t0_wall) * self._rate)
            # Never ahead of a message still to be published (a late tick under load): time seen
            # by the replaying nodes then never passes data they have not received yet.
            if self._next is not None:
                now_bag = min(now_bag, self._next.log_time_ns)
            self._publish_clock_at(now_bag)

    def _publish_clock_at(self, t_ns: int) -> None:
        self._last_clock_ns = t_ns
        if self._clock_pub is not None:
            msg = ClockMsg()
            msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 10**9)
            self._clock_pub.publish(msg)

    def wait_for_acks(self, timeout_s: float = 2.0) -> bool:
        """Wait until reliable subscribers have acknowledged everything published."""
        ok = True
        for pub in self.publishers_by_topic.values():
            if pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                ok = pub.wait_for_all_acked(Duration(seconds=timeout_s)) and ok
        return ok


def _play(node: BagPlayerNode) -> None:
    rclpy.spin_until_future_complete(node, node.finished)
    node.wait_for_acks()   # do not exit with reliable messages still in flight


def main(args: list[str] | None = None) -> None:
    try:
        spin_node(BagPlayerNode, args, _play)
    except (FileNotFoundError, mcap_reader.BagError) as exc:   # a bag it cannot open: one line, no traceback
        print(f'bag_player: {exc}', file=sys.stderr)
        sys.exit(1)


if __name__ == '__main__':
    main(sys.argv)
