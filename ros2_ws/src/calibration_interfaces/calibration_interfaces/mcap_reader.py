"""Read the recorder's MCAP bags: topics, counts, QoS and messages (pure module, no rclpy).

``read_messages`` decodes with ``mcap_ros2`` (dynamic classes built from the schemas stored in
the file, so no ROS install is needed); ``read_raw`` gives the CDR bytes (what the player
republishes); ``summary`` lists topics, types, counts and the time span.

A file whose writer was killed (SIGKILL, power loss) has no summary and may end in a torn
chunk: it is then read front to back and every message of the complete chunks is returned, in
file order (complete files are read in log-time order). ``summary(path).complete`` tells which.

Example
-------
>>> from calibration_interfaces import mcap_reader as bag
>>> s = bag.summary('run.mcap'); s.topics['/joint_states'].count
>>> for topic, t_ns, msg in bag.read_messages('run.mcap', ['/hand_pose']): ...

The bag player, the report and the offline evaluation all read bags through this module;
``calibration_bringup.mcap_writer`` writes them (the publishers' QoS as :class:`QosOffer`).
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
import yaml
from mcap_ros2.decoder import DecoderFactory

#: rmw's RMW_DURATION_INFINITE (2^63 - 1 ns), written as {sec: 9223372036, nsec: 854775807}.
INFINITE_NS = 2**63 - 1


@dataclass(frozen=True)
class QosOffer:
    """One publisher's QoS as rosbag2 stores it (policy names as in rmw's ``*_to_str``).

    Durations are in nanoseconds; :data:`INFINITE_NS` means infinite. ``history`` is usually
    ``'unknown'`` and ``depth`` 0: DDS discovery does not carry them.
    """

    history: str = 'unknown'
    depth: int = 0
    reliability: str = 'reliable'
    durability: str = 'volatile'
    deadline_ns: int = INFINITE_NS
    lifespan_ns: int = INFINITE_NS
    liveliness: str = 'automatic'
    liveliness_lease_duration_ns: int = INFINITE_NS
    avoid_ros_namespace_conventions: bool = False


_POLICY_NAMES = {  # rmw enum values -> names (rosbag2 metadata <= 8 wrote the numbers)
    'history': ('system_default', 'keep_last', 'keep_all', 'unknown'),
    'reliability': ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available'),
    'durability': ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available'),
    'liveliness': ('system_default', 'automatic', 'manual_by_node', 'manual_by_topic', 'unknown',
                   'best_available'),
}
# Infinity as Foxy-era rmw implementations reported it (rosbag2 maps these to infinite too).
_FOXY_INFINITE = {(0x7FFFFFFF, 0xFFFFFFFF), (0x7FFFFFFF, 0x7FFFFFFF), divmod(INFINITE_NS, 10**9)}


def _policy(kind: str, value: Any) -> str:
    names = _POLICY_NAMES[kind]
    if isinstance(value, int) and not isinstance(value, bool):
        return names[value] if 0 <= value < len(names) else 'unknown'
    value = str(value).lower()
    return value if value in names else 'unknown'


def _duration_ns(d: Any) -> int:
    if not isinstance(d, dict):
        return INFINITE_NS
    sec, nsec = int(d.get('sec', 0)), int(d.get('nsec', 0))
    if (sec, nsec) in _FOXY_INFINITE:
        return INFINITE_NS
    return sec * 10**9 + nsec


def parse_offered_qos(text: str) -> list[QosOffer]:
    """Parse ``offered_qos_profiles`` (names as metadata version 9, or numbers as before).

    Raises
    ------
    ValueError
        If ``text`` is not a YAML list of QoS mappings.
    """
    if not text.strip():
        return []
    try:
        items = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f'offered_qos_profiles is not YAML: {exc}') from exc
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise ValueError(f'offered_qos_profiles is not a list of mappings: {text[:200]!r}')
    return [QosOffer(
        history=_policy('history', i.get('history', 'unknown')),
        depth=int(i.get('depth', 0)),
        reliability=_policy('reliability', i.get('reliability', 'unknown')),
        durability=_policy('durability', i.get('durability', 'unknown')),
        deadline_ns=_duration_ns(i.get('deadline')),
        lifespan_ns=_duration_ns(i.get('lifespan')),
        liveliness=_policy('liveliness', i.get('liveliness', 'unknown')),
        liveliness_lease_duration_ns=_duration_ns(i.get('liveliness_lease_duration')),
        avoid_ros_namespace_conventions=bool(i.get('avoid_ros_namespace_conventions', False)),
    ) for i in items]


class RawMessage(NamedTuple):
    """One recorded message, undecoded."""

    topic: str
    type: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass(frozen=True)
class TopicSummary:
    """One recorded topic (one channel)."""

    name: str
    type: str
    count: int
    offered_qos: tuple[QosOffer, ...] = ()
    type_hash: str = ''


@dataclass(frozen=True)
class BagSummary:
    """What a bag holds.

    Attributes
    ----------
    complete : bool
        The file was finished (summary and footer present). False after a crash: the figures
        then come from a scan of the complete records.
    damage : str
        Why the scan of an incomplete file stopped (empty when complete).
    """

    path: Path
    profile: str
    library: str
    topics: dict[str, TopicSummary] = field(default_factory=dict)
    message_count: int = 0
    start_ns: int = 0
    end_ns: int = 0
    complete: bool = True
    damage: str = ''

    @property
    def duration_s(self) -> float:
        """Time between the first and the last message's log time [s]."""
        return (self.end_ns - self.start_ns) * 1e-9 if self.message_count else 0.0


