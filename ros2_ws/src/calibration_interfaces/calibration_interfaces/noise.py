"""The noise-model parameters the detector, the estimator and the selector share (no rclpy).

One vocabulary (:data:`body_schema.noise.NOISE_MODELS`: ``pose_dependent`` | ``constant``),
one default and one description per parameter; models are built by the
:func:`body_schema.noise.noise_model` factory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from body_schema.noise import NOISE_MODELS, ConstantNoise, PoseDependentNoise, noise_model

from .parameters import setting

__all__ = ['NoiseSettings', 'PoseDependentSettings']

_CN = ConstantNoise()        # fitted defaults live in body_schema.noise
_PDN = PoseDependentNoise()


@dataclass(frozen=True)
class PoseDependentSettings:
    """Coefficients of the pose-dependent law (paper eq. 13, one law per block)."""

    pdn_a_pos: float = setting(_PDN.a_pos, 'Pose-dependent position variance per r^2', (0.0, 1.0))
    pdn_b_pos: float = setting(_PDN.b_pos, 'Pose-dependent position variance per (phi-45)^2', (0.0, 1.0))
    pdn_a_rot: float = setting(_PDN.a_rot, 'Pose-dependent orientation variance per r^2', (0.0, 10.0))
    pdn_b_rot: float = setting(_PDN.b_rot, 'Pose-dependent orientation variance per (phi-45)^2', (0.0, 1.0))

    def build(self) -> PoseDependentNoise:
        """The model (floors: the fitted defaults)."""
        return PoseDependentNoise(self.pdn_a_pos, self.pdn_b_pos, self.pdn_a_rot, self.pdn_b_rot,
                                  _PDN.floor_pos, _PDN.floor_rot)


@dataclass(frozen=True)
class NoiseSettings:
    """Which observation-noise model a node uses, and the CN baseline's constants."""

    noise_model: str = setting('pose_dependent', "Observation covariance: 'pose_dependent' (paper eq. 13; "
                               "the estimator takes it from /hand_pose) or 'constant' (the CN baseline)",
                               choices=NOISE_MODELS)
    cn_sigma_pos: float = setting(_CN.sigma_pos, 'CN position standard deviation [m]', (1e-6, 1.0))
    cn_sigma_rot_deg: float = setting(float(np.degrees(_CN.sigma_rot)), 'CN orientation standard deviation [deg]',
                                      (1e-4, 90.0))

    @property
    def constant(self) -> bool:
        """Whether the CN baseline is selected."""
        return self.noise_model == 'constant'

    def build(self, pose_dependent: PoseDependentSettings = PoseDependentSettings()) -> PoseDependentNoise | ConstantNoise:
        """The selected model, through the :func:`body_schema.noise.noise_model` factory.

        Raises
        ------
        ValueError
            If ``noise_model`` is not one of :data:`body_schema.noise.NOISE_MODELS`.
        """
        if self.constant:
            return noise_model('constant', sigma_pos=self.cn_sigma_pos,
                               sigma_rot=float(np.radians(self.cn_sigma_rot_deg)))
        p = pose_dependent.build()
        return noise_model(self.noise_model, a_pos=p.a_pos, b_pos=p.b_pos, a_rot=p.a_rot, b_rot=p.b_rot,
                           floor_pos=p.floor_pos, floor_rot=p.floor_rot)
