"""sensor_msgs/Image <-> numpy, the few conversions cv_bridge would do (pure; no rclpy).

The message is duck-typed: anything with ``height``, ``width``, ``encoding``, ``step`` and
``data`` (bytes, bytearray, ``array.array('B')``, a list of ints or a uint8 ndarray) works, so the
functions are testable without ROS. Supported encodings are the 8-bit ones our graph uses:
``rgb8``, ``bgr8`` and ``mono8``. Every inconsistency raises :class:`ImageConversionError`
naming the offending field; the node turns it into a warning and a failed outcome.

Building an Image: ``msg.data`` accepts bytes far faster (~500x) than a numpy array, so
:func:`array_to_image_fields` returns the payload as ``bytes``::

    for k, v in array_to_image_fields(rgb, 'rgb8').items():
        setattr(msg, k, v)
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['ImageConversionError', 'ENCODING_CHANNELS', 'image_to_array', 'image_to_gray',
           'array_to_image_fields']

#: Supported encodings and their channel count (all 8 bits per channel).
ENCODING_CHANNELS: dict[str, int] = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}

#: Refuse absurd sizes before allocating (a corrupted header must not exhaust memory).
_MAX_SIDE = 1 << 15


class ImageConversionError(ValueError):
    """An image message cannot be converted; the message names the bad field and value.

    Parameters
    ----------
    field : str
        The offending field (``encoding``, ``height/width``, ``step``, ``data``, ...): the kind of
        the problem, which the node's warnings are throttled by.
    reason : str
    """

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f'{field}: {reason}')
        self.field = field


def _field(msg: Any, name: str) -> Any:
    try:
        return getattr(msg, name)
    except AttributeError:
        raise ImageConversionError(name, 'image message has no such field') from None


def _as_bytes_view(data: Any) -> NDArray[np.uint8]:
    """A flat uint8 view of the payload without copying when the buffer protocol allows."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise ImageConversionError('data', f'expected uint8 values, got dtype {data.dtype}')
        return data.reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        pass
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError) as exc:
        raise ImageConversionError('data', f'not a byte sequence ({type(data).__name__})') from exc
    if arr.ndim != 1 or (arr.size and (not np.issubdtype(arr.dtype, np.integer)
                                       or arr.min() < 0 or arr.max() > 255)):
        raise ImageConversionError('data', f'expected a flat sequence of bytes, got '
                                   f'{type(data).__name__} of shape {arr.shape}')
    return arr.astype(np.uint8)


def image_to_array(msg: Any, desired_encoding: str = 'passthrough') -> NDArray[np.uint8]:
    """Convert an Image message to a numpy array.

    Parameters
    ----------
    msg : object with ``height``, ``width``, ``encoding``, ``step``, ``data``
    desired_encoding : {'passthrough', 'rgb8', 'bgr8', 'mono8'}
        Output encoding; ``passthrough`` keeps the message's.

    Returns
    -------
    ndarray, uint8, shape (H, W, 3) for colour or (H, W) for mono8
        A fresh, C-contiguous array (never a view of the message's buffer).

    Raises
    ------
    ImageConversionError
        Unsupported encoding, non-positive or absurd size, step smaller than a row, or a data
        length that is not ``step * height``.
    """
    encoding = _field(msg, 'encoding')
    if encoding not in ENCODING_CHANNELS:
        raise ImageConversionError('encoding', f'unsupported {encoding!r}; expected one of '
                                   f'{sorted(ENCODING_CHANNELS)}')
    if desired_encoding != 'passthrough' and desired_encoding not in ENCODING_CHANNELS:
        raise ImageConversionError('desired_encoding', f'unsupported {desired_encoding!r}')
    height, width, step = (_field(msg, k) for k in ('height', 'width', 'step'))
    for name, v in (('height', height), ('width', width), ('step', step)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ImageConversionError(name, f'expected an integer, got {v!r}')
    if not (0 < height <= _MAX_SIDE and 0 < width <= _MAX_SIDE):
        raise ImageConversionError('height/width', f'expected 1..{_MAX_SIDE} pixels, '
                                   f'got {height} x {width}')
    channels = ENCODING_CHANNELS[encoding]
    row = width * channels
    if step < row:
        raise ImageConversionError('step', f'{step} bytes is less than a row of {width} x {channels} '
                                   f'= {row} bytes for {encoding}')
    buf = _as_bytes_view(_field(msg, 'data'))
    if buf.size != step * height:
        raise ImageConversionError('data', f'length {buf.size} bytes, expected step * height = '
                                   f'{step} * {height} = {step * height}')
    img = buf.reshape(height, step)[:, :row]
    img = img.reshape(height, width, channels) if channels > 1 else img
    out_enc = encoding if desired_encoding == 'passthrough' else desired_encoding
    return _convert(img, encoding, out_enc)


def _convert(img: NDArray[np.uint8], src: str, dst: str) -> NDArray[np.uint8]:
    import cv2

    if src == dst:
        return np.ascontiguousarray(img).copy()
    codes = {('rgb8', 'bgr8'): cv2.COLOR_RGB2BGR, ('bgr8', 'rgb8'): cv2.COLOR_BGR2RGB,
             ('rgb8', 'mono8'): cv2.COLOR_RGB2GRAY, ('bgr8', 'mono8'): cv2.COLOR_BGR2GRAY,
             ('mono8', 'rgb8'): cv2.COLOR_GRAY2RGB, ('mono8', 'bgr8'): cv2.COLOR_GRAY2BGR}
    return cv2.cvtColor(np.ascontiguousarray(img), codes[(src, dst)])


def image_to_gray(msg: Any) -> NDArray[np.uint8]:
    """The image as 8-bit grey levels, shape (H, W): what the marker detector needs."""
    return image_to_array(msg, 'mono8')


def array_to_image_fields(array: NDArray[np.uint8], encoding: str = 'rgb8') -> dict[str, Any]:
    """Image message fields for an array: ``height, width, encoding, is_bigendian, step, data``.

    Parameters
    ----------
    array : ndarray, uint8, shape (H, W, 3) for rgb8/bgr8 or (H, W) / (H, W, 1) for mono8
    encoding : {'rgb8', 'bgr8', 'mono8'}
        How the channels of ``array`` are ordered (no conversion is done).

    Returns
    -------
    dict
        ``data`` is ``bytes`` (tightly packed rows, ``step = W * channels``).
    """
    if encoding not in ENCODING_CHANNELS:
        raise ImageConversionError('encoding', f'unsupported {encoding!r}; expected one of '
                                   f'{sorted(ENCODING_CHANNELS)}')
    a = np.asarray(array)
    if a.dtype != np.uint8:
        raise ImageConversionError('array', f'expected dtype uint8, got {a.dtype}')
    channels = ENCODING_CHANNELS[encoding]
    if channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    want = 2 if channels == 1 else 3
    if a.ndim != want or (channels > 1 and a.shape[2] != channels) or 0 in a.shape:
        raise ImageConversionError('array', f'shape {a.shape} does not fit {encoding} '
                                   f'({"(H, W)" if channels == 1 else "(H, W, 3)"})')
    h, w = a.shape[:2]
    return {'height': int(h), 'width': int(w), 'encoding': encoding, 'is_bigendian': 0,
            'step': int(w * channels), 'data': np.ascontiguousarray(a).tobytes()}
