"""The live view node in-process (its web server stops with the node): a camera's image in any encoding, or on the compressed
transport, reaches the frustum as rgb8; an image it cannot convert is named once and not shown."""
from __future__ import annotations

import socket
from typing import Any

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import CompressedImage, Image

from calibration_interfaces.image_conversion import compress, image_to_array, rgb_to_image_fields
from calibration_interfaces.node_util import qos_profile
from calibration_viz.viz_node import VizNode


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture
def picture() -> np.ndarray:
    y, x = np.mgrid[0:24, 0:32]
    return np.stack([8 * x, 10 * y, 255 - 6 * x], axis=-1).clip(0, 255).astype(np.uint8)


def _viz(ros: Any, transport: str) -> VizNode:
    node = VizNode(context=ros.context, parameter_overrides=[
        Parameter('port', value=_free_port()), Parameter('cameras', value=['left']),
        Parameter('image_rate', value=30.0), Parameter('transport', value=transport)])
    return ros.add(node)


@pytest.mark.parametrize('transport, encoding', [('raw', 'bayer_gbrg8'), ('raw', 'yuv422_yuy2'),
                                                 ('compressed', 'bgra8')])
def test_images_of_any_encoding_or_transport_are_shown(ros: Any, picture: np.ndarray, transport: str,
                                                       encoding: str) -> None:
    viz = _viz(ros, transport)
    cam = ros.node('camera')
    topic = '/camera/left/image_raw' + ('' if transport == 'raw' else '/compressed')
    pub = cam.create_publisher(Image if transport == 'raw' else CompressedImage, topic, qos_profile(topic))
    msg = Image() if transport == 'raw' else CompressedImage()
    fields = rgb_to_image_fields(picture, encoding)
    want = image_to_array(Image(**fields), 'rgb8')
    if transport == 'compressed':
        fields = compress(image_to_array(Image(**fields)), encoding, 'png')
    for k, v in fields.items():
        setattr(msg, k, v)
    ros.spin_until(lambda: (pub.publish(msg), viz.state.camera('left').image is not None)[1], 10.0, 'image shown')
    np.testing.assert_array_equal(viz.state.camera('left').image, want)


def test_an_image_it_cannot_convert_is_named_and_not_shown(ros: Any, monkeypatch) -> None:
    viz = _viz(ros, 'raw')
    warned: list[str] = []
    monkeypatch.setattr(viz, '_warn', lambda key, text: warned.append(text))
    pub = ros.node('camera').create_publisher(Image, '/camera/left/image_raw', qos_profile('/camera/left/image_raw'))
    bad = Image(height=2, width=2, encoding='32FC1', step=8, data=bytes(16))
    ros.spin_until(lambda: (pub.publish(bad), bool(warned))[1], 10.0, 'a warning')
    assert "'32FC1'" in warned[0] and '/camera/left/image_raw' in warned[0]
    assert viz.state.camera('left').image is None
