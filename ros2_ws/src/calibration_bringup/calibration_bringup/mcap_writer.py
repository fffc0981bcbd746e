"""Write ROS 2 bags as single MCAP files, the way rosbag2's MCAP storage plugin does.

Pure module (never imports rclpy): the recorder node feeds it serialized messages and
publisher QoS as plain values, so the file format is testable without a ROS graph.

What makes a file a rosbag2 MCAP file (and so readable by ``ros2 bag play FILE.mcap``, the
``mcap`` and ``rosbags`` libraries and Foxglove):

* header profile ``ros2``;
* one schema per type, encoding ``ros2msg``, named ``pkg/msg/Type``, whose text is the type's
  ``.msg`` file followed by each dependency once, depth first, each introduced by a line of 80
  ``=`` and ``MSG: pkg/Type`` (:func:`schema_text`; ``ros2idl`` when only an ``.idl`` exists);
* one channel per topic, message encoding ``cdr``, metadata ``offered_qos_profiles`` (the
  publishers' QoS as YAML, :func:`offered_qos_yaml`) and ``topic_type_hash`` (``RIHS01_...``);
* chunked, compressed chunks, message indexes, and a summary with statistics at the end.

Files are written unbuffered chunk by chunk (:class:`McapBagWriter`), so a writer killed with
SIGKILL leaves a file whose complete chunks are all readable (see :mod:`calibration_interfaces.mcap_reader`).
"""
from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Self

from mcap.writer import CompressionType, Writer

from calibration_interfaces.mcap_reader import QosOffer

PROFILE = 'ros2'
MESSAGE_ENCODING = 'cdr'
SEPARATOR = '=' * 80
LIBRARY = 'calibration_bringup.mcap_writer'

# The field-type pattern and primitive list of rosbag2_storage_mcap's definition cache, so that
# dependency order and names match what rosbag2 writes (wstring added: it has no .msg either).
_MSG_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
_PRIMITIVES = frozenset({'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16',
                         'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'})
_TYPE_NAME = re.compile(r'^([a-zA-Z][a-zA-Z0-9_]*)/(?:(msg|srv|action)/)?([a-zA-Z][a-zA-Z0-9_]*)$')

_COMPRESSION = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4, 'none': CompressionType.NONE}
COMPRESSIONS: tuple[str, ...] = tuple(_COMPRESSION)


class DefinitionNotFoundError(LookupError):
    """No ``.msg`` or ``.idl`` file for a type in any package share directory."""


#: Interface packages whose standard definitions this package carries (share/calibration_bringup/
#: msg_definitions/<pkg>) for topics it records without their Python types installed:
#: tf2_msgs (/tf, /tf_static) has no wheel (docs/architecture.md, "TF and robot model").
CARRIED_DEFINITIONS = ('tf2_msgs',)


def _default_share(package: str) -> str:
    # ament_index_python is plain Python (no rclpy); imported lazily so tests can inject shares.
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        return get_package_share_directory(package)
    except PackageNotFoundError as exc:
        if package in CARRIED_DEFINITIONS:   # an installed package (a full ROS 2 install) comes first
            return str(Path(get_package_share_directory('calibration_bringup')) / 'msg_definitions' / package)
        raise DefinitionNotFoundError(f'package {package!r} is not in the ament index '
                                      f'(AMENT_PREFIX_PATH)') from exc


def split_type_name(type_name: str) -> tuple[str, str, str]:
    """Split ``pkg/msg/Type`` or ``pkg/Type`` into ``(pkg, 'msg', Type)``.

    Raises
    ------
    ValueError
        If ``type_name`` is not a ROS 2 interface name.
    """
    m = _TYPE_NAME.match(type_name)
    if m is None:
        raise ValueError(f'not a ROS 2 type name: {type_name!r} (expected pkg/msg/Type)')
    return m.group(1), m.group(2) or 'msg', m.group(3)


def _read_definition(type_name: str, ext: str, share: Callable[[str], str]) -> str:
    pkg, ns, name = split_type_name(type_name)
    path = Path(share(pkg)) / ns / f'{name}.{ext}'
    try:
        return path.read_text()
    except FileNotFoundError as exc:
        raise DefinitionNotFoundError(f'no {ext} definition for {type_name!r} at {path}') from exc


def msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a ``.msg`` text, sorted, as ``pkg/Type``.

    Types without a package are resolved in ``package`` (ROS 2 .msg files may refer to their own
    package's types by bare name).
    """
    deps = set()
    for m in _MSG_FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if '/' in t else f'{package}/{t}')
    return sorted(deps)


def _delimiter(kind: str, name: str) -> str:
    return f'{SEPARATOR}\n{kind}: {name}\n'


@functools.cache
def _schema_cached(type_name: str, share: Callable[[str], str]) -> tuple[str, str]:
    seen: set[str] = set()

    def expand(name: str, ext: str, depth: int) -> str:
        if depth <= 0:   # rosbag2's guard against recursive definitions
            raise DefinitionNotFoundError(f'definition of {type_name!r} nests deeper than 50 levels')
        text = _read_definition(name, ext, share)
        if ext == 'msg':
            deps = msg_dependencies(text, split_type_name(name)[0])
        else:
            deps = sorted(set(_IDL_INCLUDE.findall(text)))
        out = text
        for dep in deps:
            if dep not in seen:
                seen.add(dep)
                out += '\n' + _delimiter('MSG' if ext == 'msg' else 'IDL', dep) + expand(dep, ext, depth - 1)
        return out

    try:
        return 'ros2msg', expand(type_name, 'msg', 50)
    except DefinitionNotFoundError:
        # Like rosbag2: a type (or one of its dependencies) without .msg falls back to IDL.
        seen.clear()
        pkg, ns, name = split_type_name(type_name)
        root = f'{pkg}/{ns}/{name}'
        return 'ros2idl', _delimiter('IDL', root) + expand(root, 'idl', 50)


def schema_for(type_name: str, share: Callable[[str], str] | None = None) -> tuple[str, str]:
    """Schema encoding and text for a type, as rosbag2 writes them.

    Parameters
    ----------
    type_name : str
        ``pkg/msg/Type`` (or ``pkg/Type``).
    share : callable, optional
        Package name -> share directory; default: the ament index.

    Returns
    -------
    (encoding, text) : tuple of str
        ``('ros2msg', root .msg text + each dependency once, depth first)``, or ``'ros2idl'`` with
        the IDL texts when some definition exists only as ``.idl``.

    Raises
    ------
    DefinitionNotFoundError
        If neither ``.msg`` nor ``.idl`` definitions can be found.
    """
    return _schema_cached(type_name, share or _default_share)


def schema_text(type_name: str, share: Callable[[str], str] | None = None) -> str:
    """The ``ros2msg`` schema text of ``type_name`` (see :func:`schema_for`)."""
    return schema_for(type_name, share)[1]




def _duration_yaml(key: str, ns: int) -> str:
    sec, nsec = divmod(int(ns), 10**9)
    return f'  {key}:\n    sec: {sec}\n    nsec: {nsec}'


def offered_qos_yaml(offers: Sequence[QosOffer]) -> str:
    """Serialize publisher QoS like rosbag2 (yaml-cpp block style, metadata version 9).

    Returns an empty string for no offers, as rosbag2 does.
    """
    items = []
    for q in offers:
        items.append('\n'.join([
            f'- history: {q.history}',
            f'  depth: {int(q.depth)}',
            f'  reliability: {q.reliability}',
            f'  durability: {q.durability}',
            _duration_yaml('deadline', q.deadline_ns),
            _duration_yaml('lifespan', q.lifespan_ns),
            f'  liveliness: {q.liveliness}',
            _duration_yaml('liveliness_lease_duration', q.liveliness_lease_duration_ns),
            f'  avoid_ros_namespace_conventions: {"true" if q.avoid_ros_namespace_conventions else "false"}',
        ]))
    return '\n'.join(items)


class _UnbufferedFile:
    """Write-through file for :class:`mcap.writer.Writer`.

    The writer hands over whole records (a finished chunk, its message index) at once; writing
    them straight to the OS (not into a Python buffer) means that a SIGKILL loses only the chunk
    still being built. Not a ``RawIOBase`` so that the writer does not wrap it in a buffer.
    """

    def __init__(self, path: Path) -> None:
        self._f = open(path, 'wb', buffering=0)   # noqa: SIM115 - closed by close()

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = self._f.write(view)
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        pass   # nothing is buffered

    def close(self) -> None:
        self._f.close()


class McapBagWriter:
    """A rosbag2-compatible MCAP file: channels by topic, raw CDR messages, summary at close.

    Parameters
    ----------
    path : str or Path
        Output ``.mcap`` file; parent directories are created.
    compression : {'zstd', 'lz4', 'none'}
        Chunk compression.
    chunk_size : int
        Uncompressed bytes after which a chunk is closed and written (a SIGKILL loses at most the
        chunk being built; call :meth:`flush` to bound that loss in time too).
    share : callable, optional
        Package name -> share directory for message definitions (default: ament index).

    Raises
    ------
    ValueError
        On an unknown compression or a non-positive chunk size.
    """

    def __init__(self, path: str | os.PathLike[str], *, compression: str = 'zstd',
                 chunk_size: int = 1 << 20, share: Callable[[str], str] | None = None) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(f'compression {compression!r} is not one of {COMPRESSIONS}')
        if chunk_size <= 0:
            raise ValueError(f'chunk_size must be positive, got {chunk_size}')
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._share = share
        self._file = _UnbufferedFile(self.path)
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_COMPRESSION[compression])
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.types: dict[str, str] = {}
        #: Messages written per topic.
        self.counts: dict[str, int] = {}
        self._pending = 0      # messages in the chunk being built
        self._closed = False

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has finished the file."""
        return self._closed

    def has_channel(self, topic: str) -> bool:
        """Whether ``topic`` already has a channel."""
        return topic in self._channels

    def add_channel(self, topic: str, type_name: str, offered_qos: Iterable[QosOffer] = (),
                    type_hash: str = '') -> int:
        """Register a topic (once) and its type's schema (once per type).

        Parameters
        ----------
        topic : str
            Absolute topic name.
        type_name : str
            ``pkg/msg/Type``.
        offered_qos : iterable of QosOffer
            The publishers' QoS, stored as ``offered_qos_profiles`` (the player offers it again).
        type_hash : str
            ``RIHS01_<hex>`` type hash if known, stored as ``topic_type_hash``.

        Returns
        -------
        int
            The channel id.

        Raises
        ------
        ValueError
            If the topic already has a channel of another type, or the file is closed.
        DefinitionNotFoundError
            If the type's definition cannot be found.
        """
        self._check_open()
        type_name = '/'.join(split_type_name(type_name))
        if topic in self._channels:
            if self.types[topic] != type_name:
                raise ValueError(f'topic {topic!r} already recorded as {self.types[topic]}, '
                                 f'not {type_name}')
            return self._channels[topic]
        if type_name not in self._schemas:
            encoding, text = schema_for(type_name, self._share)
            self._schemas[type_name] = self._writer.register_schema(type_name, encoding, text.encode())
        metadata = {'offered_qos_profiles': offered_qos_yaml(list(offered_qos)),
                    'topic_type_hash': type_hash}
        cid = self._writer.register_channel(topic, MESSAGE_ENCODING, self._schemas[type_name], metadata)
        self._channels[topic] = cid
        self.types[topic] = type_name
        self.counts[topic] = 0
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write an MCAP metadata record ``name`` (string keys and values), e.g. how log times were taken.

        Raises
        ------
        ValueError
            If the file is closed.
        """
        self._check_open()
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None,
              sequence: int = 0) -> None:
        """Append one serialized (CDR) message to ``topic``'s channel.

        Raises
        ------
        KeyError
            If ``topic`` has no channel (call :meth:`add_channel` first).
        ValueError
            If the file is closed.
        """
        self._check_open()
        try:
            cid = self._channels[topic]
        except KeyError:
            raise KeyError(f'topic {topic!r} has no channel; add_channel() first') from None
        self._writer.add_message(channel_id=cid, log_time=int(log_time_ns), data=bytes(data),
                                 publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
                                 sequence=int(sequence) & 0xFFFFFFFF)
        self.counts[topic] += 1
        self._pending += 1

    def flush(self) -> None:
        """Close the chunk being built (if it has messages) and write it to disk."""
        if not self._closed and self._pending:
            self._writer.flush()
            self._pending = 0

    def close(self) -> None:
        """Finish the file (last chunk, summary, indexes, footer); idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f'{self.path} is closed')

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
