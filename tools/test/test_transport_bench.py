"""The transport benchmark: profile selection, and camera frames crossing processes through the
shipped Fast DDS shared-memory profile."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from tools import transport_bench

PROFILE = Path(__file__).resolve().parents[2] / 'ros2_ws' / 'src' / 'calibration_bringup' / 'config' / 'fastdds_shm.xml'
FRAME_BYTES = 640 * 480 * 3
# Domains 101..149: clear of the in-process fixture (1..100) and of the benchmark (150..).
DOMAIN_ID = 101 + os.getpid() % 49


def test_profile_env_sets_and_clears_both_variables() -> None:
    env = transport_bench.profile_env(PROFILE, base={'FASTRTPS_DEFAULT_PROFILES_FILE': '/x'})
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(PROFILE)
    assert env['FASTDDS_DEFAULT_PROFILES_FILE'] == str(PROFILE)
    cleared = transport_bench.profile_env(None, base=env)
    assert not set(transport_bench.PROFILE_ENV_VARS) & set(cleared)


def test_profile_path_prefers_the_installed_copy() -> None:
    from ament_index_python.packages import get_package_share_directory

    installed = Path(get_package_share_directory('calibration_bringup')) / 'config' / PROFILE.name
    assert transport_bench.profile_path() == installed
    assert installed.read_bytes() == PROFILE.read_bytes()


def test_profile_path_falls_back_to_the_sources(monkeypatch) -> None:
    monkeypatch.setenv('AMENT_PREFIX_PATH', '/nonexistent')
    assert transport_bench.profile_path() == PROFILE


# One rerun: the subscriber process once timed out at 70 s on a fresh clone (one run in five);
# not understood yet (docs/tests.md).
@pytest.mark.flaky(reruns=1)
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
