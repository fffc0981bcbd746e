"""Image conversion: every camera encoding against OpenCV's own cvtColor, the Bayer and YUV
layouts against colours known in advance, byte order, padded rows, compressed JPEG/PNG as
image_transport writes them, and a clear error for every bad field."""
from __future__ import annotations

import array
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from calibration_interfaces.image_conversion import (ENCODINGS, ImageConversionError, array_to_image_fields,
                                                     balance_mosaic, compress, compressed_to_array, encode_rgb,
                                                     image_to_array, image_to_gray, message_encoding, message_to_array,
                                                     message_to_gray, mosaic_gains, parse_compressed_format,
                                                     rgb_to_image_fields)


def _msg(**fields):
    return SimpleNamespace(**fields)


@pytest.fixture
def rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)


def _random_layout(name: str, h: int = 6, w: int = 8, seed: int = 1) -> np.ndarray:
    """A random array in the layout of ``name`` (any values a camera could send)."""
    enc = ENCODINGS[name]
    shape = (h, w) if enc.channels == 1 else (h, w, enc.channels)
    return np.random.default_rng(seed).integers(0, 1 << enc.bits, shape, dtype=enc.dtype)


# OpenCV's cvtColor code from each 8-bit layout to (mono8, rgb8, bgr8), written out here
# independently of the module's table; None: no conversion (the array itself).
C = cv2
REFERENCE = {
    'mono': (None, C.COLOR_GRAY2RGB, C.COLOR_GRAY2BGR),
    'rgb': (C.COLOR_RGB2GRAY, None, C.COLOR_RGB2BGR),
    'bgr': (C.COLOR_BGR2GRAY, C.COLOR_BGR2RGB, None),
    'rgba': (C.COLOR_RGBA2GRAY, C.COLOR_RGBA2RGB, C.COLOR_RGBA2BGR),
    'bgra': (C.COLOR_BGRA2GRAY, C.COLOR_BGRA2RGB, C.COLOR_BGRA2BGR),
    'bayer_rggb': (C.COLOR_BayerRGGB2GRAY, C.COLOR_BayerRGGB2RGB, C.COLOR_BayerRGGB2BGR),
    'bayer_bggr': (C.COLOR_BayerBGGR2GRAY, C.COLOR_BayerBGGR2RGB, C.COLOR_BayerBGGR2BGR),
    'bayer_gbrg': (C.COLOR_BayerGBRG2GRAY, C.COLOR_BayerGBRG2RGB, C.COLOR_BayerGBRG2BGR),
    'bayer_grbg': (C.COLOR_BayerGRBG2GRAY, C.COLOR_BayerGRBG2RGB, C.COLOR_BayerGRBG2BGR),
    'uyvy': (C.COLOR_YUV2GRAY_UYVY, C.COLOR_YUV2RGB_UYVY, C.COLOR_YUV2BGR_UYVY),
    'yuyv': (C.COLOR_YUV2GRAY_YUY2, C.COLOR_YUV2RGB_YUY2, C.COLOR_YUV2BGR_YUY2),
}


def test_every_sensor_msgs_camera_encoding_is_covered() -> None:
    want = {'mono8', 'mono16', 'rgb8', 'bgr8', 'rgba8', 'bgra8', 'rgb16', 'bgr16', 'rgba16', 'bgra16',
            'uyvy', 'yuv422', 'yuyv', 'yuv422_yuy2'}
    want |= {f'bayer_{p}{b}' for p in ('rggb', 'bggr', 'gbrg', 'grbg') for b in (8, 16)}
    assert set(ENCODINGS) == want


@pytest.mark.parametrize('name', sorted(ENCODINGS))
def test_passthrough_round_trip(name: str) -> None:
    arr = _random_layout(name)
    fields = array_to_image_fields(arr, name)
    assert isinstance(fields['data'], bytes)
    assert fields['step'] == arr.shape[1] * ENCODINGS[name].channels * arr.itemsize
    out = image_to_array(_msg(**fields))
    assert out.dtype == arr.dtype and out.flags['C_CONTIGUOUS']
    np.testing.assert_array_equal(out, arr)