def _topic_summary(ch: Channel, schema: Schema | None, count: int) -> TopicSummary:
    try:
        qos = tuple(parse_offered_qos(ch.metadata.get('offered_qos_profiles', '')))
    except ValueError:
        qos = ()   # unreadable QoS is not worth refusing a bag over; the player uses defaults
    return TopicSummary(ch.topic, schema.name if schema else '', count, qos,
                        ch.metadata.get('topic_type_hash', ''))


def _read_end(f: Any) -> tuple[bool, Any | None]:
    """``(finished, summary)``: whether the file has its footer, and its summary if it has one."""
    try:
        f.seek(0)
        return True, SeekingReader(f).get_summary()
    except (McapError, OSError, ValueError):
        # Too short for a footer (OSError on seek) or a torn end: the writer never finished.
        return False, None


class _Scan:
    """Front-to-back reading of a file that may end in a torn record."""

    def __init__(self, f: Any) -> None:
        self.f = f
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.damage = ''

    def messages(self) -> Iterator[tuple[Channel, Message]]:
        self.f.seek(0)
        records = StreamReader(self.f, skip_magic=False).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except Exception as exc:   # noqa: BLE001
                # A torn tail shows up as whatever the cut hits: EndOfFile, struct.error, a
                # decompressor error... Everything before it was complete: stop there.
                self.damage = f'{type(exc).__name__}: {exc}' if str(exc) else type(exc).__name__
                return
            if isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in self.channels:
                yield self.channels[record.channel_id], record


def summary(path: str | os.PathLike[str]) -> BagSummary:
    """Topics, types, counts and time span of a bag (a killed recording is scanned).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    mcap.exceptions.InvalidMagic
        If ``path`` is not an MCAP file.
    """
    path = Path(path)
    with open(path, 'rb') as f:
        reader = SeekingReader(f)   # checks the magic
        header = reader.get_header()
        finished, s = _read_end(f)
        if s is not None and s.statistics is not None:
            counts = s.statistics.channel_message_counts
            topics = {ch.topic: _topic_summary(ch, s.schemas.get(ch.schema_id), counts.get(cid, 0))
                      for cid, ch in sorted(s.channels.items())}
            st = s.statistics
            return BagSummary(path, header.profile, header.library, topics, st.message_count,
                              st.message_start_time, st.message_end_time)
        scan = _Scan(f)
        counts: dict[int, int] = {}
        n, t0, t1 = 0, 0, 0
        for ch, msg in scan.messages():
            counts[ch.id] = counts.get(ch.id, 0) + 1
            t0 = msg.log_time if n == 0 else min(t0, msg.log_time)
            t1 = max(t1, msg.log_time)
            n += 1
        topics = {ch.topic: _topic_summary(ch, scan.schemas.get(ch.schema_id), counts.get(cid, 0))
                  for cid, ch in sorted(scan.channels.items())}
        return BagSummary(path, header.profile, header.library, topics, n, t0, t1,
                          complete=finished, damage=scan.damage)


def recording_metadata(path: str | os.PathLike[str]) -> dict[str, str]:
    """The recorder's ``recording`` metadata: ``log_time`` (``sim`` or ``system``) and ``tf``.

    A bag written before the recorder wrote it (or by another tool) says nothing: its log times
    are system time, as rosbag2's without ``--use-sim-time``; that default is returned.
    """
    out = {'log_time': 'system', 'tf': 'none'}
    with open(path, 'rb') as f:
        try:
            for record in SeekingReader(f).iter_metadata():
                if record.name == 'recording':
                    out.update(record.metadata)
        except McapError:
            pass   # a killed recording has no metadata index: say what an old bag says
    return out


def _iter(path: Path, topics: Iterable[str] | None,
          start_ns: int | None) -> Iterator[tuple[Schema | None, Channel, Message]]:
    wanted = None if topics is None else set(topics)
    with open(path, 'rb') as f:
        if _read_end(f)[0]:
            f.seek(0)
            yield from SeekingReader(f).iter_messages(
                topics=None if wanted is None else sorted(wanted), log_time_order=True,
                starting_at=start_ns)
            return
        scan = _Scan(f)
        for ch, msg in scan.messages():
            if (wanted is None or ch.topic in wanted) and (start_ns is None or msg.log_time >= start_ns):
                yield scan.schemas.get(ch.schema_id), ch, msg


def read_raw(path: str | os.PathLike[str], topics: Iterable[str] | None = None,
             start_ns: int | None = None) -> Iterator[RawMessage]:
    """Recorded messages as CDR bytes, in log-time order (file order for a killed recording).

    Parameters
    ----------
    path : path
        The ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).
    start_ns : int, optional
        Only messages logged at or after this time [ns].
    """
    for schema, ch, msg in _iter(Path(path), topics, start_ns):
        yield RawMessage(ch.topic, schema.name if schema else '', msg.log_time, msg.publish_time,
                         msg.data)


def read_messages(path: str | os.PathLike[str],
                  topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """Decoded messages as ``(topic, log_time_ns, msg)``.

    ``msg`` is an ``mcap_ros2`` dynamic object with the message's fields as attributes (e.g.
    ``msg.header.stamp.sec``, ``msg.position``), built from the schema stored in the file.

    Raises
    ------
    mcap_ros2.decoder.McapROS2DecodeError
        If a schema cannot be parsed.
    """
    factory = DecoderFactory()
    decoders: dict[int, Any] = {}
    for schema, ch, msg in _iter(Path(path), topics, None):
        dec = decoders.get(ch.id)
        if dec is None:
            dec = decoders[ch.id] = factory.decoder_for(ch.message_encoding, schema)
            if dec is None:
                raise ValueError(f'topic {ch.topic!r}: no ROS 2 decoder for encoding '
                                 f'{ch.message_encoding!r} / schema '
                                 f'{schema.encoding if schema else None!r}')
        yield ch.topic, msg.log_time, dec(msg.data)
