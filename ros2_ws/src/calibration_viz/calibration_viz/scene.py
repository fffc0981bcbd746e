"""What the live view draws, computed from the calibration's data (pure: no rclpy, no viser).

:class:`SceneState` keeps the latest of everything the view shows and turns it into geometry:
the joint origins of the real and the estimated arm (:func:`arm_points`), the observed hand
positions with their covariance ellipsoids (:func:`covariance_ellipsoid`), the cameras, and the
error of each estimate against the real arm (:class:`ErrorCurve`, the paper's metric on fewer
configurations so that it keeps up).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema.kinematics import chain_frames
from body_schema.metrics import PoseErrorEvaluator
from body_schema.robot import ArmModel, CameraIntrinsics

__all__ = ['arm_points', 'covariance_ellipsoid', 'ErrorCurve', 'Observation', 'CameraView', 'SceneState']


def arm_points(model: ArmModel, dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """The chain drawn as a polyline: root, base, each DH frame's origin, the hand.

    Returns
    -------
    ndarray, shape (L + 2, 3)
        Points in the root frame [m].
    """
    frames = chain_frames(model.base, dh, q)
    return np.vstack([np.zeros((1, 3)), frames[:, :3, 3]])


def covariance_ellipsoid(cov: ArrayLike, n_sigma: float = 3.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Axes of the position uncertainty of a ``PoseWithCovariance``.

    Parameters
    ----------
    cov : array_like, shape (6, 6) or (36,)
        Row-major, position block first (x, y, z, then rotation), as ROS stores it [m^2].
    n_sigma : float
        Radius in standard deviations.

    Returns
    -------
    radii : ndarray, shape (3,)
        Semi-axes [m].
    rotation : ndarray, shape (3, 3)
        Columns are the axes (a proper rotation).

    Raises
    ------
    ValueError
        If the position block is not finite.
    """
    c = np.asarray(cov, dtype=float).reshape(6, 6)[:3, :3]
    if not np.all(np.isfinite(c)):
        raise ValueError(f'position covariance is not finite: {c.tolist()}')
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    if np.linalg.det(v) < 0:
        v[:, 0] = -v[:, 0]
    return n_sigma * np.sqrt(np.clip(w, 0.0, None)), v


class ErrorCurve:
    """Average hand position [mm] and orientation [deg] error of each estimate vs the real arm.

    Parameters
    ----------
    model : ArmModel
        Base and calibration box (where the configurations are drawn).
    n_configs : int
        Configurations scored (the paper's 1000 in the offline evaluation; fewer here).
    """

    def __init__(self, model: ArmModel, n_configs: int = 200) -> None:
        self.model, self.n_configs = model, n_configs
        self._evaluator: PoseErrorEvaluator | None = None
        self.position_mm: list[float] = []
        self.orientation_deg: list[float] = []

    def set_true(self, dh: ArrayLike) -> None:
        """The real arm (L, 4): later estimates are scored against it."""
        self._evaluator = PoseErrorEvaluator(self.model.base, dh, self.model.calibration_box, self.n_configs)

    def add(self, dh: ArrayLike) -> bool:
        """Score an estimate (L, 4); False (nothing added) before the real arm is known."""
        if self._evaluator is None:
            return False
        e = self._evaluator(dh)
        self.position_mm.append(e.position_mm)
        self.orientation_deg.append(e.orientation_deg)
        return True


@dataclass
class Observation:
    """An observed hand pose: ``root_T_hand`` (4, 4) and its 6 x 6 covariance."""

    root_T_hand: NDArray[np.float64]
    covariance: NDArray[np.float64]


@dataclass
class CameraView:
    """A camera: ``root_T_optical`` (4, 4), intrinsics, the latest image (H, W, 3) uint8 or None."""

    root_T_optical: NDArray[np.float64] | None = None
    intrinsics: CameraIntrinsics | None = None
    image: NDArray[np.uint8] | None = None


@dataclass
class SceneState:
    """The latest of everything the view shows; ``version`` counts changes (redraw when it moved).

    Parameters
    ----------
    model : ArmModel
    history : int
        Observations kept (the oldest drop out).
    n_configs : int
        Configurations of the error curve.
    """

    model: ArmModel
    history: int = 50
    n_configs: int = 200
    q: NDArray[np.float64] | None = None
    true_dh: NDArray[np.float64] | None = None
    estimate_dh: NDArray[np.float64] | None = None
    cameras: dict[str, CameraView] = field(default_factory=dict)
    version: int = 0

    def __post_init__(self) -> None:
        self.observations: deque[Observation] = deque(maxlen=self.history)
        self.errors = ErrorCurve(self.model, self.n_configs)
        self._pending_estimate: NDArray[np.float64] | None = None

    def _changed(self) -> None:
        self.version += 1

    def set_joints(self, q: ArrayLike) -> None:
        """Joint positions (L,) [rad]."""
        self.q = np.asarray(q, dtype=float)
        self._changed()

    def set_true(self, dh: ArrayLike) -> None:
        """The real arm's table (L, 4); an estimate that came first is scored now."""
        self.true_dh = np.asarray(dh, dtype=float).reshape(self.model.dh.shape)
        self.errors.set_true(self.true_dh)
        if self._pending_estimate is not None:
            self.errors.add(self._pending_estimate)
            self._pending_estimate = None
        self._changed()

    def set_estimate(self, dh: ArrayLike) -> None:
        """A new estimate (L, 4): drawn, and scored on the error curve."""
        self.estimate_dh = np.asarray(dh, dtype=float).reshape(self.model.dh.shape)
        if not self.errors.add(self.estimate_dh):
            self._pending_estimate = self.estimate_dh
        self._changed()

    def add_observation(self, root_T_hand: ArrayLike, covariance: ArrayLike) -> None:
        """An observed hand pose (4, 4) with its covariance (6, 6)."""
        self.observations.append(Observation(np.asarray(root_T_hand, dtype=float),
                                             np.asarray(covariance, dtype=float).reshape(6, 6)))
        self._changed()

    def camera(self, eye: str) -> CameraView:
        """The camera ``eye`` (created empty on first use)."""
        return self.cameras.setdefault(eye, CameraView())

    def set_camera_pose(self, eye: str, root_T_optical: ArrayLike) -> None:
        self.camera(eye).root_T_optical = np.asarray(root_T_optical, dtype=float)
        self._changed()

    def set_camera_intrinsics(self, eye: str, intrinsics: CameraIntrinsics) -> None:
        if self.camera(eye).intrinsics != intrinsics:
            self.camera(eye).intrinsics = intrinsics
            self._changed()

    def set_image(self, eye: str, rgb: NDArray[np.uint8]) -> None:
        """The latest image (H, W, 3) of ``eye``."""
        self.camera(eye).image = rgb
        self._changed()

    def real_arm(self) -> NDArray[np.float64] | None:
        """Polyline (L + 2, 3) of the real arm, or None before joints are known."""
        if self.q is None:
            return None
        return arm_points(self.model, self.model.dh if self.true_dh is None else self.true_dh, self.q)

    def estimated_arm(self) -> NDArray[np.float64] | None:
        """Polyline (L + 2, 3) of the estimated arm at the same joints, or None."""
        if self.q is None or self.estimate_dh is None:
            return None
        return arm_points(self.model, self.estimate_dh, self.q)