@pytest.mark.parametrize('name', sorted(ENCODINGS))
@pytest.mark.parametrize('k, desired', list(enumerate(['mono8', 'rgb8', 'bgr8'])))
def test_conversion_matches_opencv_cvtcolor(name: str, k: int, desired: str) -> None:
    enc = ENCODINGS[name]
    arr = _random_layout(name, 10, 12, seed=k)
    eight = (arr >> 8).astype(np.uint8) if enc.bits == 16 else arr     # the high byte
    code = REFERENCE[enc.kind][k]
    want = eight if code is None else cv2.cvtColor(eight, code)
    got = image_to_array(_msg(**array_to_image_fields(arr, name)), desired)
    assert got.dtype == np.uint8 and got.shape == want.shape
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize('name', ['bayer_rggb8', 'bayer_bggr16', 'bayer_gbrg8', 'bayer_grbg16'])
@pytest.mark.parametrize('method, tail', [('edge_aware', '_EA'), ('vng', '_VNG')])
def test_other_demosaicing_algorithms_match_opencv(name: str, method: str, tail: str) -> None:
    arr = _random_layout(name, 10, 12)
    eight = (arr >> 8).astype(np.uint8) if arr.dtype == np.uint16 else arr
    tile = {'bayer_rggb': 'RGGB', 'bayer_bggr': 'BGGR', 'bayer_gbrg': 'GBRG', 'bayer_grbg': 'GRBG'}[ENCODINGS[name].kind]
    msg = _msg(**array_to_image_fields(arr, name))
    rgb = cv2.cvtColor(eight, getattr(cv2, f'COLOR_Bayer{tile}2RGB{tail}'))
    np.testing.assert_array_equal(image_to_array(msg, 'rgb8', method), rgb)
    np.testing.assert_array_equal(image_to_array(msg, 'bgr8', method),
                                  cv2.cvtColor(eight, getattr(cv2, f'COLOR_Bayer{tile}2BGR{tail}')))
    np.testing.assert_array_equal(image_to_gray(msg, method), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    with pytest.raises(ImageConversionError, match='demosaicing'):
        image_to_gray(msg, 'nearest')


def _ros_mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Bayer mosaic as sensor_msgs defines it: ``pattern`` is the 2x2 tile read from the top left."""
    ch = {'r': 0, 'g': 1, 'b': 2}
    out = np.zeros(rgb.shape[:2], rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, ch[pattern[0]]]
    out[0::2, 1::2] = rgb[0::2, 1::2, ch[pattern[1]]]
    out[1::2, 0::2] = rgb[1::2, 0::2, ch[pattern[2]]]
    out[1::2, 1::2] = rgb[1::2, 1::2, ch[pattern[3]]]
    return out


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
@pytest.mark.parametrize('bits', [8, 16])
def test_bayer_patterns_demosaic_to_the_colour_that_was_mosaicked(pattern: str, bits: int) -> None:
    colour = np.array([200, 90, 30], np.uint8)       # R, G, B all different: a swap shows
    flat = np.broadcast_to(colour, (8, 10, 3)).copy()
    mosaic = _ros_mosaic(flat, pattern)
    np.testing.assert_array_equal(encode_rgb(flat, f'bayer_{pattern}{bits}'),
                                  mosaic.astype(np.uint16) * 257 if bits == 16 else mosaic)
    name = f'bayer_{pattern}{bits}'
    for method in ('bilinear', 'edge_aware', 'vng'):
        out = image_to_array(_msg(**rgb_to_image_fields(flat, name)), 'rgb8', method)
        np.testing.assert_array_equal(out[2:-2, 2:-2], flat[2:-2, 2:-2], err_msg=method)   # borders: extrapolated
    bgr = image_to_array(_msg(**rgb_to_image_fields(flat, name)), 'bgr8')
    np.testing.assert_array_equal(bgr[2:-2, 2:-2], flat[2:-2, 2:-2, ::-1])


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
@pytest.mark.parametrize('bits', [8, 16])
def test_mosaic_reads_every_photosite_as_grey(pattern: str, bits: int) -> None:
    rng = np.random.default_rng(3)
    name = f'bayer_{pattern}{bits}'
    # A grey scene (R = G = B at every pixel, as on the marker): the mosaic is its grey image
    # exactly, at full resolution, where every interpolating algorithm blurs its edges.
    grey = rng.integers(0, 256, (8, 10), dtype=np.uint8)
    msg = _msg(**rgb_to_image_fields(np.repeat(grey[..., None], 3, axis=2), name))
    np.testing.assert_array_equal(image_to_gray(msg, 'mosaic'), grey)
    assert not np.array_equal(image_to_gray(msg, 'vng'), grey)
    # A colour scene: the photosites as they are (the pattern's checkerboard), 16 bits reduced
    # to their high byte; colour output is VNG's.
    rgb = rng.integers(0, 256, (8, 10, 3), dtype=np.uint8)
    msg = _msg(**rgb_to_image_fields(rgb, name))
    np.testing.assert_array_equal(image_to_gray(msg, 'mosaic'), _ros_mosaic(rgb, pattern))
    np.testing.assert_array_equal(image_to_array(msg, 'rgb8', 'mosaic'), image_to_array(msg, 'rgb8', 'vng'))


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
def test_a_white_sheet_gives_the_gains_that_balance_an_unbalanced_sensor(pattern: str) -> None:
    # A sensor whose red sites see 0.5 and blue sites 0.8 of the green sites' response.
    response = np.array([0.5, 1.0, 0.8])
    name = f'bayer_{pattern}8'
    white = np.full((6, 8, 3), 200.0)
    sheet = _ros_mosaic(np.rint(white * response).astype(np.uint8), pattern)
    gains = mosaic_gains(sheet, name)
    np.testing.assert_allclose(gains, 1.0 / response, rtol=1e-12)
    grey = np.random.default_rng(5).integers(0, 256, (6, 8)).astype(float)
    raw = _ros_mosaic(np.rint(grey[..., None] * response).astype(np.uint8), pattern)
    # Balanced, the grey scene comes back to within the rounding of the raw values (a gain of 2
    # doubles it: one grey level).
    assert np.abs(balance_mosaic(raw, name, gains).astype(int) - grey).max() <= 1
    assert np.abs(raw.astype(int) - grey).max() > 50
    assert message_encoding(_msg(**array_to_image_fields(raw, name))) == name
    assert message_encoding(SimpleNamespace(format='bayer_rggb8; png compressed ', data=b'')) == 'bayer_rggb8'


def test_balance_refuses_what_it_cannot_balance() -> None:
    grey = np.full((4, 4), 100, np.uint8)
    with pytest.raises(ImageConversionError, match='not a Bayer encoding'):
        balance_mosaic(grey, 'rgb8', (1.0, 1.0, 1.0))
    with pytest.raises(ImageConversionError, match=r'gains: .*got \[1.0, 0.0, 1.0\]'):
        balance_mosaic(grey, 'bayer_rggb8', (1.0, 0.0, 1.0))
    with pytest.raises(ImageConversionError, match='the red sites average 0.0'):
        mosaic_gains(_ros_mosaic(np.dstack([np.zeros((4, 4)), grey, grey]).astype(np.uint8), 'rggb'), 'bayer_rggb8')
    assert balance_mosaic(np.full((3, 3), 200, np.uint8), 'bayer_rggb8', (2.0, 1.0, 1.0)).max() == 255


def test_mosaic_leaves_other_encodings_alone() -> None:
    rgb = np.random.default_rng(4).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    for name in ('rgb8', 'mono16', 'yuyv'):
        msg = _msg(**rgb_to_image_fields(rgb, name))
        np.testing.assert_array_equal(image_to_gray(msg, 'mosaic'), image_to_gray(msg), err_msg=name)


@pytest.mark.parametrize('name, first', [('uyvy', 'chroma'), ('yuv422', 'chroma'), ('yuyv', 'luma'),
                                         ('yuv422_yuy2', 'luma')])
def test_yuv422_byte_orders(name: str, first: str) -> None:
    white = np.full((2, 4, 3), 255, np.uint8)
    data = np.frombuffer(rgb_to_image_fields(white, name)['data'], np.uint8)
    # BT.601 studio range: white is Y 235, U = V = 128; UYVY starts with U, YUYV with Y.
    luma, chroma = (data[1::2], data[0::2]) if first == 'chroma' else (data[0::2], data[1::2])
    assert set(luma.tolist()) == {235} and set(chroma.tolist()) == {128}
    colour = np.broadcast_to(np.array([200, 90, 30], np.uint8), (4, 6, 3)).copy()
    back = image_to_array(_msg(**rgb_to_image_fields(colour, name)), 'rgb8')
    assert np.abs(back.astype(int) - colour).max() <= 2


def test_16_bit_byte_order_and_high_byte() -> None:
    values = np.array([[0x0102, 0xFFFF], [0x8000, 0x00FF]], np.uint16)
    little = array_to_image_fields(values, 'mono16')
    big = array_to_image_fields(values, 'mono16', bigendian=True)
    assert big['is_bigendian'] == 1 and big['data'][:2] == b'\x01\x02' and little['data'][:2] == b'\x02\x01'
    for fields in (little, big):
        np.testing.assert_array_equal(image_to_array(_msg(**fields)), values)
        np.testing.assert_array_equal(image_to_gray(_msg(**fields)), [[1, 255], [128, 0]])
    # An 8-bit image stored as 16 bits (v * 257) comes back exactly.
    rgb = np.random.default_rng(3).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    for name in ('rgb16', 'bgra16', 'mono16'):
        out = image_to_array(_msg(**rgb_to_image_fields(rgb, name, bigendian=True)), 'rgb8')
        want = image_to_array(_msg(**rgb_to_image_fields(rgb, name.replace('16', '8'))), 'rgb8')
        np.testing.assert_array_equal(out, want)


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
    # Every lossless encoding of the same picture gives the same grey image.
    gray = image_to_gray(msg)
    for name in ('bgr8', 'rgba8', 'bgra8', 'mono8', 'rgb16', 'bgra16', 'mono16'):
        np.testing.assert_array_equal(image_to_gray(_msg(**rgb_to_image_fields(rgb, name))), gray, err_msg=name)


@pytest.mark.parametrize('name', ['rgb8', 'mono16', 'yuyv', 'bayer_gbrg16'])
def test_padded_rows_and_other_buffers(name: str) -> None:
    arr = _random_layout(name)
    fields = array_to_image_fields(arr, name, step=array_to_image_fields(arr, name)['step'] + 6)
    h, step = fields['height'], fields['step']
    padded = np.frombuffer(fields['data'], np.uint8)
    for data in (fields['data'], array.array('B', fields['data']), list(fields['data']), padded.copy()):
        out = image_to_array(_msg(**{**fields, 'data': data}))
        np.testing.assert_array_equal(out, arr)
        assert out.flags['C_CONTIGUOUS']
    # The result never aliases the message's buffer (a later message reuse must not change it).
    buf = padded.copy()
    out = image_to_array(_msg(**{**fields, 'data': buf}))
    buf[:] = 0
    np.testing.assert_array_equal(out, arr)
    assert buf.size == h * step


@pytest.mark.parametrize('change, field', [
    ({'encoding': '32FC1'}, 'encoding'),          # depth, not a camera image
    ({'encoding': '8UC3'}, 'encoding'),           # no channel meaning
    ({'encoding': 'nv21'}, 'encoding'),
    ({'encoding': None}, 'encoding'),
    ({'step': 20}, 'step'),
    ({'data': b'\x00' * 10}, 'data'),
    ({'height': 0, 'data': b''}, 'height/width'),
    ({'width': -3}, 'height/width'),
    ({'height': 5.0}, 'height'),
    ({'data': [1, 2, 300]}, 'data'),
])
def test_bad_fields_raise_clear_error(change: dict, field: str, rgb: np.ndarray) -> None:
    fields = array_to_image_fields(rgb, 'rgb8')
    fields.update(change)
    with pytest.raises(ImageConversionError, match=field) as err:
        image_to_array(_msg(**fields))
    assert err.value.field == field
    if field == 'encoding' and change['encoding']:
        assert repr(change['encoding']) in str(err.value) and 'bayer_rggb8' in str(err.value)


def test_missing_field_odd_yuv_width_and_bad_arrays() -> None:
    with pytest.raises(ImageConversionError, match='step'):
        image_to_array(SimpleNamespace(height=1, width=1, encoding='mono8', data=b'\x00'))
    with pytest.raises(ImageConversionError, match='is_bigendian'):
        image_to_array(SimpleNamespace(height=1, width=1, encoding='mono16', step=2, data=b'\x00\x00'))
    with pytest.raises(ImageConversionError, match='width'):
        image_to_array(_msg(height=1, width=3, encoding='uyvy', is_bigendian=0, step=6, data=bytes(6)))
    with pytest.raises(ImageConversionError, match='shape'):
        array_to_image_fields(np.zeros((4, 4), np.uint8), 'rgb8')
    with pytest.raises(ImageConversionError, match='dtype'):
        array_to_image_fields(np.zeros((4, 4, 3), np.float32), 'rgb8')
    with pytest.raises(ImageConversionError, match='dtype'):
        array_to_image_fields(np.zeros((4, 4), np.uint8), 'mono16')
    with pytest.raises(ImageConversionError, match='desired_encoding'):
        image_to_array(_msg(**array_to_image_fields(np.zeros((2, 2), np.uint8), 'mono8')), 'rgba8')
    assert issubclass(ImageConversionError, ValueError)


def test_real_image_message(rgb: np.ndarray) -> None:
    from sensor_msgs.msg import Image

    msg = Image()
    for k, v in rgb_to_image_fields(rgb, 'bayer_rggb16', bigendian=True).items():
        setattr(msg, k, v)
    np.testing.assert_array_equal(image_to_array(msg, 'mono8'),
                                  cv2.cvtColor(_ros_mosaic(rgb, 'rggb'), cv2.COLOR_BayerRGGB2GRAY))


# ----------------------------------------------------------------------------------------------
# Compressed


@pytest.fixture
def picture() -> np.ndarray:
    """A smooth colour picture (JPEG's errors on random noise would say nothing)."""
    y, x = np.mgrid[0:48, 0:64]
    return np.stack([4 * x, 5 * y, 255 - 3 * x], axis=-1).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize('name, fmt, want', [
    ('rgb8', 'jpeg', 'rgb8; jpeg compressed bgr8'),
    ('bgra8', 'png', 'bgra8; png compressed bgr8'),
    ('rgb16', 'png', 'rgb16; png compressed bgr16'),
    ('yuyv', 'jpeg', 'yuyv; jpeg compressed bgr8'),
    ('mono8', 'jpeg', 'mono8; jpeg compressed '),
    ('mono16', 'png', 'mono16; png compressed '),
    ('bayer_rggb8', 'png', 'bayer_rggb8; png compressed '),
])
def test_format_strings_are_image_transports(name: str, fmt: str, want: str, picture: np.ndarray) -> None:
    assert compress(encode_rgb(picture, name), name, fmt)['format'] == want


@pytest.mark.parametrize('name', ['rgb8', 'bgr8', 'rgba8', 'mono8', 'mono16', 'rgb16', 'bayer_grbg8', 'bayer_bggr16'])
def test_png_is_lossless_for_every_kind(name: str, picture: np.ndarray) -> None:
    raw = _msg(**rgb_to_image_fields(picture, name))
    packed = _msg(**compress(encode_rgb(picture, name), name, 'png'))
    for desired in ('mono8', 'rgb8', 'bgr8'):
        np.testing.assert_array_equal(compressed_to_array(packed, desired), image_to_array(raw, desired),
                                      err_msg=f'{name} -> {desired}')


def test_jpeg_decodes_close_to_the_original_in_both_channel_orders(picture: np.ndarray) -> None:
    packed = _msg(**compress(picture, 'rgb8', 'jpeg', jpeg_quality=90))
    rgb = compressed_to_array(packed, 'rgb8')
    assert np.abs(rgb.astype(int) - picture).mean() < 2.0
    np.testing.assert_array_equal(compressed_to_array(packed, 'bgr8'), rgb[..., ::-1])
    np.testing.assert_array_equal(compressed_to_array(packed, 'passthrough'), rgb[..., ::-1])   # payload: bgr
    # Grey straight from the JPEG (no colour conversion) is the luma of the decoded colour.
    gray = compressed_to_array(packed, 'mono8')
    assert np.abs(gray.astype(int) - cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)).max() <= 2
    # A publisher that compressed RGB as it was says so ("compressed rgb8"); a bare "jpeg" is BGR.
    ok, data = cv2.imencode('.jpg', picture, [cv2.IMWRITE_JPEG_QUALITY, 90])     # RGB bytes as if BGR
    as_stored = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)                          # the RGB picture again
    assert np.abs(as_stored.astype(int) - picture).mean() < 2.0
    np.testing.assert_array_equal(compressed_to_array(_msg(format='rgb8; jpeg compressed rgb8', data=data.tobytes()),
                                                      'rgb8'), as_stored)
    np.testing.assert_array_equal(compressed_to_array(_msg(format='jpeg', data=data.tobytes()), 'bgr8'), as_stored)


