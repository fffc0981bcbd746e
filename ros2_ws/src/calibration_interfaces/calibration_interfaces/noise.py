"""The noise-model parameters the detector, the estimator and the selector share (no rclpy).

One vocabulary (:data:`body_schema.noise.NOISE_MODELS`: ``pose_dependent`` | ``constant``),
one default and one description per parameter; models are built by the
:func:`body_schema.noise.noise_model` factory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from body_schema.noise import NOISE_MODELS, ConstantNoise, PoseDependentNoise, noise_model
from body_schema.robot import ArmModel

from .parameters import setting

__all__ = ['NoiseSettings', 'PoseDependentSettings']

_CN = ConstantNoise()        # fitted defaults live in body_schema.noise

_FROM_DESCRIPTION = ("; negative: the robot description's (its noise_model block, fitted for its camera and "
                     "marker by tools.fit_noise), or the built-in iCub fit")


@dataclass(frozen=True)
class PoseDependentSettings:
    """Coefficients of the pose-dependent law (paper eq. 13, one law per block).

    Each is negative by default: the law then comes from the robot description
    (:meth:`body_schema.noise.PoseDependentNoise.for_robot`), so a camera and marker of another size
    need no parameter; a value set here overrides that coefficient alone.
    """

    pdn_a_pos: float = setting(-1.0, 'Pose-dependent position variance per r^2 [m^2/m^2]' + _FROM_DESCRIPTION,
                               (-1.0, 1.0))
    pdn_b_pos: float = setting(-1.0, 'Pose-dependent position variance per (phi-45)^2 [m^2/deg^2]'
                               + _FROM_DESCRIPTION, (-1.0, 1.0))
    pdn_a_rot: float = setting(-1.0, 'Pose-dependent orientation variance per r^2 [rad^2/m^2]' + _FROM_DESCRIPTION,
                               (-1.0, 10.0))
    pdn_b_rot: float = setting(-1.0, 'Pose-dependent orientation variance per (phi-45)^2 [rad^2/deg^2]'
                               + _FROM_DESCRIPTION, (-1.0, 1.0))
    pdn_floor_pos: float = setting(-1.0, 'Pose-dependent position variance floor [m^2] (0 with equal a, b for both '
                                   "blocks: the paper's single law)" + _FROM_DESCRIPTION, (-1.0, 1.0))
    pdn_floor_rot: float = setting(-1.0, 'Pose-dependent orientation variance floor [rad^2]' + _FROM_DESCRIPTION,
                                   (-1.0, 1.0))

    def build(self, model: ArmModel | None = None) -> PoseDependentNoise:
        """The description's law (the built-in defaults without ``model``) with the coefficients
        set here (>= 0) in place of its own."""
        given = {k: getattr(self, f'pdn_{k}') for k in ('a_pos', 'b_pos', 'a_rot', 'b_rot', 'floor_pos', 'floor_rot')}
        overrides = {k: v for k, v in given.items() if v >= 0}
        return PoseDependentNoise.for_robot(model, **overrides) if model is not None \
            else PoseDependentNoise(**overrides)


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

    def build(self, model: ArmModel | None = None,
              pose_dependent: PoseDependentSettings = PoseDependentSettings()) -> PoseDependentNoise | ConstantNoise:
        """The selected model.

        ``model`` (the robot description) gives the pose-dependent law, its ``depth_ratio`` and
        stereo ratios included (:meth:`PoseDependentSettings.build`); without it, the built-in defaults.

        Raises
        ------
        ValueError
            If ``noise_model`` is not one of :data:`body_schema.noise.NOISE_MODELS`.
        """
        if self.constant:
            return noise_model('constant', sigma_pos=self.cn_sigma_pos,
                               sigma_rot=float(np.radians(self.cn_sigma_rot_deg)))
        if self.noise_model not in NOISE_MODELS:
            raise ValueError(f'unknown noise model {self.noise_model!r}; expected one of {list(NOISE_MODELS)}')
        # The whole law, its depth_ratio and stereo ratios included (not only the six coefficients).
        return pose_dependent.build(model)
