"""Parameters of the estimator node beyond the filter and the pairing (pure; no rclpy).

The node declares :class:`EstimatorNodeSettings`, :class:`~calibration_interfaces.noise.NoiseSettings`,
:class:`~dh_estimator.estimator.EstimatorSettings` and :class:`~dh_estimator.pairing.PairingSettings`
as its parameters; :func:`settings_from_parameters` builds the same settings from a parameter file
(the offline evaluation re-runs a bag with what the run used).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from body_schema import sampling
from calibration_interfaces import parameters
from calibration_interfaces.noise import NoiseSettings
from calibration_interfaces.parameters import setting

from .estimator import EstimatorSettings
from .pairing import PairingSettings

__all__ = ['EstimatorNodeSettings', 'SETTINGS', 'settings_from_parameters']


@dataclass(frozen=True)
class EstimatorNodeSettings:
    """Robot, initial guess and files of the estimator node."""

    robot: str = setting('icub_right_arm', 'Packaged robot name or YAML path')
    initial_guess: str = setting('perturbed', "'perturbed': seeded uniform draw around the description's table "
                                 "(paper); 'nominal': the description's table; 'file': initial_dh_file",
                                 choices=('perturbed', 'nominal', 'file'))
    initial_seed: int = setting(0, 'Seed of the perturbed initial guess', (0, 2**31 - 1))
    initial_dh_file: str = setting('', 'DH file (an exported calibrated_dh.yaml or a robot description) '
                                   'for initial_guess=file')
    width_length: float = setting(sampling.PAPER_WIDTH_LENGTH, 'Full width of the a, d prior [m]', (1e-6, 1.0))
    width_angle_deg: float = setting(float(np.degrees(sampling.PAPER_WIDTH_ANGLE)),
                                     'Full width of the alpha, offset prior [deg]', (1e-4, 180.0))
    checkpoint_path: str = setting('', 'State file rewritten after every update; resumed if it exists')
    export_dir: str = setting('', 'Where ~/export and shutdown write the calibrated model')
    export_on_shutdown: bool = setting(True, 'Export the calibrated model when the node stops')

    @property
    def widths(self) -> tuple[float, float]:
        """Full prior widths (lengths [m], angles [rad])."""
        return self.width_length, float(np.radians(self.width_angle_deg))


#: Every settings class the estimator node declares, in order.
SETTINGS: tuple[type, ...] = (EstimatorNodeSettings, NoiseSettings, EstimatorSettings, PairingSettings)


def settings_from_parameters(values: Mapping[str, Any]) -> tuple[EstimatorNodeSettings, NoiseSettings,
                                                                  EstimatorSettings, PairingSettings]:
    """All four settings from parameter values (e.g. :func:`~calibration_interfaces.parameters.read_params_file`);
    missing parameters take their defaults."""
    return tuple(parameters.settings_from_parameters(cls, values) for cls in SETTINGS)  # type: ignore[return-value]
