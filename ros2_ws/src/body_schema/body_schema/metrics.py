"""Evaluation metrics of the paper (sec. IV-C).

* Average position error over N configurations: ``mean ||p_i - p_hat_i||`` [m].
* Average orientation error: ``mean sqrt(||logm(O_i^T O_hat_i)||_F^2 / 2)`` [deg]. For a rotation
  ``logm`` is the skew matrix of the rotation vector, whose Frobenius norm is ``sqrt(2) |w|``, so
  the error is the geodesic angle ``|w|``; it is computed with scipy's ``Rotation``.
* Accumulated joint movement: ``sum_k ||theta_k - theta_{k-1}||_1`` [deg].
* Discarded samples: failed measurement attempts.

The N = 1000 evaluation configurations are drawn uniformly in the calibration box with a fixed
seed (:class:`PoseErrorEvaluator`) so every method and iteration is scored on the same set.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import kinematics
from .sampling import uniform_configs

__all__ = ['orientation_errors_deg', 'PoseErrors', 'PoseErrorEvaluator', 'accumulated_movement_deg',
           'discarded_samples', 'EVAL_CONFIGS', 'EVAL_SEED']

#: The paper's number of evaluation configurations and our fixed seed for them.
EVAL_CONFIGS = 1000
EVAL_SEED = 20240601


def orientation_errors_deg(r_true: ArrayLike, r_est: ArrayLike) -> NDArray[np.float64]:
    """Geodesic angle between rotation matrices, ``sqrt(||logm(O^T O_hat)||_F^2 / 2)`` in degrees.

    Parameters
    ----------
    r_true, r_est : array_like, shape (3, 3) or (N, 3, 3)

    Returns
    -------
    ndarray, shape () or (N,)
    """
    return kinematics.rotation_angle_deg(r_est, r_true)


@dataclass(frozen=True)
class PoseErrors:
    """Average hand-pose errors of an estimated model."""

    position_m: float
    orientation_deg: float

    @property
    def position_mm(self) -> float:
        return 1000.0 * self.position_m


class PoseErrorEvaluator:
    """Scores DH tables against the true one on a fixed set of configurations.

    Parameters
    ----------
    base : array_like, shape (4, 4)
    true_dh : array_like, shape (L, 4)
    box : array_like, shape (L, 2)
        Where the configurations are drawn [rad].
    n : int
        Number of configurations (paper: 1000).
    seed : int
    """

    def __init__(self, base: ArrayLike, true_dh: ArrayLike, box: ArrayLike,
                 n: int = EVAL_CONFIGS, seed: int = EVAL_SEED) -> None:
        self.base = np.asarray(base, dtype=float)
        self.true_dh = np.asarray(true_dh, dtype=float)
        self.configs = uniform_configs(box, n, seed)
        self._true = kinematics.forward_kinematics(self.base, self.true_dh, self.configs)

    def __call__(self, dh: ArrayLike) -> PoseErrors:
        """Average position [m] and orientation [deg] errors of ``dh`` (L, 4) or (4 L,)."""
        dh = np.asarray(dh, dtype=float).reshape(self.true_dh.shape)
        if not np.all(np.isfinite(dh)):
            raise ValueError('DH table contains NaN or inf')
        est = kinematics.forward_kinematics(self.base, dh, self.configs)
        pos = np.linalg.norm(est[:, :3, 3] - self._true[:, :3, 3], axis=1)
        rot = orientation_errors_deg(self._true[:, :3, :3], est[:, :3, :3])
        return PoseErrors(float(pos.mean()), float(rot.mean()))


def accumulated_movement_deg(thetas: ArrayLike) -> NDArray[np.float64]:
    """Accumulated L1 joint movement after each move, eq. totalArmMovement.

    Parameters
    ----------
    thetas : array_like, shape (K + 1, L)
        ``theta_0`` (the initial configuration) then each visited configuration [rad].

    Returns
    -------
    ndarray, shape (K,)
        ``sum_{k<=j} ||theta_k - theta_{k-1}||_1`` in degrees, for j = 1..K.
    """
    t = np.asarray(thetas, dtype=float)
    if t.ndim != 2 or t.shape[0] < 1:
        raise ValueError(f'thetas must have shape (K + 1, L), got {t.shape}')
    return np.degrees(np.cumsum(np.sum(np.abs(np.diff(t, axis=0)), axis=1)))


def discarded_samples(outcomes: ArrayLike) -> int:
    """Number of failed attempts in a sequence of outcomes (``True`` = success)."""
    return int(np.size(outcomes) - np.count_nonzero(outcomes))
