"""Pinhole camera <-> OpenGL matrices for PyBullet's TinyRenderer, and image degradations.

Conventions. OpenCV pixel coordinates ``(u, v)`` put the centre of pixel ``(i, j)`` at
``u = i, v = j``; the optical frame has z forward, x right, y down. OpenGL's camera looks down
-z with y up, so ``cam_T_gl = diag(1, -1, -1, 1)``.

TinyRenderer samples coverage at integer window coordinates rather than at pixel centres, and
PyBullet flips the rows on readout. Measured (see ``test_world.py``): with the textbook
pixel-centre projection, column ``i`` shows the ray through ``u = i - 0.5`` and row ``j`` the ray
through ``v = j + 0.5``. :func:`gl_projection` compensates, so that pixel ``(i, j)`` shows exactly
the ray that ``K`` maps to ``(i, j)`` and the published CameraInfo holds for the image.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['CV_T_GL', 'RASTER_OFFSET', 'gl_projection', 'gl_view', 'to_gl_list', 'project_points',
           'degrade']

#: Optical frame (z forward, y down) -> OpenGL camera frame (looks down -z, y up).
CV_T_GL = np.diag([1.0, -1.0, -1.0, 1.0])

#: Ray offsets (du, dv) [px] TinyRenderer adds to the pixel-centre convention (measured).
RASTER_OFFSET = (-0.5, 0.5)


def gl_projection(K: ArrayLike, width: int, height: int, near: float = 0.01,
                  far: float = 10.0) -> NDArray[np.float64]:
    """OpenGL projection matrix reproducing the pinhole ``K`` in TinyRenderer images.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Camera matrix (no skew).
    width, height : int
        Image size [px].
    near, far : float
        Clipping planes [m], ``0 < near < far``.

    Returns
    -------
    ndarray, shape (4, 4)
        Row-major matrix (use :func:`to_gl_list` for PyBullet).
    """
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or K[0, 1] != 0:
        raise ValueError(f'K must be a 3x3 camera matrix without skew, got {K.tolist()}')
    if not 0 < near < far:
        raise ValueError(f'need 0 < near < far, got near={near}, far={far}')
    fx, fy = K[0, 0], K[1, 1]
    # Principal point as TinyRenderer must see it so that its samples land on pixel centres.
    cx, cy = K[0, 2] + RASTER_OFFSET[0], K[1, 2] + RASTER_OFFSET[1]
    p = np.zeros((4, 4))
    p[0, 0] = 2.0 * fx / width
    p[0, 2] = 1.0 - (2.0 * cx + 1.0) / width      # pixel-centre convention: window x = u + 1/2
    p[1, 1] = 2.0 * fy / height
    p[1, 2] = (2.0 * cy + 1.0) / height - 1.0     # image rows go down, window y goes up
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def gl_view(root_T_cam: ArrayLike) -> NDArray[np.float64]:
    """OpenGL view matrix for an optical frame posed in the world.

    Parameters
    ----------
    root_T_cam : array_like, shape (4, 4)
        Optical frame (z forward, x right, y down) in the world (root_link) frame.

    Returns
    -------
    ndarray, shape (4, 4)
        World -> OpenGL camera transform, row-major.
    """
    t = np.asarray(root_T_cam, dtype=float)
    if t.shape != (4, 4):
        raise ValueError(f'camera pose must be 4x4, got {t.shape}')
    return np.linalg.inv(t @ CV_T_GL)


def to_gl_list(m: NDArray[np.float64]) -> list[float]:
    """A 4x4 matrix as the 16 column-major floats PyBullet expects."""
    return np.asarray(m, dtype=float).T.reshape(16).tolist()


def project_points(points: ArrayLike, root_T_cam: ArrayLike, K: ArrayLike) -> NDArray[np.float64]:
    """Pinhole projection of world points, no distortion.

    Parameters
    ----------
    points : array_like, shape (N, 3)
    root_T_cam : array_like, shape (4, 4)
    K : array_like, shape (3, 3)

    Returns
    -------
    ndarray, shape (N, 2)
        Pixel coordinates (OpenCV convention); NaN for points behind the camera.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    cam_T_root = np.linalg.inv(np.asarray(root_T_cam, dtype=float))
    pc = pts @ cam_T_root[:3, :3].T + cam_T_root[:3, 3]
    uvw = pc @ np.asarray(K, dtype=float).T
    with np.errstate(divide='ignore', invalid='ignore'):
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[pc[:, 2] <= 0] = np.nan
    return uv


def degrade(image: NDArray[np.uint8], noise_std: float = 0.0, blur_sigma: float = 0.0,
            rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
    """Optional Gaussian blur then additive Gaussian pixel noise.

    Parameters
    ----------
    image : ndarray, shape (H, W, 3), uint8
    noise_std : float
        Standard deviation of the additive noise [grey levels]; 0 disables it.
    blur_sigma : float
        Gaussian blur sigma [px]; 0 disables it.
    rng : numpy Generator, optional
        Source of the noise (seed it for reproducible images).

    Returns
    -------
    ndarray, shape (H, W, 3), uint8
    """
    if noise_std < 0 or blur_sigma < 0 or not (np.isfinite(noise_std) and np.isfinite(blur_sigma)):
        raise ValueError(f'noise_std and blur_sigma must be finite and >= 0, got {noise_std}, {blur_sigma}')
    out = image
    if blur_sigma > 0:
        import cv2

        out = cv2.GaussianBlur(out, (0, 0), blur_sigma)
    if noise_std > 0:
        rng = rng if rng is not None else np.random.default_rng()
        noisy = out.astype(np.float32) + rng.normal(0.0, noise_std, out.shape).astype(np.float32)
        out = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    return out