def test_parse_compressed_format() -> None:
    assert parse_compressed_format('rgb8; jpeg compressed bgr8') == ('rgb8', 'jpeg', 'bgr')
    assert parse_compressed_format('mono8; png compressed ') == ('mono8', 'png', '')
    assert parse_compressed_format(' PNG ') == ('', 'png', '')
    assert parse_compressed_format('jpg') == ('', 'jpeg', '')
    for bad in ('16UC1; compressedDepth png', 'rgb8; tiff compressed bgr8', 'h264'):
        with pytest.raises(ImageConversionError, match='format'):
            parse_compressed_format(bad)


def test_bad_compressed_messages_raise_clear_errors(picture: np.ndarray) -> None:
    with pytest.raises(ImageConversionError, match='data'):
        compressed_to_array(_msg(format='jpeg', data=b''))
    with pytest.raises(ImageConversionError, match='data'):
        compressed_to_array(_msg(format='rgb8; jpeg compressed bgr8', data=b'\xff\xd8 not a jpeg'))
    with pytest.raises(ImageConversionError, match='format'):
        compressed_to_array(_msg(format='32FC1; png compressed ', data=b'x'))
    packed = compress(picture, 'rgb8', 'png')
    with pytest.raises(ImageConversionError, match='format'):       # a colour payload for a mono source
        compressed_to_array(_msg(format='mono8; png compressed ', data=packed['data']), 'mono8')
    with pytest.raises(ImageConversionError, match='encoding'):
        compress(encode_rgb(picture, 'mono16'), 'mono16', 'jpeg')
    with pytest.raises(ImageConversionError, match='format'):
        compress(picture, 'rgb8', 'webp')


def test_either_message_type(picture: np.ndarray) -> None:
    from sensor_msgs.msg import CompressedImage, Image

    img = Image()
    for k, v in rgb_to_image_fields(picture, 'yuyv').items():
        setattr(img, k, v)
    comp = CompressedImage()
    for k, v in compress(picture, 'rgb8', 'png').items():
        setattr(comp, k, v)
    np.testing.assert_array_equal(message_to_gray(img), image_to_gray(img))
    np.testing.assert_array_equal(message_to_array(comp, 'rgb8'), picture)
    assert message_to_gray(comp).shape == picture.shape[:2]
