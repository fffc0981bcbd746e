"""Camera images <-> numpy: what cv_bridge and image_transport's compressed plugin do (pure; no rclpy).

cv_bridge and image_transport have no wheels here, so the graph converts images itself; this
module covers the camera encodings of ``sensor_msgs/image_encodings.hpp`` that drivers publish:

* ``mono8``, ``mono16``;
* ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` and their 16-bit forms ``rgb16`` ... ``bgra16``;
* the four Bayer mosaics ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` and
  their 16-bit forms, demosaiced by OpenCV's ``cvtColor``: ``bilinear`` (the default, as
  cv_bridge does), ``edge_aware`` or ``vng`` (variable number of gradients: fewer zipper
  artefacts along edges, so marker corners closer to a colour camera's; slower, see
  ``tools/encoding_bench.py``); or, for grey output, ``mosaic``: no interpolation, every
  photosite read as a grey level. On a grey surface (the black-and-white marker) a
  white-balanced sensor's red, green and blue sites all read its luminance, so the mosaic *is*
  the full-resolution grey image there, which interpolation only blurs; colour areas show the
  pattern's checkerboard. Colour output from ``mosaic`` is demosaiced with ``vng``. A camera
  that does not apply its white balance to the raw data needs the gains applied here
  (:func:`balance_mosaic`, with :func:`mosaic_gains` measured on an image of a white sheet);
* YUV 4:2:2 in both byte orders: ``uyvy`` (alias ``yuv422``, the older name) and ``yuyv``
  (alias ``yuv422_yuy2``).

Every conversion goes to ``mono8`` (what the marker detector needs), ``rgb8`` or ``bgr8`` (the
viewers). 16-bit data are reduced to 8 bits first by keeping the high byte (``v >> 8``, so
``v * 257`` maps back to ``v`` exactly; cv_bridge rounds ``v / 256``, which differs by at most
one grey level), with ``is_bigendian`` honoured; rows may be padded (``step``). The abstract
``8UC3``-style encodings, the depth encodings (``16UC1``, ``32FC1``) and the YUV 4:2:0 / 4:4:4
ones (``nv21``, ``nv24``) are refused: no driver of a colour camera publishes the first two
for an image, and OpenCV has no conversion for the last that this module could be tested
against.

``sensor_msgs/CompressedImage`` (image_transport's ``compressed`` transport: JPEG or PNG) is
decoded with ``cv2.imdecode``; its ``format`` string, e.g. ``"rgb8; jpeg compressed bgr8"``, says
which encoding the publisher had and in which channel order the payload is
(:func:`compressed_to_array`). :func:`compress` writes the same strings.

Messages are duck-typed: anything with the fields (``height``, ``width``, ``encoding``,
``is_bigendian``, ``step``, ``data``; or ``format``, ``data``) works, so the functions are
testable without ROS. ``data`` may be bytes, bytearray, ``array.array('B')``, a list of ints or a
uint8 ndarray. Every inconsistency raises :class:`ImageConversionError` naming the offending
field; the nodes turn it into a warning (the detector: a bad-input frame).

Building an Image: ``msg.data`` accepts bytes far faster (~500x) than a numpy array, so
:func:`array_to_image_fields` returns the payload as ``bytes``::

    for k, v in rgb_to_image_fields(rgb, 'bayer_rggb8').items():
        setattr(msg, k, v)
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['ImageConversionError', 'Encoding', 'ENCODINGS', 'OUTPUT_ENCODINGS', 'COMPRESSED_FORMATS', 'DEMOSAICING',
           'image_to_array', 'image_to_gray', 'convert_array', 'compressed_to_array', 'message_to_array', 'message_to_gray',
           'encode_rgb', 'array_to_image_fields', 'rgb_to_image_fields', 'compress', 'parse_compressed_format',
           'message_encoding', 'check_gains', 'balance_mosaic', 'mosaic_gains']

#: Refuse absurd sizes before allocating (a corrupted header must not exhaust memory).
_MAX_SIDE = 1 << 15


@dataclass(frozen=True)
class Encoding:
    """How an encoding lays out its pixels.

    Attributes
    ----------
    name : str
        As in ``sensor_msgs/image_encodings.hpp``.
    kind : str
        ``mono``, ``rgb``, ``bgr``, ``rgba``, ``bgra``, ``bayer_rggb`` / ``bayer_bggr`` /
        ``bayer_gbrg`` / ``bayer_grbg`` (the 2 x 2 tile from the top-left pixel), ``uyvy`` or
        ``yuyv`` (YUV 4:2:2 byte order).
    channels : int
        Values per pixel in the buffer (YUV 4:2:2: 2, a luma and every other chroma).
    bits : int
        8 or 16 per value.
    """

    name: str
    kind: str
    channels: int
    bits: int

    @property
    def colour(self) -> bool:
        """Carries colour (what image_transport's ``isColor`` says: not mono, not Bayer)."""
        return self.kind in ('rgb', 'bgr', 'rgba', 'bgra', 'uyvy', 'yuyv')

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bits == 8 else np.uint16)

    @property
    def shape_text(self) -> str:
        return '(H, W)' if self.channels == 1 else f'(H, W, {self.channels})'


