"""The rosbag2 MCAP format without ROS: schema texts, QoS metadata, writer, reader, torn files."""
from __future__ import annotations

from pathlib import Path

import pytest
from ament_index_python.packages import get_package_share_directory
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from calibration_bringup.mcap_writer import (SEPARATOR, DefinitionNotFoundError, McapBagWriter, offered_qos_yaml,
                                             schema_for, schema_text)
from calibration_interfaces import mcap_reader as bag
from calibration_interfaces.mcap_reader import INFINITE_NS, QosOffer, parse_offered_qos

# CDR of std_msgs/String 'hi' and of an empty-named JointState would need rclpy to serialize;
# these literal messages keep the module pure (little-endian CDR header + fields).
STRING_HI = b'\x00\x01\x00\x00\x03\x00\x00\x00hi\x00'


def _cdr_string(text: str) -> bytes:
    raw = text.encode() + b'\x00'
    return b'\x00\x01\x00\x00' + len(raw).to_bytes(4, 'little') + raw


def _msg(pkg: str, name: str) -> str:
    return (Path(get_package_share_directory(pkg)) / 'msg' / f'{name}.msg').read_text()


def test_joint_state_schema_is_root_then_each_dependency_depth_first() -> None:
    expected = (_msg('sensor_msgs', 'JointState')
                + f'\n{SEPARATOR}\nMSG: std_msgs/Header\n' + _msg('std_msgs', 'Header')
                + f'\n{SEPARATOR}\nMSG: builtin_interfaces/Time\n' + _msg('builtin_interfaces', 'Time'))
    assert schema_for('sensor_msgs/msg/JointState') == ('ros2msg', expected)
    assert schema_text('sensor_msgs/JointState') == expected   # the short form names the same type
    assert len(SEPARATOR) == 80 and set(SEPARATOR) == {'='}


def test_nested_dependencies_appear_once_in_depth_first_order() -> None:
    text = schema_text('geometry_msgs/msg/PoseWithCovarianceStamped')
    names = [line[5:] for line in text.splitlines() if line.startswith('MSG: ')]
    # Sorted per level as rosbag2's std::set; bare 'Pose' inside geometry_msgs resolves there.
    assert names == ['geometry_msgs/PoseWithCovariance', 'geometry_msgs/Pose', 'geometry_msgs/Point',
                     'geometry_msgs/Quaternion', 'std_msgs/Header', 'builtin_interfaces/Time']


def test_fake_share_bare_names_idl_fallback_and_errors(tmp_path: Path) -> None:
    share = {'pkg': tmp_path / 'pkg'}
    (share['pkg'] / 'msg').mkdir(parents=True)
    outer = '# comment with Other word\nInner a\npkg/Inner[] b\nint32 X=1\n'
    (share['pkg'] / 'msg' / 'Outer.msg').write_text(outer)
    (share['pkg'] / 'msg' / 'Inner.msg').write_text('float64 v\n')
    (share['pkg'] / 'msg' / 'OnlyIdl.idl').write_text('#include "pkg/msg/Inner.idl"\nmodule pkg {};\n')
    (share['pkg'] / 'msg' / 'Inner.idl').write_text('module pkg { struct Inner { double v; }; };\n')

    def lookup(p: str) -> str:
        if p not in share:
            raise DefinitionNotFoundError(p)
        return str(share[p])

    # 'Inner' and 'pkg/Inner' are one dependency, written once; comments and constants are none.
    assert schema_for('pkg/msg/Outer', lookup) == ('ros2msg', outer + f'\n{SEPARATOR}\nMSG: pkg/Inner\nfloat64 v\n')
    encoding, text = schema_for('pkg/msg/OnlyIdl', lookup)
    assert encoding == 'ros2idl'
    assert text.startswith(f'{SEPARATOR}\nIDL: pkg/msg/OnlyIdl\n#include')
    assert f'\n{SEPARATOR}\nIDL: pkg/msg/Inner\nmodule pkg' in text
    with pytest.raises(DefinitionNotFoundError, match='Missing'):
        schema_for('pkg/msg/Missing', lookup)
    with pytest.raises(ValueError, match="'no_slash'"):
        schema_for('no_slash', lookup)


def test_offered_qos_yaml_is_rosbag2s_and_parses_back_old_and_new() -> None:
    offers = [QosOffer(), QosOffer(history='keep_last', depth=1, reliability='best_effort',
                                   durability='transient_local', deadline_ns=1_500_000_000)]
    text = offered_qos_yaml(offers)
    assert text.splitlines()[:6] == ['- history: unknown', '  depth: 0', '  reliability: reliable',
                                     '  durability: volatile', '  deadline:', '    sec: 9223372036']
    assert '    nsec: 854775807' in text and text.endswith('avoid_ros_namespace_conventions: false')
    assert parse_offered_qos(text) == offers
    assert offered_qos_yaml([]) == '' and parse_offered_qos('') == []
    # rosbag2 metadata <= 8 wrote enum numbers, and Foxy wrote its own infinity.
    old = ('- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n'
           '  deadline: {sec: 2147483647, nsec: 4294967295}\n  lifespan: {sec: 0, nsec: 7}\n'
           '  liveliness: 1\n  liveliness_lease_duration: {sec: 1, nsec: 0}\n'
           '  avoid_ros_namespace_conventions: false\n')
    assert parse_offered_qos(old) == [QosOffer('keep_last', 5, 'best_effort', 'transient_local',
                                               INFINITE_NS, 7, 'automatic', 10**9, False)]
    with pytest.raises(ValueError, match='not a list'):
        parse_offered_qos('history: keep_last')


