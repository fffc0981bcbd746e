"""Read the recorder's MCAP bags: topics, counts, QoS and messages (pure module, no rclpy).

``read_messages`` decodes with ``mcap_ros2`` (dynamic classes built from the schemas stored in
the file, so no ROS install is needed); ``read_raw`` gives the CDR bytes (what the player
republishes); ``summary`` lists topics, types, counts and the time span.

A file whose writer was killed (SIGKILL, power loss) has no summary and may end in a torn
chunk: it is then read front to back and every message of the complete chunks is returned, in
file order (complete files are read in log-time order). ``summary(path).complete`` tells which
and ``summary(path).loss`` says, in one line, how much was recovered and what was lost; every
tool that reads bags (the bag player, the report, the offline evaluation) goes through here and
reports it. :func:`recover` rewrites such a file into a complete one that other readers open
(rosbags, mcap's default reader, ``ros2 bag``). An empty or non-MCAP file raises
:class:`BagError` (one line naming the file), never a parser's exception.

Example
-------
>>> from calibration_interfaces import mcap_reader as bag
>>> s = bag.summary('run.mcap'); s.topics['/joint_states'].count
>>> for topic, t_ns, msg in bag.read_messages('run.mcap', ['/hand_pose']): ...

The bag player, the report and the offline evaluation all read bags through this module;
``calibration_bringup.mcap_writer`` writes them (the publishers' QoS as :class:`QosOffer`).
"""
from __future__ import annotations

import heapq
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
import yaml
from mcap_ros2.decoder import DecoderFactory

__all__ = ['INFINITE_NS', 'MAGIC', 'BagError', 'QosOffer', 'parse_offered_qos', 'RawMessage', 'TopicSummary',
           'BagSummary', 'summary', 'recording_metadata', 'read_raw', 'ORDERS', 'read_messages', 'COMPRESSIONS',
           'recover']

#: rmw's RMW_DURATION_INFINITE (2^63 - 1 ns), written as {sec: 9223372036, nsec: 854775807}.
INFINITE_NS = 2**63 - 1

#: The 8 bytes every MCAP file starts and (when finished) ends with.
MAGIC = b'\x89MCAP0\r\n'


class BagError(ValueError):
    """A file that is not a readable MCAP bag (empty, another format); the message names it."""


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
    lost_bytes : int
        Bytes after the last complete record (0 when complete).
    torn_record : str
        The kind of that cut record (``CHUNK``: its messages are lost; ``MESSAGE_INDEX``: none).
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
    lost_bytes: int = 0
    torn_record: str = ''

    @property
    def duration_s(self) -> float:
        """Time between the first and the last message's log time [s]."""
        return (self.end_ns - self.start_ns) * 1e-9 if self.message_count else 0.0

    @property
    def loss(self) -> str:
        """One line on what an unfinished file lost (empty when complete)."""
        if self.complete:
            return ''
        end = f'up to t={self.end_ns * 1e-9:.3f} s' if self.message_count else 'none'
        if not self.lost_bytes:
            lost = 'no record cut, only the summary missing'
        elif self.torn_record == 'CHUNK':
            lost = f'the last chunk ({self.lost_bytes} bytes, cut by the crash) lost'
        else:
            lost = f'the last {self.lost_bytes} bytes ({self.torn_record or "a record"} cut by the crash) unreadable'
        return (f'bag truncated ({self.path.name} was not finished): recovered {self.message_count} messages '
                f'{end}; {lost}' + (f' [{self.damage}]' if self.damage and self.lost_bytes else ''))


def _topic_summary(ch: Channel, schema: Schema | None, count: int) -> TopicSummary:
    try:
        qos = tuple(parse_offered_qos(ch.metadata.get('offered_qos_profiles', '')))
    except ValueError:
        qos = ()   # unreadable QoS is not worth refusing a bag over; the player uses defaults
    return TopicSummary(ch.topic, schema.name if schema else '', count, qos,
                        ch.metadata.get('topic_type_hash', ''))


