"""Synthetic marker images from a known camera and marker pose (tests, docs; pure).

A marker (with a white quiet zone) is rendered by a homography: its canvas corners are projected
with ``cv2.projectPoints`` and the canvas is warped with ``cv2.warpPerspective``. Rendering is
supersampled and area-averaged so edges are anti-aliased like a real sensor's, and seeded
Gaussian noise can be added.
"""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema.markers import aruco_dictionary

__all__ = ['look_at_pose', 'render_markers']


def look_at_pose(distance: float, tilt_deg: float, axis: ArrayLike = (0.0, 1.0, 0.0),
                 offset: ArrayLike = (0.0, 0.0), spin_deg: float = 0.0) -> NDArray[np.float64]:
    """A marker pose in the camera frame, facing the camera then tilted.

    Parameters
    ----------
    distance : float
        Distance of the marker centre along the optical axis [m].
    tilt_deg : float
        Rotation about ``axis`` (in the marker frame) away from head-on [deg]; this is the
        viewing angle phi for a centred marker.
    axis : array_like, shape (3,)
    offset : array_like, shape (2,)
        Lateral offset (x, y) of the marker centre in the camera frame [m].
    spin_deg : float
        Rotation about the marker normal before tilting [deg].

    Returns
    -------
    ndarray, shape (4, 4)
        ``cam_T_marker`` (z of the marker points back toward the camera).
    """
    from scipy.spatial.transform import Rotation

    facing = Rotation.from_euler('x', 180, degrees=True)          # marker z toward the camera
    ax = np.asarray(axis, dtype=float)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * ax / np.linalg.norm(ax))
    spin = Rotation.from_euler('z', spin_deg, degrees=True)
    t = np.eye(4)
    t[:3, :3] = (facing * tilt * spin).as_matrix()
    t[:3, 3] = [offset[0], offset[1], distance]
    return t


def render_markers(k: ArrayLike, size: tuple[int, int], markers: Sequence[tuple[int, NDArray[np.float64]]],
                   side: float, dictionary: str = 'DICT_4X4_50', background: int = 128,
                   noise_sigma: float = 0.0, seed: int = 0, supersample: int = 4,
                   quiet_zone: float = 0.25) -> NDArray[np.uint8]:
    """Render markers into a grey image.

    Parameters
    ----------
    k : array_like, shape (3, 3)
        Camera matrix (no distortion).
    size : (width, height)
    markers : sequence of (marker_id, cam_T_marker (4, 4))
    side : float
        Black-square side length [m].
    background : int
        Grey level of the scene.
    noise_sigma : float
        Standard deviation of additive Gaussian pixel noise (grey levels).
    seed : int
        Seeds the noise.
    supersample : int
        Render at this many times the resolution, then area-average down.
    quiet_zone : float
        White margin around the black square, as a fraction of ``side``.

    Returns
    -------
    ndarray, uint8, shape (height, width)
    """
    width, height = size
    s = int(supersample)
    k = np.asarray(k, dtype=float)
    # Same field of view at s times the pixels (pixel-centre convention: c' = (c + 0.5) s - 0.5).
    ks = k.copy()
    ks[0, 0] *= s
    ks[1, 1] *= s
    ks[0, 2] = (k[0, 2] + 0.5) * s - 0.5
    ks[1, 2] = (k[1, 2] + 0.5) * s - 0.5
    big = np.full((height * s, width * s), background, np.uint8)
    aruco = aruco_dictionary(dictionary)
    n_px = 240                                   # canvas resolution of the black square
    margin = int(round(quiet_zone * n_px))
    for marker_id, pose in markers:
        img = cv2.aruco.generateImageMarker(aruco, int(marker_id), n_px)
        canvas = cv2.copyMakeBorder(img, margin, margin, margin, margin, cv2.BORDER_CONSTANT,
                                    value=255)
        full = n_px + 2 * margin
        # Canvas pixel edges (-0.5 .. full - 0.5) <-> marker-frame coordinates.
        half = side / 2.0 * full / n_px
        obj = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]])
        pose = np.asarray(pose, dtype=float)
        rvec = cv2.Rodrigues(pose[:3, :3])[0]
        proj, _ = cv2.projectPoints(obj, rvec, pose[:3, 3], ks, np.zeros(5))
        src = np.array([[-0.5, -0.5], [full - 0.5, -0.5], [full - 0.5, full - 0.5], [-0.5, full - 0.5]],
                       np.float32)
        h = cv2.getPerspectiveTransform(src, proj.reshape(4, 2).astype(np.float32))
        warped = cv2.warpPerspective(canvas, h, (width * s, height * s), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = cv2.warpPerspective(np.full_like(canvas, 255), h, (width * s, height * s),
                                   flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                   borderValue=0)
        big = np.where(mask > 0, warped, big)
    out = cv2.resize(big, (width, height), interpolation=cv2.INTER_AREA).astype(float)
    if noise_sigma > 0:
        out += np.random.default_rng(seed).normal(0.0, noise_sigma, out.shape)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