@pytest.mark.parametrize('compression', ['zstd', 'lz4', 'none'])
def test_round_trip_through_mcap_and_rosbags(tmp_path: Path, compression: str) -> None:
    path = tmp_path / 'deep' / 'dir' / 'b.mcap'   # parents are created
    with McapBagWriter(path, compression=compression, chunk_size=4096) as w:
        w.add_channel('/chatter', 'std_msgs/msg/String', [QosOffer(durability='transient_local')],
                      'RIHS01_' + '0' * 64)
        w.add_channel('/chatter', 'std_msgs/String')   # same topic, same type: the same channel
        for i in range(200):
            w.write('/chatter', _cdr_string(f'msg {i}'), log_time_ns=10**9 + i * 1000, sequence=i)
        assert w.counts == {'/chatter': 200}
    w.close()   # idempotent

    with open(path, 'rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        s = reader.get_summary()
        assert s.statistics.message_count == 200 and s.statistics.chunk_count > 1
        assert {c.compression for c in s.chunk_indexes} == {'' if compression == 'none' else compression}
        (schema,) = s.schemas.values()
        (channel,) = s.channels.values()
        assert (schema.name, schema.encoding) == ('std_msgs/msg/String', 'ros2msg')
        assert channel.message_encoding == 'cdr'
        assert parse_offered_qos(channel.metadata['offered_qos_profiles'])[0].durability == 'transient_local'
        assert channel.metadata['topic_type_hash'] == 'RIHS01_' + '0' * 64
        decoded = [m.data for _, _, _, m in reader.iter_decoded_messages()]
    assert decoded == [f'msg {i}' for i in range(200)]

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # rosbags reads a bare .mcap (no metadata.yaml) through rosbag2.Reader, which AnyReader uses.
    # The dummy hash would fail rosbags' RIHS01 check, so this copy has none.
    plain = tmp_path / 'plain.mcap'
    with McapBagWriter(plain, compression=compression) as w:
        w.add_channel('/chatter', 'std_msgs/msg/String')
        w.write('/chatter', STRING_HI, 5)
    with AnyReader([plain], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        (conn,) = r.connections
        assert (conn.topic, conn.msgtype, conn.msgcount) == ('/chatter', 'std_msgs/msg/String', 1)
        assert [r.deserialize(raw, c.msgtype).data for c, _, raw in r.messages()] == ['hi']


def test_writer_rejects_bad_use(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="'gzip'"):
        McapBagWriter(tmp_path / 'a.mcap', compression='gzip')
    with pytest.raises(ValueError, match='-1'):
        McapBagWriter(tmp_path / 'a.mcap', chunk_size=-1)
    w = McapBagWriter(tmp_path / 'b.mcap')
    w.add_channel('/a', 'std_msgs/msg/String')
    with pytest.raises(ValueError, match='std_msgs/msg/Int32'):
        w.add_channel('/a', 'std_msgs/msg/Int32')
    with pytest.raises(KeyError, match="'/b'"):
        w.write('/b', STRING_HI, 0)
    with pytest.raises(DefinitionNotFoundError, match='no_such_pkg'):
        w.add_channel('/c', 'no_such_pkg/msg/Thing')
    w.close()
    with pytest.raises(ValueError, match='closed'):
        w.write('/a', STRING_HI, 0)


def test_torn_file_reads_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / 'torn.mcap'
    w = McapBagWriter(path, chunk_size=4096)
    w.add_channel('/chatter', 'std_msgs/msg/String')
    for i in range(100):
        w.write('/chatter', _cdr_string(f'{i:04d}' + 'x' * 300), 1000 + i)
    on_disk = path.read_bytes()   # as a SIGKILL would leave it: complete chunks, no summary
    w.close()
    whole = bag.summary(path)
    assert whole.complete and whole.message_count == 100 and whole.topics['/chatter'].count == 100

    torn = tmp_path / 'cut.mcap'
    torn.write_bytes(on_disk[:-100])   # and cut into the last chunk
    s = bag.summary(torn)
    assert not s.complete and s.damage
    got = [m.data for _, _, m in bag.read_messages(torn)]
    assert 50 < len(got) < 100
    assert got == [f'{i:04d}' + 'x' * 300 for i in range(len(got))]   # a prefix, nothing garbled
    assert s.message_count == len(got) and s.topics['/chatter'].type == 'std_msgs/msg/String'


def test_recording_metadata_says_which_clock_and_old_bags_read_as_system_time(tmp_path: Path) -> None:
    new, old = tmp_path / 'new.mcap', tmp_path / 'old.mcap'
    with McapBagWriter(new) as w:
        w.add_metadata('recording', {'log_time': 'sim', 'tf': 'derived'})
    with McapBagWriter(old):
        pass
    # Publish times of unknown origin: the offline evaluation replays such a bag in log order.
    assert bag.recording_metadata(new) == {'log_time': 'sim', 'tf': 'derived', 'publish_time': 'unknown'}
    assert bag.recording_metadata(old) == {'log_time': 'system', 'tf': 'none', 'publish_time': 'unknown'}
    w = McapBagWriter(tmp_path / 'closed.mcap')
    w.close()
    with pytest.raises(ValueError, match='closed'):
        w.add_metadata('recording', {'log_time': 'sim'})
