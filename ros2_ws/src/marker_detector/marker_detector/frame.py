"""One camera frame judged: detected, no marker, or bad input (pure; no rclpy).

The node hands every image with its eye's latest camera calibration to :func:`judge_frame`; the
:class:`~marker_detector.detection.FrameResult` it returns says which of the three it was
(:attr:`~marker_detector.detection.FrameResult.status`). Only a valid image with a valid
calibration can be "no marker": a frame that cannot be decoded, does not match its camera_info,
or comes with a camera_info that cannot be used (NaN or zero K, NaN distortion, no size) is
``bad_input`` and carries the reason, so nobody downstream mistakes it for a hidden hand.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration_interfaces.image_conversion import (ImageConversionError, balance_mosaic, message_encoding,
                                                     message_to_gray)

from .detection import BadInput, FrameResult, HandPoseEstimator

__all__ = ['DISTORTION_MODELS', 'CameraCalibration', 'calibration_from_info', 'judge_frame']

#: Distortion models whose coefficients OpenCV applies as they are.
DISTORTION_MODELS = ('plumb_bob', 'rational_polynomial')


@dataclass(frozen=True)
class CameraCalibration:
    """A usable camera calibration.

    Attributes
    ----------
    k : ndarray, shape (3, 3)
        Camera matrix (finite, positive focal lengths).
    dist : ndarray, shape (N,)
        Distortion coefficients (finite; five zeros when the camera_info has none).
    size : (int, int) or None
        Image width and height [px]; None when the camera_info leaves them 0 (not checked).
    """

    k: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int] | None


def calibration_from_info(k: Sequence[float], d: Sequence[float], width: int, height: int) -> CameraCalibration:
    """The calibration a ``sensor_msgs/CameraInfo`` describes.

    Parameters
    ----------
    k : sequence of 9 float
        Row-major camera matrix.
    d : sequence of float
        Distortion coefficients (may be empty).
    width, height : int
        Image size [px]; both 0 means unknown.

    Raises
    ------
    BadInput
        ``camera_info.K`` (not 9 finite values with positive focal lengths), ``camera_info.D``
        (a non-finite coefficient) or ``camera_info.size`` (one side 0, or absurd).
    """
    kk = np.asarray(k, dtype=float).reshape(-1)
    if kk.size != 9 or not np.all(np.isfinite(kk)) or kk[0] <= 0 or kk[4] <= 0:
        raise BadInput('camera_info.K', f'expected 9 finite values with positive focal lengths, got {kk.tolist()}')
    dist = np.asarray(d, dtype=float).reshape(-1)
    if not np.all(np.isfinite(dist)):
        raise BadInput('camera_info.D', f'distortion coefficients must be finite, got {dist.tolist()}')
    w, h = int(width), int(height)
    if (w, h) != (0, 0) and not (0 < w <= 1 << 15 and 0 < h <= 1 << 15):
        raise BadInput('camera_info.size', f'width x height must be positive (or both 0), got {w} x {h}')
    return CameraCalibration(kk.reshape(3, 3), dist if dist.size else np.zeros(5), None if (w, h) == (0, 0) else (w, h))


def judge_frame(estimator: HandPoseEstimator, image: Any, calibration: CameraCalibration | BadInput,
                root_T_cam: NDArray[np.float64] | None, demosaicing: str = 'bilinear',
                bayer_gains: Sequence[float] = (1.0, 1.0, 1.0)) -> FrameResult:
    """Detect the hand in one image, or say why the image cannot be judged.

    Parameters
    ----------
    estimator : HandPoseEstimator
    image : sensor_msgs/Image or CompressedImage, or any object with their fields (see
        :mod:`calibration_interfaces.image_conversion`)
    calibration : CameraCalibration or BadInput
        The eye's latest camera_info: usable, or why it is not (a missing one included).
    root_T_cam : ndarray, shape (4, 4), or None
        Camera pose in the root frame; None gives the hand in the camera frame.
    demosaicing : {'bilinear', 'edge_aware', 'vng', 'mosaic'}
        For a Bayer image (:data:`calibration_interfaces.image_conversion.DEMOSAICING`).
    bayer_gains : sequence of 3 float
        With ``mosaic``: the red, green and blue sites' white-balance gains
        (:func:`~calibration_interfaces.image_conversion.balance_mosaic`); all 1 leaves them as sent.

    Returns
    -------
    FrameResult
        ``status`` ``detected`` or ``no_marker`` for a valid frame; ``bad_input`` with the reason
        (:class:`~marker_detector.detection.BadInput`, kind ``image.<field>`` or
        ``camera_info.<field>``) otherwise. OpenCV errors are not caught (the node reports them).
    """
    if isinstance(calibration, BadInput):
        return FrameResult(bad_input=calibration)
    try:
        gray = message_to_gray(image, demosaicing)
        if demosaicing == 'mosaic' and tuple(bayer_gains) != (1.0, 1.0, 1.0):
            encoding = message_encoding(image)
            if encoding.startswith('bayer_'):
                gray = balance_mosaic(gray, encoding, bayer_gains)
    except ImageConversionError as exc:
        return FrameResult(bad_input=BadInput(f'image.{exc.field}', str(exc)))
    if calibration.size is not None and calibration.size != (gray.shape[1], gray.shape[0]):
        return FrameResult(bad_input=BadInput('image.size', f'image is {gray.shape[1]} x {gray.shape[0]} but '
                                              f'camera_info says {calibration.size[0]} x {calibration.size[1]}'))
    try:
        return estimator.process(gray, calibration.k, calibration.dist, root_T_cam)
    except BadInput as exc:
        return FrameResult(bad_input=exc)
