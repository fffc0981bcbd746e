"""Image conversion: round trips, padded rows, and a clear error for every bad field."""
from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest

from calibration_interfaces.image_conversion import (ImageConversionError, array_to_image_fields,
                                              image_to_array, image_to_gray)


def _msg(**fields):
    return SimpleNamespace(**fields)


@pytest.fixture
def rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'mono8'])
def test_round_trip(encoding: str, rgb: np.ndarray) -> None:
    arr = rgb if encoding != 'mono8' else rgb[..., 0]
    fields = array_to_image_fields(arr, encoding)
    assert isinstance(fields['data'], bytes) and fields['step'] == arr.shape[1] * (1 if arr.ndim == 2 else 3)
    out = image_to_array(_msg(**fields))
    np.testing.assert_array_equal(out, arr)


def test_channel_order_and_gray(rgb: np.ndarray) -> None:
    msg = _msg(**array_to_image_fields(rgb, 'rgb8'))
    np.testing.assert_array_equal(image_to_array(msg, 'bgr8'), rgb[..., ::-1])
    bgr = _msg(**array_to_image_fields(np.ascontiguousarray(rgb[..., ::-1]), 'bgr8'))
    np.testing.assert_array_equal(image_to_gray(msg), image_to_gray(bgr))
    # Pure red is darker than pure green in luma; a swapped channel order would invert this.
    red = np.zeros((2, 2, 3), np.uint8)
    red[..., 0] = 255
    green = np.roll(red, 1, axis=2)
    assert image_to_gray(_msg(**array_to_image_fields(red, 'rgb8'))).max() < \
        image_to_gray(_msg(**array_to_image_fields(green, 'rgb8'))).max()


def test_padded_rows_and_other_buffers(rgb: np.ndarray) -> None:
    h, w, _ = rgb.shape
    step = w * 3 + 5
    padded = np.zeros((h, step), np.uint8)
    padded[:, :w * 3] = rgb.reshape(h, -1)
    for data in (padded.tobytes(), array.array('B', padded.tobytes()), list(padded.tobytes()),
                 padded.reshape(-1)):
        out = image_to_array(_msg(height=h, width=w, encoding='rgb8', step=step, data=data))
        np.testing.assert_array_equal(out, rgb)
        assert out.flags['C_CONTIGUOUS']
    # The result never aliases the message's buffer (a later message reuse must not change it).
    buf = padded.reshape(-1).copy()
    out = image_to_array(_msg(height=h, width=w, encoding='rgb8', step=step, data=buf))
    buf[:] = 0
    np.testing.assert_array_equal(out, rgb)


@pytest.mark.parametrize('change, field', [
    ({'encoding': 'rgba8'}, 'encoding'),
    ({'encoding': '16UC1'}, 'encoding'),
    ({'step': 20}, 'step'),
    ({'data': b'\x00' * 10}, 'data'),
    ({'height': 0, 'data': b''}, 'height'),
    ({'width': -3}, 'height/width'),
    ({'height': 5.0}, 'height'),
    ({'data': [1, 2, 300]}, 'data'),
])
def test_bad_fields_raise_clear_error(change: dict, field: str, rgb: np.ndarray) -> None:
    fields = array_to_image_fields(rgb, 'rgb8')
    fields.update(change)
    with pytest.raises(ImageConversionError, match=field):
        image_to_array(_msg(**fields))


def test_missing_field_and_bad_arrays() -> None:
    with pytest.raises(ImageConversionError, match='step'):
        image_to_array(SimpleNamespace(height=1, width=1, encoding='mono8', data=b'\x00'))
    with pytest.raises(ImageConversionError, match='shape'):
        array_to_image_fields(np.zeros((4, 4), np.uint8), 'rgb8')
    with pytest.raises(ImageConversionError, match='dtype'):
        array_to_image_fields(np.zeros((4, 4, 3), np.float32), 'rgb8')
    assert issubclass(ImageConversionError, ValueError)


def test_real_image_message(rgb: np.ndarray) -> None:
    from sensor_msgs.msg import Image

    msg = Image()
    for k, v in array_to_image_fields(rgb, 'rgb8').items():
        setattr(msg, k, v)
    np.testing.assert_array_equal(image_to_array(msg), rgb)