def _table() -> dict[str, Encoding]:
    out = {}
    for bits in (8, 16):
        out[f'mono{bits}'] = Encoding(f'mono{bits}', 'mono', 1, bits)
        for kind in ('rgb', 'bgr', 'rgba', 'bgra'):
            out[f'{kind}{bits}'] = Encoding(f'{kind}{bits}', kind, len(kind), bits)
        for pattern in ('rggb', 'bggr', 'gbrg', 'grbg'):
            out[f'bayer_{pattern}{bits}'] = Encoding(f'bayer_{pattern}{bits}', f'bayer_{pattern}', 1, bits)
    # Jazzy's names and the deprecated ones drivers still publish (usb_cam, v4l2_camera).
    for name, kind in (('uyvy', 'uyvy'), ('yuv422', 'uyvy'), ('yuyv', 'yuyv'), ('yuv422_yuy2', 'yuyv')):
        out[name] = Encoding(name, kind, 2, 8)
    return out


#: Every supported encoding.
ENCODINGS: dict[str, Encoding] = _table()
#: What a conversion can produce (besides ``passthrough``).
OUTPUT_ENCODINGS = ('mono8', 'rgb8', 'bgr8')
#: Codecs of the compressed transport.
COMPRESSED_FORMATS = ('jpeg', 'png')
#: Demosaicing of Bayer images: OpenCV's algorithms (``bilinear``: cv_bridge's), and ``mosaic``
#: (grey output: the photosites as they are; colour output: ``vng``).
DEMOSAICING = ('bilinear', 'edge_aware', 'vng', 'mosaic')
#: The 8-bit output of each kind that needs no colour conversion.
_SAME = {'mono': 'mono8', 'rgb': 'rgb8', 'bgr': 'bgr8'}


