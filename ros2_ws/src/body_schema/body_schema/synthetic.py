"""Synthetic calibration runs: exact observations plus noise drawn from the noise model.

No rendering, no detection: each observation is the true hand pose at a configuration, perturbed
by a draw from ``N(0, R)`` with ``R`` the noise model's prediction for that pose, so the noise the
estimator assumes is the noise it gets. This isolates the estimator (consistency: NEES / NIS) and
makes studies of adaptation cheap; the rendered loop (``active_selector.study``) measures the
whole chain.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import kinematics
from .extrinsics import corrections
from .noise import NoiseModel, sample_pose
from .robot import ArmModel
from .sampling import as_rng, uniform_configs

__all__ = ['Observation', 'SyntheticRun']


@dataclass(frozen=True)
class Observation:
    """One synthetic hand-pose observation."""

    q: NDArray[np.float64]          # (L,) joints [rad]
    pose: NDArray[np.float64]       # (4, 4) noisy hand pose in the root frame
    R: NDArray[np.float64]          # (6, 6) its covariance  # noqa: N815
    true_dh: NDArray[np.float64]    # (L, 4) the real table when it was taken


@dataclass
class SyntheticRun:
    """A stream of observations of a robot whose table may change.

    Parameters
    ----------
    model : ArmModel
        Base, box, markers and camera.
    true_dh : array_like, shape (L, 4)
        The real table at the start.
    noise : NoiseModel
    seed : int or Generator
    changes : dict, optional
        ``{k: table}``: from observation ``k`` (0-based) on, the real table is ``table``.
    camera_delta, marker_delta : array_like, shape (6,), optional
        The real camera pose and marker placement differ from the description's by these
        (:func:`body_schema.extrinsics.perturb_pose`); the observation is what the detector makes
        of the marker with the description's poses, ``C_nom C^-1 FK M M_nom^-1``.
    """

    model: ArmModel
    true_dh: ArrayLike
    noise: NoiseModel
    seed: int | np.random.Generator = 0
    changes: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    camera_delta: ArrayLike | None = None
    marker_delta: ArrayLike | None = None

    def table_at(self, k: int) -> NDArray[np.float64]:
        """The real table when observation ``k`` is taken."""
        table = np.asarray(self.true_dh, dtype=float)
        for start in sorted(self.changes):
            if k >= start:
                table = np.asarray(self.changes[start], dtype=float)
        return table

    def __call__(self, n: int, configs: Callable[[int, np.random.Generator], NDArray] | None = None
                 ) -> list[Observation]:
        """``n`` observations at uniform configurations of the box (or ``configs(n, rng)``)."""
        rng = as_rng(self.seed)
        model = self.model
        qs = uniform_configs(model.calibration_box, n, rng) if configs is None else configs(n, rng)
        cam = model.camera_pose('left')
        big_e, big_f = corrections(cam, model.markers[0].hand_T_marker,
                                   *(np.zeros(6) if d is None else d for d in (self.camera_delta, self.marker_delta)))
        out = []
        for k, q in enumerate(qs):
            table = self.table_at(k)
            pose = big_e @ kinematics.forward_kinematics(model.base, table, q) @ big_f
            cov = self.noise.hand_covariance(cam, pose, model.markers)
            out.append(Observation(np.asarray(q, dtype=float), sample_pose(pose, cov, rng), cov, table))
        return out
