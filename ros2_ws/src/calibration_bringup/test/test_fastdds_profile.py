"""The shipped Fast DDS shared-memory profile is valid and carries camera frames between processes."""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

from calibration_bringup import transport_bench

PROFILE = Path(__file__).resolve().parents[1] / 'config' / 'fastdds_shm.xml'
NS = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
FRAME_BYTES = 640 * 480 * 3
# Domains 101..149: clear of the in-process fixture (1..100) and of the benchmark (150..).
DOMAIN_ID = 101 + os.getpid() % 49


def test_profile_is_well_formed_and_complete() -> None:
    root = ET.parse(PROFILE).getroot()
    assert root.tag == f'{{{NS["f"]}}}dds'
    descriptors = {d.findtext('f:transport_id', namespaces=NS): d
                   for d in root.iterfind('f:profiles/f:transport_descriptors/f:transport_descriptor',
                                          NS)}
    kinds = {tid: d.findtext('f:type', namespaces=NS) for tid, d in descriptors.items()}
    assert sorted(kinds.values()) == ['SHM', 'UDPv4']
    (shm,) = [d for d in descriptors.values() if d.findtext('f:type', namespaces=NS) == 'SHM']
    # Several whole frames must fit in one writer's segment (the default 512 KiB holds none).
    assert int(shm.findtext('f:segment_size', namespaces=NS)) >= 4 * FRAME_BYTES

    participants = root.findall('f:profiles/f:participant', NS)
    assert len(participants) == 1
    (participant,) = participants
    assert participant.get('is_default_profile') == 'true'
    rtps = participant.find('f:rtps', NS)
    used = [t.text for t in rtps.iterfind('f:userTransports/f:transport_id', NS)]
    assert set(used) == set(descriptors), 'every declared transport is used, none is undefined'
    assert kinds[used[0]] == 'SHM', 'shared memory is listed first'
    assert rtps.findtext('f:useBuiltinTransports', namespaces=NS) == 'false'


def test_profile_env_sets_and_clears_both_variables() -> None:
    env = transport_bench.profile_env(PROFILE, base={'FASTRTPS_DEFAULT_PROFILES_FILE': '/x'})
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(PROFILE)
    assert env['FASTDDS_DEFAULT_PROFILES_FILE'] == str(PROFILE)
    cleared = transport_bench.profile_env(None, base=env)
    assert not set(transport_bench.PROFILE_ENV_VARS) & set(cleared)


def test_profile_path_finds_the_shipped_file() -> None:
    assert transport_bench.profile_path().read_bytes() == PROFILE.read_bytes()


def test_640x480_frames_cross_processes_through_the_8mib_segment() -> None:
    result = transport_bench.run_pair(PROFILE, 'shm', 'reliable', domain_id=DOMAIN_ID, rate=10.0,
                                      duration=1.0, timeout=40.0)
    assert result['sent'] == 10
    assert result['received'] == 10, result['records']
    assert result['content_ok'], 'a frame arrived truncated or with the wrong bytes'
    assert {r[3] for r in result['records']} == {FRAME_BYTES}
    # The profile really applied: the subscriber mapped its own 8 MiB segment and the
    # publisher's (which it reads frames from), not only Fast DDS's 512 KiB default.
    big = [size for size in result['sub_shm'].values() if size >= 8 * 2**20]
    assert len(big) >= 2, result['sub_shm']
