"""The encoding study: lossless encodings detect exactly what rgb8 detects, the lossy ones are
measured (not assumed), and the section has a row per encoding with its time at 1280x1024."""
from __future__ import annotations

import pytest

from tools.encoding_bench import CORNER_TARGET_PX, VARIANTS, run


def _table(text: str, header_start: str) -> dict[str, list[str]]:
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = {}
    for line in lines[i + 2:]:
        if not line.startswith('|'):
            break
        cells = [c.strip() for c in line.strip().strip('|').split('|')]
        rows[cells[0]] = cells[1:]
    return rows


@pytest.fixture(scope='module')
def section() -> str:
    return run(n=12, seed=0, timing_frames=1, repeats=1)


def test_every_encoding_has_a_row_and_a_time(section: str) -> None:
    names = [v.name for v in VARIANTS]
    accuracy = _table(section, '| encoding | same markers')
    timing = _table(section, '| encoding | conversion')
    assert list(accuracy) == names and list(timing) == names
    assert all(float(t[0].split(' / ')[0]) > 0 for t in timing.values())


def test_lossless_encodings_detect_what_rgb8_detects(section: str) -> None:
    rows = _table(section, '| encoding | same markers')
    for v in VARIANTS:
        same, corners, mm = rows[v.name][0], rows[v.name][1], rows[v.name][2]
        if v.lossless:
            assert same == '12/12' and corners == '0.000 / 0.000 / 0.000' and mm == '0.000 / 0.000', (v.name, rows[v.name])
        elif v.encoding in ('uyvy', 'yuyv'):                   # chroma subsampled, luma kept
            assert float(corners.split(' / ')[2]) <= CORNER_TARGET_PX, (v.name, corners)
    # The lossy ones differ measurably: the comparison is not blind.
    assert float(rows['bayer_rggb8'][1].split(' / ')[0]) > 0.0
    assert 'MISSES' not in section
