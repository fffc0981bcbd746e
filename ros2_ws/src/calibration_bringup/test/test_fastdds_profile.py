"""The shipped Fast DDS shared-memory profile is valid and installed where the launcher looks for it."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from ament_index_python.packages import get_package_share_directory

PROFILE = Path(__file__).resolve().parents[1] / 'config' / 'fastdds_shm.xml'
NS = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
FRAME_BYTES = 640 * 480 * 3


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


def test_the_installed_profile_is_the_shipped_one() -> None:
    # run_calibration.sh and the launch file read the installed copy (share/<pkg>/config), not the
    # sources; an uninstalled package raises PackageNotFoundError here.
    installed = Path(get_package_share_directory('calibration_bringup')) / 'config' / PROFILE.name
    assert installed.is_file(), f'{installed} missing: run make setup'
    assert installed.parent != PROFILE.parent, 'the source file, not an installed copy'
    assert installed.read_bytes() == PROFILE.read_bytes()
