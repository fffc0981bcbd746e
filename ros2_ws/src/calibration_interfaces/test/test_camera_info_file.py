"""camera_info_manager YAML files: the file camera_calibration writes reads back, URLs resolve as
camera_info_manager resolves them, every malformed field is named, and the differences from a
topic's camera_info are named field by field."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration_interfaces.camera_info_file import (CameraInfoFile, CameraInfoFileError, camera_info_differences,
                                                     read_camera_info, resolve_url, write_camera_info)

#: As camera_calibration's cameracalibrator saves it (ost.yaml), numbers from a 640x480 webcam.
OST = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [ 812.51017,    0.     ,  317.20581,
            0.     ,  814.71386,  244.19733,
            0.     ,    0.     ,    1.     ]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [ 0.081231, -0.250301, 0.001547, -0.000836, 0.000000]
rectification_matrix:
  rows: 3
  cols: 3
  data: [ 1.,  0.,  0.,
          0.,  1.,  0.,
          0.,  0.,  1.]
projection_matrix:
  rows: 3
  cols: 4
  data: [ 815.33527,    0.     ,  316.29339,    0.     ,
            0.     ,  819.80896,  244.74539,    0.     ,
            0.     ,    0.     ,    1.     ,    0.     ]
"""


@pytest.fixture
def ost(tmp_path: Path) -> Path:
    path = tmp_path / 'ost.yaml'
    path.write_text(OST)
    return path


def test_reads_what_camera_calibration_writes(ost: Path) -> None:
    info = read_camera_info(str(ost))
    assert (info.width, info.height, info.camera_name, info.distortion_model) == (640, 480, 'narrow_stereo',
                                                                                 'plumb_bob')
    np.testing.assert_allclose(info.k, [[812.51017, 0, 317.20581], [0, 814.71386, 244.19733], [0, 0, 1]])
    np.testing.assert_allclose(info.d, [0.081231, -0.250301, 0.001547, -0.000836, 0.0])
    assert info.p.shape == (3, 4) and info.p[0, 0] == pytest.approx(815.33527)
    np.testing.assert_array_equal(info.r, np.eye(3))
    assert info.source == str(ost)


def test_url_forms(ost: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    assert resolve_url(f'file://{ost}') == ost
    assert resolve_url(str(ost)) == ost
    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    assert resolve_url('file://${ROS_HOME}/ost.yaml') == ost
    assert read_camera_info('file://${ROS_HOME}/ost.yaml').width == 640
    share = resolve_url('package://calibration_interfaces/package.xml')
    assert share.name == 'package.xml' and share.is_file()
    for bad, words in (('', 'empty'), ('http://host/ost.yaml', 'file://'), ('file://${NAME}.yaml', 'ROS_HOME'),
                       ('package://no_such_package_here/ost.yaml', 'no_such_package_here')):
        with pytest.raises(CameraInfoFileError, match=words):
            resolve_url(bad)


def test_minimal_file_gets_camera_info_managers_defaults(tmp_path: Path) -> None:
    path = tmp_path / 'min.yaml'
    path.write_text('image_width: 320\nimage_height: 240\ncamera_matrix: {rows: 3, cols: 3, '
                    'data: [257.34, 0, 160, 0, 257.34, 120, 0, 0, 1]}\n')
    info = read_camera_info(str(path))
    assert info.d.size == 0 and info.distortion_model == 'plumb_bob' and info.camera_name == ''
    np.testing.assert_array_equal(info.p, np.hstack([info.k, np.zeros((3, 1))]))


@pytest.mark.parametrize('edit, words', [
    (lambda t: t.replace('image_width: 640\n', ''), 'image_width'),
    (lambda t: t.replace('image_height: 480', 'image_height: -4'), 'image_height'),
    (lambda t: t.replace('cols: 5', 'cols: 4'), 'distortion_coefficients says 1 x 4 but has 5'),
    (lambda t: t.replace('812.51017', '-812.51017'), 'focal'),
    (lambda t: t.replace('812.51017', '.nan'), 'NaN'),
    (lambda t: t.replace('  rows: 3\n  cols: 4', '  rows: 4\n  cols: 3'), 'projection_matrix must be 3 x 4'),
    (lambda t: t.replace('0.081231', 'abc'), 'distortion_coefficients is not numeric'),
    (lambda t: '[1, 2', 'not YAML'),
    (lambda t: '- a list', 'mapping'),
])
def test_malformed_files_name_the_field(ost: Path, edit, words: str) -> None:
    ost.write_text(edit(OST))
    with pytest.raises(CameraInfoFileError, match=words) as err:
        read_camera_info(str(ost))
    assert str(ost) in str(err.value)


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(CameraInfoFileError, match='nothing.yaml'):
        read_camera_info(f'file://{tmp_path}/nothing.yaml')


def test_write_then_read_round_trip(tmp_path: Path) -> None:
    k = np.array([[257.34, 0, 159.5], [0, 257.34, 119.5], [0, 0, 1]])
    info = CameraInfoFile(320, 240, k, np.array([0.1, -0.2, 0, 0, 0.05]), 'plumb_bob', camera_name='left')
    back = read_camera_info(str(write_camera_info(tmp_path / 'sub' / 'left.yaml', info)))
    assert (back.width, back.height, back.camera_name) == (320, 240, 'left')
    np.testing.assert_array_equal(back.k, k)
    np.testing.assert_array_equal(back.d, info.d)
    np.testing.assert_array_equal(back.p, info.p)


def test_differences_name_each_field(ost: Path) -> None:
    info = read_camera_info(str(ost))
    k = info.k.reshape(-1).tolist()
    assert camera_info_differences(info, 640, 480, k, info.d.tolist(), 'plumb_bob') == []
    # Five zeros and no coefficients are the same camera; so is an empty model on the topic.
    clean = CameraInfoFile(640, 480, info.k)
    assert camera_info_differences(clean, 640, 480, k, [0.0] * 5, '') == []
    other = list(k)
    other[0], other[5] = 820.0, 250.0
    diff = camera_info_differences(info, 320, 240, other, [0.0] * 5, 'equidistant')
    assert len(diff) == 4, diff
    assert diff[0].startswith('size: 640 x 480 in the file vs 320 x 240')
    assert 'fx 812.51 in the file vs 820' in diff[1] and 'cy 244.197 in the file vs 250' in diff[1]
    assert diff[2].startswith('D: ') and "'plumb_bob' in the file vs 'equidistant'" in diff[3]
    assert camera_info_differences(info, 640, 480, [], info.d, 'plumb_bob') == ['K: 0 values on the topic']
