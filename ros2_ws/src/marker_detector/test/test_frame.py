"""A frame is judged detected, no marker, or bad input (pure: duck-typed images, no ROS).

On main every bad input below came out as an empty detection, the same as "hand not visible",
and a NaN distortion raised nothing at all.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from body_schema import load_robot
from body_schema.noise import PoseDependentNoise
from calibration_interfaces.outcome import FrameStatus
from marker_detector.detection import BadInput, HandPoseEstimator
from marker_detector.frame import calibration_from_info, judge_frame
from calibration_interfaces.image_conversion import (array_to_image_fields, message_to_gray, mosaic_gains,
                                                     rgb_to_image_fields)
from marker_detector.synthetic import look_at_pose, render_markers


@pytest.fixture(scope='module')
def model():
    return load_robot('icub_right_arm')


@pytest.fixture(scope='module')
def estimator(model):
    return HandPoseEstimator(model, PoseDependentNoise())


@pytest.fixture(scope='module')
def scene(model):
    """A frame of the palm marker at 0.3 m, 20 deg off axis, and its camera_info fields."""
    cam = model.camera
    gray = render_markers(cam.K, (cam.width, cam.height), [(model.markers[0].marker_id,
                                                           look_at_pose(0.3, 20.0, axis=(1.0, 0.0, 0.0)))],
                          model.marker_side_length, noise_sigma=1.0, seed=3)
    info = dict(k=cam.K.reshape(-1).tolist(), d=[0.0] * 5, width=cam.width, height=cam.height)
    return np.repeat(gray[..., None], 3, axis=2), info


def _image(rgb: np.ndarray, **override) -> SimpleNamespace:
    return SimpleNamespace(**{**array_to_image_fields(rgb, 'rgb8'), **override})


def test_a_valid_frame_is_detected_and_an_empty_one_is_no_marker(estimator, scene) -> None:
    rgb, info = scene
    cal = calibration_from_info(**info)
    assert judge_frame(estimator, _image(rgb), cal, np.eye(4)).status is FrameStatus.DETECTED
    empty = judge_frame(estimator, _image(np.zeros_like(rgb)), cal, np.eye(4))
    assert empty.status is FrameStatus.NO_MARKER and empty.bad_input is None
    noise = np.random.default_rng(0).integers(0, 256, rgb.shape, dtype=np.uint8)
    assert judge_frame(estimator, _image(noise), cal, np.eye(4)).status is FrameStatus.NO_MARKER


@pytest.mark.parametrize('override, kind', [
    (dict(encoding='32FC1'), 'image.encoding'),         # a depth image
    (dict(data=b'\x00' * 100), 'image.data'),                         # truncated payload
    (dict(step=10), 'image.step'),                                     # step shorter than a row
    (dict(height=0, width=0, step=0, data=b''), 'image.height/width'),  # empty message
    (dict(data='not bytes at all'), 'image.data'),                      # garbage payload type
    (dict(width=1.5), 'image.width'),
])
def test_each_bad_image_is_bad_input_with_its_kind(estimator, scene, override, kind) -> None:
    rgb, info = scene
    res = judge_frame(estimator, _image(rgb, **override), calibration_from_info(**info), np.eye(4))
    assert res.status is FrameStatus.BAD_INPUT, res
    assert res.bad_input.kind == kind and res.markers == [] and res.hand is None


def test_an_image_of_another_size_than_its_camera_info_is_bad_input(estimator, scene) -> None:
    rgb, info = scene
    res = judge_frame(estimator, _image(rgb[::2, ::2].copy()), calibration_from_info(**info), np.eye(4))
    assert res.status is FrameStatus.BAD_INPUT and res.bad_input.kind == 'image.size'
    assert '160 x 120' in str(res.bad_input)


@pytest.mark.parametrize('change, kind', [
    (dict(d=[np.nan, 0, 0, 0, 0]), 'camera_info.D'),
    (dict(d=[0, np.inf, 0, 0, 0]), 'camera_info.D'),
    (dict(k=[np.nan] * 9), 'camera_info.K'),
    (dict(k=[0.0] * 9), 'camera_info.K'),                  # zero focal length
    (dict(k=[1.0] * 4), 'camera_info.K'),                  # not 3 x 3
    (dict(width=320, height=0), 'camera_info.size'),
])
def test_each_bad_camera_info_is_refused_and_its_frames_are_bad_input(estimator, scene, change, kind) -> None:
    rgb, info = scene
    with pytest.raises(BadInput) as exc:
        calibration_from_info(**{**info, **change})
    assert exc.value.kind == kind
    res = judge_frame(estimator, _image(rgb), exc.value, np.eye(4))
    assert res.status is FrameStatus.BAD_INPUT and res.bad_input is exc.value


def test_nan_distortion_given_straight_to_the_estimator_is_not_no_marker(estimator, scene) -> None:
    """The estimator itself refuses it: every marker would fail to solve and look hidden."""
    rgb, info = scene
    with pytest.raises(BadInput, match='camera_info.D'):
        estimator.process(rgb[..., 0].copy(), np.reshape(info['k'], (3, 3)), [np.nan, 0, 0, 0, 0])


def test_a_camera_info_without_size_or_distortion_is_usable(estimator, scene) -> None:
    rgb, info = scene
    cal = calibration_from_info(**{**info, 'd': [], 'width': 0, 'height': 0})
    assert cal.size is None and cal.dist.tolist() == [0.0] * 5
    assert judge_frame(estimator, _image(rgb), cal, np.eye(4)).status is FrameStatus.DETECTED


def test_the_white_balance_gains_make_an_unbalanced_bayer_camera_see_the_colour_one(estimator, scene) -> None:
    """With ``mosaic``, a Bayer camera that does not balance its raw data (red sites at 0.45, blue
    at 0.7 of the green's response) detects the marker where a colour camera does once its gains
    are applied, and its hand pose moves less than without them."""
    rgb, info = scene
    cal = calibration_from_info(**info)
    ref = judge_frame(estimator, _image(rgb), cal, np.eye(4)).hand.pose
    response = np.array([0.45, 1.0, 0.7])
    raw = np.rint(rgb * response).astype(np.uint8)
    image = SimpleNamespace(**rgb_to_image_fields(raw, 'bayer_rggb8'))
    white = SimpleNamespace(**rgb_to_image_fields(np.rint(np.full_like(rgb, 220) * response).astype(np.uint8),
                                                  'bayer_rggb8'))
    gains = mosaic_gains(message_to_gray(white, 'mosaic'), 'bayer_rggb8')
    balanced = judge_frame(estimator, image, cal, np.eye(4), 'mosaic', gains)
    assert balanced.status is FrameStatus.DETECTED
    moved = 1e3 * np.linalg.norm(balanced.hand.pose[:3, 3] - ref[:3, 3])
    assert moved < 0.1                                     # [mm]: the rounding of the raw values (0.05 here)
    as_sent = judge_frame(estimator, image, cal, np.eye(4), 'mosaic')
    assert as_sent.hand is None or 1e3 * np.linalg.norm(as_sent.hand.pose[:3, 3] - ref[:3, 3]) > 5 * moved   # 1.4 mm here
    # Gains apply to Bayer images only: an rgb8 frame is judged as without them.
    same = judge_frame(estimator, _image(rgb), cal, np.eye(4), 'mosaic', gains).hand.pose
    np.testing.assert_array_equal(same, ref)
