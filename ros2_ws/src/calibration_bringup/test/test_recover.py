"""Bags cut short by a crash: every prefix is read or refused in one line; ``recover`` makes them whole.

The bag is written with the project's writer (the recorder's), with two topics, QoS metadata
and the recorder's ``recording`` metadata, in small chunks; it is then cut at many offsets, as a
SIGKILL leaves it at some moment (the recorder's own SIGKILL test, in test_recorder_node.py,
recovers a really killed file).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader

from calibration_bringup.mcap_writer import McapBagWriter
from calibration_bringup.recover import main as recover_main
from calibration_interfaces import mcap_reader as bag
from calibration_interfaces.mcap_reader import BagError, QosOffer

TEXTS = [f'{i:04d} ' + 'x' * (50 + 37 * i % 300) for i in range(120)]
RECORDING = {'log_time': 'sim', 'tf': 'derived', 'publish_time': 'source'}


def _cdr_string(text: str) -> bytes:
    raw = text.encode() + b'\x00'
    return b'\x00\x01\x00\x00' + len(raw).to_bytes(4, 'little') + raw


def _write(path: Path) -> Path:
    with McapBagWriter(path, chunk_size=2048) as w:
        w.add_metadata('recording', RECORDING)
        w.add_channel('/chatter', 'std_msgs/msg/String', [QosOffer(durability='transient_local')])
        w.add_channel('/other', 'std_msgs/msg/String')
        for i, text in enumerate(TEXTS):
            w.write('/chatter' if i % 3 else '/other', _cdr_string(text), 10**9 + i * 10**7, sequence=i)
    return path


@pytest.fixture(scope='module')
def full(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    return _write(tmp_path_factory.mktemp('bag') / 'full.mcap').read_bytes()


def _texts(raw: list[bag.RawMessage]) -> list[str]:
    return [m.data[8:-1].decode() for m in raw]


def test_every_prefix_of_a_bag_is_read_up_to_its_last_complete_record(full: bytes, tmp_path: Path) -> None:
    # On main, some cuts made summary() raise EndOfFile and recording_metadata() an OSError or a
    # UnicodeDecodeError (the footer parser reading the torn tail), and a cut torn file read as
    # system-time: the tools that open a killed bag then failed with a traceback.
    path = tmp_path / 'cut.mcap'
    seen = set()
    for cut in range(0, len(full), 23):
        path.write_bytes(full[:cut])
        if cut < 8:
            with pytest.raises(BagError, match='cut.mcap (is empty|is not an MCAP file)'):
                bag.summary(path)
            continue
        s = bag.summary(path)
        got = _texts(list(bag.read_raw(path)))
        assert got == [t for i, t in enumerate(TEXTS) if i < len(got)], cut    # a prefix, nothing garbled
        assert not s.complete and s.message_count == len(got), cut
        assert s.loss.startswith(f'bag truncated (cut.mcap was not finished): recovered {len(got)} messages')
        if got:
            assert bag.recording_metadata(path) == RECORDING, cut
        seen.add(s.torn_record)
    assert {'CHUNK', 'MESSAGE_INDEX'} <= seen        # the cuts hit both kinds of record


def test_recover_rewrites_a_cut_bag_that_rosbags_and_mcaps_reader_open(full: bytes, tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(full[:len(full) * 3 // 5 + 11])
    with cut.open('rb') as f:             # mcap's default reader cannot read the cut file
        with pytest.raises(McapError):
            list(make_reader(f).iter_messages())
    out = tmp_path / 'whole.mcap'
    source = bag.recover(cut, out)
    n = source.message_count
    assert 20 < n < len(TEXTS) and not source.complete

    s = bag.summary(out)
    assert s.complete and s.message_count == n and not s.loss
    assert bag.recording_metadata(out) == RECORDING
    assert s.topics['/chatter'].offered_qos[0].durability == 'transient_local'
    with out.open('rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == n and summary.chunk_indexes and summary.metadata_indexes
        assert [m.sequence for _, _, m in reader.iter_messages(log_time_order=False)] == list(range(n))
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        assert {c.topic for c in r.connections} == {'/chatter', '/other'}
        got = [r.deserialize(raw, c.msgtype).data for c, _, raw in r.messages()]
    assert got == TEXTS[:n]

    complete = tmp_path / 'complete.mcap'
    complete.write_bytes(full)
    assert bag.recover(complete, tmp_path / 'again.mcap').complete       # a finished bag copies whole
    assert bag.summary(tmp_path / 'again.mcap').message_count == len(TEXTS)
    with pytest.raises(ValueError, match='another file'):
        bag.recover(complete, complete)


def test_the_recover_command(full: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / 'run.mcap'
    cut.write_bytes(full[:len(full) // 2])
    assert recover_main([str(cut)]) == 0
    out = capsys.readouterr().out
    n = bag.summary(cut).message_count
    assert out.startswith(f'bag truncated (run.mcap was not finished): recovered {n} messages')
    assert bag.summary(tmp_path / 'run.recovered.mcap').message_count == n
    assert recover_main([str(cut)]) == 1                                   # never overwrites unasked
    assert 'exists (use --force' in capsys.readouterr().err
    assert recover_main([str(cut), '--force', '-o', str(tmp_path / 'run.recovered.mcap')]) == 0
    empty = tmp_path / 'empty.mcap'
    empty.write_bytes(b'')
    assert recover_main([str(empty)]) == 1
    assert capsys.readouterr().err == f'recover: {empty} is empty\n'
    # The module entry, as `python -m` (and `ros2 run calibration_bringup recover` through the console script).
    proc = subprocess.run([sys.executable, '-m', 'calibration_bringup.recover', str(cut), '-o', str(tmp_path / 'm.mcap')],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and f'recovered {n} messages' in proc.stdout, proc.stderr