def _open(path: str | os.PathLike[str]) -> Any:
    """The file opened for reading; FileNotFoundError if missing, :class:`BagError` unless it starts as MCAP."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'no bag at {path}')
    f = open(path, 'rb')   # noqa: SIM115 - the caller closes it
    start = f.read(len(MAGIC))
    if start != MAGIC:
        f.close()
        what = 'is empty' if not start else f'is not an MCAP file (it starts with {start!r})'
        raise BagError(f'{path} {what}')
    f.seek(0)
    return f


def _read_end(f: Any) -> tuple[bool, Any | None]:
    """``(finished, summary)``: whether the file has its footer, and its summary if it has one."""
    try:
        f.seek(-len(MAGIC), os.SEEK_END)
        if f.read() != MAGIC:
            return False, None      # the writer never wrote its closing magic
        f.seek(0)
        return True, SeekingReader(f).get_summary()
    except Exception:   # noqa: BLE001
        # A torn end that happens to end in the magic is read as whatever the bytes say: a
        # struct.error, RecordLengthLimitExceeded... The writer never finished.
        return False, None


class _Scan:
    """Front-to-back reading of a file that may end in a torn record."""

    def __init__(self, f: Any) -> None:
        self.f = f
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.header: Header | None = None
        self.metadata: list[Metadata] = []
        self.damage = ''
        self.lost_bytes = 0
        self.torn_record = ''

    def records(self) -> Iterator[Any]:
        """Every complete record in file order (chunks opened), remembering schemas and channels."""
        self.f.seek(0, os.SEEK_END)
        size = self.f.tell()
        self.f.seek(0)
        records = StreamReader(self.f, skip_magic=False).records
        good_end = 0
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except Exception as exc:   # noqa: BLE001
                # A torn tail shows up as whatever the cut hits: EndOfFile, struct.error, a
                # decompressor error... Everything before it was complete: stop there.
                self.damage = f'{type(exc).__name__}: {exc}' if str(exc) else type(exc).__name__
                self.lost_bytes = size - good_end
                self.f.seek(good_end)
                opcode = self.f.read(1)
                if opcode:
                    self.torn_record = Opcode(opcode[0]).name if opcode[0] in Opcode._value2member_map_ \
                        else f'opcode {opcode[0]:#x}'
                return
            good_end = self.f.tell()     # a chunk is read whole before its records come out
            if isinstance(record, Header):
                self.header = record
            elif isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Metadata):
                self.metadata.append(record)
            yield record

    def messages(self) -> Iterator[tuple[Channel, Message]]:
        for record in self.records():
            if isinstance(record, Message) and record.channel_id in self.channels:
                yield self.channels[record.channel_id], record


def summary(path: str | os.PathLike[str]) -> BagSummary:
    """Topics, types, counts and time span of a bag (a killed recording is scanned).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    BagError
        If ``path`` is empty or not an MCAP file.
    """
    path = Path(path)
    with _open(path) as f:
        finished, s = _read_end(f)
        if s is not None and s.statistics is not None:
            f.seek(0)
            header = SeekingReader(f).get_header()
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
        header = scan.header or Header(profile='', library='')
        return BagSummary(path, header.profile, header.library, topics, n, t0, t1,
                          complete=finished, damage=scan.damage, lost_bytes=scan.lost_bytes,
                          torn_record=scan.torn_record)


def recording_metadata(path: str | os.PathLike[str]) -> dict[str, str]:
    """The recorder's ``recording`` metadata: ``log_time`` (``sim`` or ``system``), ``tf`` and
    ``publish_time`` (``source``: the publishers' source timestamps,
    :data:`calibration_interfaces.contract.PUBLISH_TIME_SOURCE`; else ``unknown``).

    A bag written before the recorder wrote it (or by another tool) says nothing: its log times
    are system time, as rosbag2's without ``--use-sim-time``, and its publish times unknown;
    those defaults are returned.
    """
    out = {'log_time': 'system', 'tf': 'none', 'publish_time': 'unknown'}
    with _open(path) as f:
        if _read_end(f)[0]:
            f.seek(0)
            records: Iterable[Metadata] = SeekingReader(f).iter_metadata()
        else:      # a killed recording has no metadata index: its records are in the data section
            scan = _Scan(f)
            for _ in scan.records():
                pass
            records = scan.metadata
        for record in records:
            if record.name == 'recording':
                out.update(record.metadata)
    return out


def _iter(path: Path, topics: Iterable[str] | None,
          start_ns: int | None) -> Iterator[tuple[Schema | None, Channel, Message]]:
    wanted = None if topics is None else set(topics)
    with _open(path) as f:
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


#: Orders the readers read in: ``log`` (the recorder's arrival order; file order for a killed
#: recording) or ``publication`` (by publish time; each topic in log order, merged).
ORDERS: tuple[str, ...] = ('log', 'publication')


def _iter_in(path: Path, topics: Iterable[str] | None, start_ns: int | None,
             order: str) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """:func:`_iter` in ``order``: by publication, one reader per topic, merged on publish time
    (memory: one message per topic, images included)."""
    if order not in ORDERS:
        raise ValueError(f'order must be one of {list(ORDERS)}, got {order!r}')
    if order == 'log':
        return _iter(path, topics, start_ns)
    names = sorted(summary(path).topics) if topics is None else sorted(set(topics))
    return heapq.merge(*(_iter(path, [t], start_ns) for t in names), key=lambda r: r[2].publish_time)


def read_raw(path: str | os.PathLike[str], topics: Iterable[str] | None = None,
             start_ns: int | None = None, order: str = 'log') -> Iterator[RawMessage]:
    """Recorded messages as CDR bytes, in log-time order (file order for a killed recording).

    Parameters
    ----------
    path : path
        The ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).
    start_ns : int, optional
        Only messages logged at or after this time [ns].
    order : {'log', 'publication'}
        ``log``: as the recorder logged them (its arrival order). ``publication``: by publish
        time, the order the publishers sent them in when the bag's publish times are their
        source timestamps (:func:`recording_metadata` says ``publish_time: source``); a recorder
        that fell behind on one topic logged the others ahead of it. Messages of one topic keep
        their order either way.

    Raises
    ------
    ValueError
        If ``order`` is not one of :data:`ORDERS`.
    """
    for schema, ch, msg in _iter_in(Path(path), topics, start_ns, order):
        yield RawMessage(ch.topic, schema.name if schema else '', msg.log_time, msg.publish_time,
                         msg.data)


def read_messages(path: str | os.PathLike[str], topics: Iterable[str] | None = None,
                  order: str = 'log') -> Iterator[tuple[str, int, Any]]:
    """Decoded messages as ``(topic, log_time_ns, msg)``.

    ``msg`` is an ``mcap_ros2`` dynamic object with the message's fields as attributes (e.g.
    ``msg.header.stamp.sec``, ``msg.position``), built from the schema stored in the file.

    Parameters
    ----------
    path, topics, order
        As :func:`read_raw`.

    Raises
    ------
    ValueError
        If ``order`` is not one of :data:`ORDERS`.
    mcap_ros2.decoder.McapROS2DecodeError
        If a schema cannot be parsed.
    """
    factory = DecoderFactory()
    decoders: dict[int, Any] = {}
    for schema, ch, msg in _iter_in(Path(path), topics, None, order):
        dec = decoders.get(ch.id)
        if dec is None:
            dec = decoders[ch.id] = factory.decoder_for(ch.message_encoding, schema)
            if dec is None:
                raise ValueError(f'topic {ch.topic!r}: no ROS 2 decoder for encoding '
                                 f'{ch.message_encoding!r} / schema '
                                 f'{schema.encoding if schema else None!r}')
        yield ch.topic, msg.log_time, dec(msg.data)


#: Chunk compressions :func:`recover` can write.
COMPRESSIONS = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4, 'none': CompressionType.NONE}


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str], *, compression: str = 'zstd',
            chunk_size: int = 1 << 20) -> BagSummary:
    """Rewrite a bag (typically an unfinished one) as a complete MCAP file, like ``mcap recover``.

    Every complete record of ``src`` is copied in file order through :class:`mcap.writer.Writer`:
    the header, schemas, channels (with their metadata: QoS, type hash), messages (log and
    publish times, sequence), metadata records (e.g. ``recording``) and attachments; the writer
    adds what the killed writer never wrote: message and chunk indexes, statistics, the summary
    and the footer. Readers that need the summary (rosbags, mcap's ``make_reader``) then open it.

    Parameters
    ----------
    src, dst : path
        The bag to read and the file to write (must differ).
    compression : {'zstd', 'lz4', 'none'}
        Chunk compression of ``dst``.
    chunk_size : int
        Uncompressed bytes per chunk of ``dst``.

    Returns
    -------
    BagSummary
        What ``src`` held (its :attr:`BagSummary.loss` says what the crash lost).

    Raises
    ------
    FileNotFoundError, BagError
        As :func:`summary`, for ``src``.
    ValueError
        If ``dst`` is ``src``, or on an unknown compression or a non-positive chunk size.
    """
    src, dst = Path(src), Path(dst)
    if compression not in COMPRESSIONS:
        raise ValueError(f'compression {compression!r} is not one of {tuple(COMPRESSIONS)}')
    if chunk_size <= 0:
        raise ValueError(f'chunk_size must be positive, got {chunk_size}')
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise ValueError(f'recover {src}: the output must be another file')
    source = summary(src)
    part = dst.with_name(dst.name + '.part')     # renamed when finished: no half-written output
    with _open(src) as f, open(part, 'wb') as out:
        writer = Writer(out, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        started = False
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for record in _Scan(f).records():
            if isinstance(record, Header):
                writer.start(record.profile, record.library)
                started = True
            elif isinstance(record, Schema) and record.id not in schema_ids:   # the summary repeats them
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), record.metadata)
            elif isinstance(record, Message) and record.channel_id in channel_ids:
                writer.add_message(channel_ids[record.channel_id], record.log_time, record.data,
                                   record.publish_time, record.sequence)
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                      record.data)
        if not started:       # the header itself was torn: an MCAP file of nothing
            writer.start(source.profile, source.library)
        writer.finish()
    os.replace(part, dst)
    return source