class ImageConversionError(ValueError):
    """An image message cannot be converted; the message names the bad field and value.

    Parameters
    ----------
    field : str
        The offending field (``encoding``, ``height/width``, ``step``, ``data``, ``format``, ...):
        the kind of the problem, which the node's warnings are throttled by.
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


def _encoding(name: Any, field: str = 'encoding') -> Encoding:
    try:
        return ENCODINGS[name]
    except (KeyError, TypeError):
        raise ImageConversionError(field, f'unsupported {name!r}; expected one of {sorted(ENCODINGS)}') from None


def _check_output(desired: str) -> None:
    if desired != 'passthrough' and desired not in OUTPUT_ENCODINGS:
        raise ImageConversionError('desired_encoding', f'unsupported {desired!r}; expected passthrough or one of '
                                   f'{list(OUTPUT_ENCODINGS)}')


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


# ----------------------------------------------------------------------------------------------
# Raw images


def image_to_array(msg: Any, desired_encoding: str = 'passthrough',
                   demosaicing: str = 'bilinear') -> NDArray[np.uint8] | NDArray[np.uint16]:
    """Convert a ``sensor_msgs/Image`` to a numpy array.

    Parameters
    ----------
    msg : object with ``height``, ``width``, ``encoding``, ``step``, ``data`` (and
        ``is_bigendian`` for 16-bit encodings)
    desired_encoding : {'passthrough', 'mono8', 'rgb8', 'bgr8'}
        Output encoding; ``passthrough`` keeps the message's layout (16-bit values in native
        byte order).
    demosaicing : {'bilinear', 'edge_aware', 'vng', 'mosaic'}
        For Bayer encodings (:data:`DEMOSAICING`).

    Returns
    -------
    ndarray
        uint8 of shape (H, W) for mono8 or (H, W, 3) for rgb8/bgr8; with ``passthrough`` the
        encoding's layout (:attr:`Encoding.shape_text`, uint16 for 16-bit encodings). A fresh,
        C-contiguous array (never a view of the message's buffer).

    Raises
    ------
    ImageConversionError
        Unsupported encoding, non-positive or absurd size, an odd width for YUV 4:2:2, step
        smaller than a row, or a data length that is not ``step * height``.
    """
    enc = _encoding(_field(msg, 'encoding'))
    _check_output(desired_encoding)
    height, width, step = (_field(msg, k) for k in ('height', 'width', 'step'))
    for name, v in (('height', height), ('width', width), ('step', step)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ImageConversionError(name, f'expected an integer, got {v!r}')
    if not (0 < height <= _MAX_SIDE and 0 < width <= _MAX_SIDE):
        raise ImageConversionError('height/width', f'expected 1..{_MAX_SIDE} pixels, '
                                   f'got {height} x {width}')
    if enc.kind in ('uyvy', 'yuyv') and width % 2:
        raise ImageConversionError('width', f'{enc.name} pairs pixels (4:2:2), so the width must be even, got {width}')
    row = width * enc.channels * enc.bits // 8
    if step < row:
        raise ImageConversionError('step', f'{step} bytes is less than a row of {width} x {enc.channels} x '
                                   f'{enc.bits // 8} = {row} bytes for {enc.name}')
    buf = _as_bytes_view(_field(msg, 'data'))
    if buf.size != step * height:
        raise ImageConversionError('data', f'length {buf.size} bytes, expected step * height = '
                                   f'{step} * {height} = {step * height}')
    rows = buf.reshape(height, step)[:, :row]
    if enc.bits == 16:
        big = _field(msg, 'is_bigendian')
        rows = np.ascontiguousarray(rows).view('>u2' if big else '<u2').astype(np.uint16, copy=False)
    img = rows.reshape(height, width, enc.channels) if enc.channels > 1 else rows
    if desired_encoding == 'passthrough':
        return np.array(img, dtype=enc.dtype, order='C')
    return convert_array(img, enc, desired_encoding, demosaicing)


def _cv2_codes() -> dict[tuple[str, str], int]:
    """cvtColor codes from an 8-bit kind to an output encoding."""
    import cv2

    codes = {('mono', 'rgb8'): cv2.COLOR_GRAY2RGB, ('mono', 'bgr8'): cv2.COLOR_GRAY2BGR,
             ('rgb', 'mono8'): cv2.COLOR_RGB2GRAY, ('rgb', 'bgr8'): cv2.COLOR_RGB2BGR,
             ('bgr', 'mono8'): cv2.COLOR_BGR2GRAY, ('bgr', 'rgb8'): cv2.COLOR_BGR2RGB,
             ('rgba', 'mono8'): cv2.COLOR_RGBA2GRAY, ('rgba', 'rgb8'): cv2.COLOR_RGBA2RGB,
             ('rgba', 'bgr8'): cv2.COLOR_RGBA2BGR,
             ('bgra', 'mono8'): cv2.COLOR_BGRA2GRAY, ('bgra', 'rgb8'): cv2.COLOR_BGRA2RGB,
             ('bgra', 'bgr8'): cv2.COLOR_BGRA2BGR,
             ('uyvy', 'mono8'): cv2.COLOR_YUV2GRAY_UYVY, ('uyvy', 'rgb8'): cv2.COLOR_YUV2RGB_UYVY,
             ('uyvy', 'bgr8'): cv2.COLOR_YUV2BGR_UYVY,
             ('yuyv', 'mono8'): cv2.COLOR_YUV2GRAY_YUY2, ('yuyv', 'rgb8'): cv2.COLOR_YUV2RGB_YUY2,
             ('yuyv', 'bgr8'): cv2.COLOR_YUV2BGR_YUY2}
    # OpenCV names a Bayer pattern by the second row's second and third pixels, so ROS's
    # bayer_rggb (R at the top left) is OpenCV's BayerBG (cv_bridge's mapping; tested with
    # flat colours in test_image_conversion).
    for ros, cv in (('rggb', 'BG'), ('bggr', 'RG'), ('gbrg', 'GR'), ('grbg', 'GB')):
        for out, suffix in (('mono8', 'GRAY'), ('rgb8', 'RGB'), ('bgr8', 'BGR')):
            codes[(f'bayer_{ros}', out)] = getattr(cv2, f'COLOR_Bayer{cv}2{suffix}')
        # The other algorithms give colour only (grey: their RGB's luma).
        for method, tail in (('edge_aware', '_EA'), ('vng', '_VNG')):
            for out, suffix in (('rgb8', 'RGB'), ('bgr8', 'BGR')):
                codes[(f'bayer_{ros}', out, method)] = getattr(cv2, f'COLOR_Bayer{cv}2{suffix}{tail}')
    return codes


_CODES: dict[tuple[str, ...], int] = {}


def convert_array(img: NDArray[Any], encoding: Encoding | str, desired: str,
                  demosaicing: str = 'bilinear') -> NDArray[np.uint8]:
    """An array laid out as ``encoding`` converted to ``desired`` (``mono8``, ``rgb8`` or ``bgr8``).

    Parameters
    ----------
    img : ndarray, the encoding's layout (:attr:`Encoding.shape_text`), uint8 or uint16
    encoding : Encoding or str
    desired : {'mono8', 'rgb8', 'bgr8'}
    demosaicing : {'bilinear', 'edge_aware', 'vng', 'mosaic'}
        For Bayer encodings (:data:`DEMOSAICING`).

    Returns
    -------
    ndarray, uint8, (H, W) or (H, W, 3); a fresh array.
    """
    import cv2

    enc = _encoding(encoding) if isinstance(encoding, str) else encoding
    _check_output(desired)
    if desired == 'passthrough':
        raise ImageConversionError('desired_encoding', 'convert_array needs an output encoding')
    if demosaicing not in DEMOSAICING:
        raise ImageConversionError('demosaicing', f'unsupported {demosaicing!r}; expected one of {list(DEMOSAICING)}')
    if enc.bits == 16:
        img = (img >> 8).astype(np.uint8)          # the high byte: v * 257 -> v exactly
    if _SAME.get(enc.kind) == desired or (enc.kind.startswith('bayer_') and demosaicing == 'mosaic'
                                          and desired == 'mono8'):
        return np.array(img, dtype=np.uint8, order='C')
    if demosaicing == 'mosaic':
        demosaicing = 'vng'                        # colour for the viewers: the mosaic is grey only
    if not _CODES:
        _CODES.update(_cv2_codes())
    img = np.ascontiguousarray(img)
    if enc.kind.startswith('bayer_') and demosaicing != 'bilinear':
        rgb = cv2.cvtColor(img, _CODES[(enc.kind, 'bgr8' if desired == 'bgr8' else 'rgb8', demosaicing)])
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if desired == 'mono8' else rgb
    return cv2.cvtColor(img, _CODES[(enc.kind, desired)])


def image_to_gray(msg: Any, demosaicing: str = 'bilinear') -> NDArray[np.uint8]:
    """The image as 8-bit grey levels, shape (H, W): what the marker detector needs."""
    return image_to_array(msg, 'mono8', demosaicing)


# ----------------------------------------------------------------------------------------------
# Building images (the simulator, tests and benchmarks)


def _mosaic(rgb: NDArray[Any], pattern: str) -> NDArray[Any]:
    """The Bayer mosaic of ``rgb`` (H, W, 3): each pixel keeps the channel its filter passes."""
    out = np.empty(rgb.shape[:2], rgb.dtype)
    channel = {'r': 0, 'g': 1, 'b': 2}
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, channel[pattern[k]]]
    return out


def encode_rgb(rgb: NDArray[np.uint8], encoding: str) -> NDArray[Any]:
    """An rgb8 image in ``encoding``'s layout, as a camera of that encoding would deliver it.

    Grey is OpenCV's luma; Bayer keeps each pixel's filter channel (a mosaic); YUV 4:2:2 is
    OpenCV's BT.601 conversion (``COLOR_RGB2YUV_UYVY`` / ``_YUY2``); 16 bits are ``v * 257``
    (the full 16-bit range).

    Parameters
    ----------
    rgb : ndarray, uint8, shape (H, W, 3)
    encoding : str
        Any of :data:`ENCODINGS`.

    Returns
    -------
    ndarray in the encoding's layout (:attr:`Encoding.shape_text`), uint8 or uint16.

    Raises
    ------
    ImageConversionError
        Unknown encoding, an array that is not (H, W, 3) uint8, or an odd width for YUV 4:2:2.
    """
    import cv2

    enc = _encoding(encoding)
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or 0 in a.shape:
        raise ImageConversionError('array', f'expected an rgb8 image (H, W, 3) uint8, got {a.dtype} {a.shape}')
    a = np.ascontiguousarray(a)
    if enc.kind in ('uyvy', 'yuyv') and a.shape[1] % 2:
        raise ImageConversionError('width', f'{enc.name} pairs pixels (4:2:2), so the width must be even, '
                                   f'got {a.shape[1]}')
    if enc.kind.startswith('bayer_'):
        out = _mosaic(a, enc.kind[len('bayer_'):])
    elif enc.kind == 'rgb':
        out = a.copy()
    else:
        code = {'mono': cv2.COLOR_RGB2GRAY, 'bgr': cv2.COLOR_RGB2BGR, 'rgba': cv2.COLOR_RGB2RGBA,
                'bgra': cv2.COLOR_RGB2BGRA, 'uyvy': cv2.COLOR_RGB2YUV_UYVY, 'yuyv': cv2.COLOR_RGB2YUV_YUY2}[enc.kind]
        out = cv2.cvtColor(a, code)
    return out.astype(np.uint16) * 257 if enc.bits == 16 else out


def array_to_image_fields(array: NDArray[Any], encoding: str = 'rgb8', *, step: int | None = None,
                          bigendian: bool = False) -> dict[str, Any]:
    """Image message fields for an array: ``height, width, encoding, is_bigendian, step, data``.

    Parameters
    ----------
    array : ndarray in ``encoding``'s layout (:attr:`Encoding.shape_text`; (H, W, 1) is taken
        for (H, W)), uint8 for 8-bit encodings, uint16 for 16-bit ones
    encoding : str
        How ``array`` is laid out (no conversion is done; :func:`rgb_to_image_fields` converts).
    step : int, optional
        Row length in bytes; longer than a row pads each row with zeros (default: tightly packed).
    bigendian : bool
        Write 16-bit values big-endian.

    Returns
    -------
    dict
        ``data`` is ``bytes``.
    """
    enc = _encoding(encoding)
    a = np.asarray(array)
    if a.dtype != enc.dtype:
        raise ImageConversionError('array', f'expected dtype {enc.dtype} for {enc.name}, got {a.dtype}')
    if enc.channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if (a.ndim != (2 if enc.channels == 1 else 3) or (enc.channels > 1 and a.shape[2] != enc.channels)
            or 0 in a.shape):
        raise ImageConversionError('array', f'shape {a.shape} does not fit {enc.name} {enc.shape_text}')
    h, w = a.shape[:2]
    if enc.kind in ('uyvy', 'yuyv') and w % 2:
        raise ImageConversionError('width', f'{enc.name} pairs pixels (4:2:2), so the width must be even, got {w}')
    if enc.bits == 16:
        a = a.astype('>u2' if bigendian else '<u2')
    rows = np.ascontiguousarray(a).reshape(h, -1).view(np.uint8)
    row = rows.shape[1]
    step = row if step is None else int(step)
    if step < row:
        raise ImageConversionError('step', f'{step} bytes is less than a row of {row} bytes for {enc.name}')
    if step > row:
        padded = np.zeros((h, step), np.uint8)
        padded[:, :row] = rows
        rows = padded
    return {'height': int(h), 'width': int(w), 'encoding': enc.name, 'is_bigendian': int(bool(bigendian)),
            'step': step, 'data': rows.tobytes()}


def rgb_to_image_fields(rgb: NDArray[np.uint8], encoding: str = 'rgb8', **kwargs: Any) -> dict[str, Any]:
    """Image message fields of an rgb8 image converted to ``encoding`` (:func:`encode_rgb`);
    ``kwargs`` (``step``, ``bigendian``) go to :func:`array_to_image_fields`."""
    return array_to_image_fields(encode_rgb(rgb, encoding), encoding, **kwargs)


# ----------------------------------------------------------------------------------------------
# Compressed images (image_transport's compressed plugin)

_FORMAT = re.compile(r'^\s*(?P<enc>[^;]*?)\s*;\s*(?P<codec>\w+)\s+compressed\s*(?P<target>\w*)\s*$')


def parse_compressed_format(fmt: str) -> tuple[str, str, str]:
    """The parts of a ``CompressedImage.format``: (source encoding, codec, payload channel order).

    ``"rgb8; jpeg compressed bgr8"`` -> ``('rgb8', 'jpeg', 'bgr')``; ``"mono8; png compressed "``
    -> ``('mono8', 'png', '')``; a bare ``"jpeg"`` or ``"png"`` (older publishers, camera
    drivers passing MJPEG through) -> ``('', 'jpeg', '')``.

    Raises
    ------
    ImageConversionError
        ``format``: depth images (``compressedDepth``) or a codec other than JPEG/PNG.
    """
    text = str(fmt).strip()
    m = _FORMAT.match(text)
    if m:
        enc, codec, target = m.group('enc'), m.group('codec').lower(), m.group('target').lower()
    elif ';' not in text and text.lower() in ('jpeg', 'jpg', 'png', ''):
        enc, codec, target = '', 'jpeg' if text.lower() in ('jpg', '') else text.lower(), ''
    else:
        raise ImageConversionError('format', f'unsupported {fmt!r}; expected image_transport\'s "<encoding>; '
                                   f'jpeg|png compressed [bgr8|rgb8]" or "jpeg" / "png" (compressedDepth is for '
                                   f'depth images)')
    if codec == 'jpg':
        codec = 'jpeg'
    if codec not in COMPRESSED_FORMATS:
        raise ImageConversionError('format', f'codec {codec!r} in {fmt!r} is not one of {list(COMPRESSED_FORMATS)}')
    order = 'rgb' if target.startswith('rgb') else 'bgr' if target.startswith('bgr') else ''
    return enc, codec, order


def compressed_to_array(msg: Any, desired_encoding: str = 'passthrough',
                        demosaicing: str = 'bilinear') -> NDArray[np.uint8] | NDArray[np.uint16]:
    """Decode a ``sensor_msgs/CompressedImage`` (JPEG or PNG) as image_transport's subscriber does.

    The payload is what the publisher compressed: a colour image converted to ``bgr8`` (or
    ``rgb8``, as the format's last word says), or a mono / Bayer image as it was.

    Parameters
    ----------
    msg : object with ``format`` and ``data``
    desired_encoding : {'passthrough', 'mono8', 'rgb8', 'bgr8'}
        ``passthrough``: the decoded payload as it is (colour in the payload's channel order).
        ``mono8`` of a colour JPEG decodes straight to the JPEG's luma (OpenCV's
        ``IMREAD_GRAYSCALE``, which skips the chroma).
    demosaicing : {'bilinear', 'edge_aware', 'vng', 'mosaic'}
        For a Bayer payload.

    Returns
    -------
    ndarray, as :func:`image_to_array`.

    Raises
    ------
    ImageConversionError
        ``format`` (see :func:`parse_compressed_format`, or a Bayer/mono source whose payload has
        colour), ``data`` (empty or not decodable).
    """
    import cv2

    src, codec, order = parse_compressed_format(_field(msg, 'format'))
    _check_output(desired_encoding)
    source = ENCODINGS.get(src)
    if src and source is None:
        raise ImageConversionError('format', f'source encoding {src!r} is not one of {sorted(ENCODINGS)}')
    buf = _as_bytes_view(_field(msg, 'data'))
    if buf.size == 0:
        raise ImageConversionError('data', 'empty compressed image')
    # Grey from a colour JPEG: libjpeg's luma, without upsampling the chroma (1.7x faster at
    # 1280x1024). Not for PNG: OpenCV's grey on reading differs from cvtColor's by one level,
    # and a lossless PNG should give exactly the raw image's grey.
    colour = source is None or source.colour
    gray = desired_encoding == 'mono8' and colour and codec == 'jpeg'
    flags = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_UNCHANGED
    img = cv2.imdecode(buf, flags)
    if img is None:
        raise ImageConversionError('data', f'{buf.size} bytes are not a JPEG or PNG image OpenCV can decode')
    if gray:
        return img
    channels = 1 if img.ndim == 2 else img.shape[2]
    bits = 16 if img.dtype == np.uint16 else 8
    if channels == 1:
        # A mono or Bayer image compressed as it was (a colour source's grey payload: mono).
        payload = source if source is not None and not source.colour and source.bits == bits else \
            ENCODINGS[f'mono{bits}']
    elif source is not None and not source.colour:
        raise ImageConversionError('format', f'{src} is mono or Bayer but the payload has {channels} channels')
    else:
        kind = ('rgb' if order == 'rgb' else 'bgr') + ('a' if channels == 4 else '')
        payload = ENCODINGS[f'{kind}{bits}']
    if desired_encoding == 'passthrough':
        return img
    return convert_array(img, payload, desired_encoding, demosaicing)


def compress(array: NDArray[Any], encoding: str, fmt: str = 'jpeg', *, jpeg_quality: int = 95,
             png_level: int = 3) -> dict[str, Any]:
    """CompressedImage fields (``format``, ``data``) as image_transport's compressed publisher
    writes them: a colour image goes to ``bgr8`` (``bgr16`` for a 16-bit PNG), a mono or
    Bayer image is compressed as it is; ``format`` is ``"<encoding>; <fmt> compressed <target>"``.

    Parameters
    ----------
    array : ndarray in ``encoding``'s layout
    encoding : str
    fmt : {'jpeg', 'png'}
    jpeg_quality : int
        1..100 (image_transport's default 95).
    png_level : int
        0..9 (image_transport's default 3).

    Raises
    ------
    ImageConversionError
        Unknown encoding or codec, or JPEG of 16-bit data (JPEG is 8-bit; image_transport
        refuses it too).
    """
    import cv2

    enc = _encoding(encoding)
    if fmt not in COMPRESSED_FORMATS:
        raise ImageConversionError('format', f'unsupported codec {fmt!r}; expected one of {list(COMPRESSED_FORMATS)}')
    if fmt == 'jpeg' and enc.bits != 8:
        raise ImageConversionError('encoding', f'JPEG needs 8-bit data; {enc.name} is {enc.bits}-bit (use png)')
    a = np.asarray(array)
    target = ''
    if enc.colour:
        # image_transport converts colour to BGR in the source's depth (YUV: 8 bits).
        a = convert_array(a, enc, 'bgr8') if enc.bits == 8 or fmt == 'jpeg' else _bgr16(a, enc)
        target = 'bgr8' if a.dtype == np.uint8 else 'bgr16'
    params = ([cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == 'jpeg'
              else [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    ok, data = cv2.imencode('.jpg' if fmt == 'jpeg' else '.png', np.ascontiguousarray(a), params)
    if not ok:
        raise ImageConversionError('array', f'OpenCV could not encode {enc.name} {a.shape} as {fmt}')
    return {'format': f'{enc.name}; {fmt} compressed {target}', 'data': data.tobytes()}


def _bgr16(a: NDArray[np.uint16], enc: Encoding) -> NDArray[np.uint16]:
    import cv2

    codes = {'rgb': cv2.COLOR_RGB2BGR, 'rgba': cv2.COLOR_RGBA2BGR, 'bgra': cv2.COLOR_BGRA2BGR}
    return a.copy() if enc.kind == 'bgr' else cv2.cvtColor(np.ascontiguousarray(a), codes[enc.kind])


# ----------------------------------------------------------------------------------------------
# Either transport


def message_to_array(msg: Any, desired_encoding: str = 'passthrough', demosaicing: str = 'bilinear') -> NDArray[Any]:
    """:func:`compressed_to_array` for a message with ``format`` (a CompressedImage), else
    :func:`image_to_array`."""
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        return compressed_to_array(msg, desired_encoding, demosaicing)
    return image_to_array(msg, desired_encoding, demosaicing)


def message_to_gray(msg: Any, demosaicing: str = 'bilinear') -> NDArray[np.uint8]:
    """Either kind of image message as 8-bit grey levels, shape (H, W)."""
    return message_to_array(msg, 'mono8', demosaicing)


# ----------------------------------------------------------------------------------------------
# A Bayer mosaic read as grey: white balance


def message_encoding(msg: Any) -> str:
    """The camera encoding of either kind of image message (a CompressedImage's from its
    ``format``; ``''`` where a bare ``"jpeg"`` format does not say)."""
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        return parse_compressed_format(str(_field(msg, 'format')))[0]
    return str(_field(msg, 'encoding'))


def _site_colours(shape: tuple[int, ...], encoding: str) -> NDArray[np.intp]:
    """Colour index (0 red, 1 green, 2 blue) of every photosite of a ``shape`` (H, W) mosaic."""
    enc = _encoding(encoding)
    if not enc.kind.startswith('bayer_'):
        raise ImageConversionError('encoding', f'{encoding!r} is not a Bayer encoding')
    tile = np.array([{'r': 0, 'g': 1, 'b': 2}[c] for c in enc.kind[len('bayer_'):]]).reshape(2, 2)
    return np.tile(tile, ((shape[0] + 1) // 2, (shape[1] + 1) // 2))[:shape[0], :shape[1]]


def check_gains(gains: Sequence[float]) -> tuple[float, float, float]:
    """White-balance gains (red, green, blue) as three floats.

    Raises
    ------
    ImageConversionError
        ``gains`` are not three positive finite numbers.
    """
    g = np.asarray(gains, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.all(g > 0):
        raise ImageConversionError('gains', f'expected three positive finite gains (red, green, blue), got {list(gains)}')
    return float(g[0]), float(g[1]), float(g[2])


def balance_mosaic(grey: NDArray[np.uint8], encoding: str, gains: Sequence[float]) -> NDArray[np.uint8]:
    """A Bayer image read as grey (``demosaicing='mosaic'``) with each photosite multiplied by its
    colour's white-balance gain: what a camera that balances its raw data would have sent.

    Parameters
    ----------
    grey : ndarray, uint8, shape (H, W)
        The mosaic, as :func:`message_to_gray` returns it with ``demosaicing='mosaic'``.
    encoding : str
        Its Bayer encoding (``bayer_rggb8`` ...): which colour each site sees.
    gains : sequence of 3 float
        Red, green and blue gains, each > 0 (:func:`mosaic_gains`).

    Returns
    -------
    ndarray, uint8, shape (H, W); rounded, clipped to 0-255.

    Raises
    ------
    ImageConversionError
        ``encoding`` is not a Bayer one, or ``gains`` are not three positive finite numbers.
    """
    g = np.array(check_gains(gains))
    scaled = grey * g[_site_colours(grey.shape, encoding)]
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


def mosaic_gains(grey: NDArray[np.uint8], encoding: str) -> tuple[float, float, float]:
    """White-balance gains (red, green, blue; green 1) for :func:`balance_mosaic`, from a mosaic of
    a white or grey surface filling the image (a sheet of paper in front of the camera, neither
    black nor saturated): the green sites' mean over each colour's.

    Raises
    ------
    ImageConversionError
        ``encoding`` is not a Bayer one, or a colour's sites are dark (mean under 10 grey levels:
        no surface to balance on) or saturated (over 245).
    """
    colours = _site_colours(grey.shape, encoding)
    means = np.array([float(np.mean(grey[colours == c])) for c in range(3)])
    for name, m in zip(('red', 'green', 'blue'), means):
        if not 10.0 <= m <= 245.0:
            raise ImageConversionError('data', f'the {name} sites average {m:.1f} grey levels; a white sheet '
                                       f'needs 10-245 (not dark, not saturated)')
    return float(means[1] / means[0]), 1.0, float(means[1] / means[2])
