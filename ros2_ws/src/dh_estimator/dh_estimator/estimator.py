"""The online DH estimator behind the node (pure Python, no rclpy).

Wraps :class:`body_schema.ekf.ExtendedKalmanFilter` with what an online calibration needs: one
update per static configuration (a repeated observation of the same configuration is not new
evidence), counters, an atomic checkpoint of ``(x, P, counters)`` to resume after a crash, and
export of the calibrated model as a DH-table YAML with one-sigma uncertainties and as a URDF.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from body_schema import ArmModel
from body_schema import ekf as ekf_mod
from body_schema.urdf import model_urdf
from calibration_interfaces.dh_file import write_dh_file
from calibration_interfaces.outcome import Outcome
from calibration_interfaces.parameters import setting

__all__ = ['EstimatorSettings', 'OnlineEstimator']


@dataclass(frozen=True)
class EstimatorSettings:
    """Filter settings.

    Attributes
    ----------
    q_length, q_angle : float
        Process-noise variances per step for lengths [m^2] and angles [rad^2].
    gate_probability : float
        Chi-square probability of the Mahalanobis gate; 0 disables gating.
    iterations : int
        Linearisations per update (1: the paper's EKF; more: iterated EKF).
    same_config_tol : float
        Max-abs joint difference [rad] under which a configuration counts as the previous one.
    gate_warmup : int
        Accepted updates before the gate may reject. Far from the truth the linearised ``S``
        underestimates the real spread of innovations (measured: the very first observation of
        a paper-wide initial guess can sit at Mahalanobis 4.9 > the 99.9% gate of 4.7), so an
        early gate would throw away the most informative samples.
    """

    q_length: float = setting(0.0, 'Process-noise variance per update for a, d [m^2]', (0.0, 1.0))
    q_angle: float = setting(0.0, 'Process-noise variance per update for alpha, offset [rad^2]', (0.0, 1.0))
    gate_probability: float = setting(0.999, 'Chi-square gate probability (0 disables gating)', (0.0, 0.999999))
    iterations: int = setting(1, "Linearisations per update (1: the paper's EKF; >1: iterated EKF)", (1, 50))
    same_config_tol: float = setting(1e-3, 'Closer than this to the previous attempt = same configuration [rad]',
                                     (0.0, 0.5), name='same_config_tolerance')
    gate_warmup: int = setting(10, 'Accepted updates before the gate may reject', (0, 100000))

    def __post_init__(self) -> None:
        if self.q_length < 0 or self.q_angle < 0:
            raise ValueError(f'process noise must be >= 0, got {self.q_length}, {self.q_angle}')
        if not 0.0 <= self.gate_probability < 1.0:
            raise ValueError(f'gate_probability must be in [0, 1), got {self.gate_probability}')
        if self.gate_warmup < 0:
            raise ValueError(f'gate_warmup must be >= 0, got {self.gate_warmup}')
        if self.iterations < 1:
            raise ValueError(f'iterations must be >= 1, got {self.iterations}')


class OnlineEstimator:
    """EKF over a model's DH table with one update per configuration.

    Parameters
    ----------
    model : ArmModel
        The robot (its ``dh`` is not used as the estimate; ``x0`` is).
    x0 : array_like, shape (L, 4) or (4 L,)
        Initial DH guess.
    P0 : array_like, shape (4 L, 4 L)
        Initial covariance.
    settings : EstimatorSettings
    """

    def __init__(self, model: ArmModel, x0: ArrayLike, P0: ArrayLike,  # noqa: N803
                 settings: EstimatorSettings = EstimatorSettings()) -> None:
        self.model = model
        self.settings = settings
        n = model.n_params
        per_link = np.array([settings.q_length, settings.q_length, settings.q_angle, settings.q_angle])
        self.gate = ekf_mod.chi2_gate(6, settings.gate_probability) if settings.gate_probability > 0 else None
        self.ekf = ekf_mod.ExtendedKalmanFilter(np.asarray(x0, dtype=float).ravel(), P0,
                                                Q=np.diag(np.tile(per_link, model.n_joints)))
        if self.ekf.dim_x != n:
            raise ValueError(f'initial guess has {self.ekf.dim_x} parameters, the model {n}')
        self.hand = ekf_mod.HandPoseModel(model.base, model.n_joints)
        self.last_config: NDArray[np.float64] | None = None
        self.n_duplicates = 0

    @property
    def dh(self) -> NDArray[np.float64]:
        """Current estimate, shape (L, 4)."""
        return self.ekf.x.reshape(self.model.dh.shape)

    @property
    def P(self) -> NDArray[np.float64]:  # noqa: N802
        return self.ekf.P

    @property
    def counters(self) -> dict[str, int]:
        return {'updates': self.ekf.n_updates, 'rejected': self.ekf.n_rejected,
                'duplicates': self.n_duplicates}

    def is_duplicate(self, q: ArrayLike) -> bool:
        """Whether ``q`` is the configuration of the previous attempt."""
        return self.last_config is not None and \
            float(np.max(np.abs(np.asarray(q, dtype=float) - self.last_config))) <= self.settings.same_config_tol

    def offer(self, q: ArrayLike, pose: ArrayLike, R: ArrayLike) -> Outcome:  # noqa: N803
        """Offer one hand-pose observation at joints ``q``.

        Parameters
        ----------
        q : array_like, shape (L,)
        pose : array_like, shape (4, 4)
            Observed hand pose in the root frame.
        R : array_like, shape (6, 6)
            Its covariance (position, rotation vector).

        Raises
        ------
        body_schema.ekf.InvalidInputError
            On NaN or mis-shaped input; nothing changes.
        """
        q = np.asarray(q, dtype=float)
        if self.is_duplicate(q):
            self.n_duplicates += 1
            return Outcome.DUPLICATE
        x, P = self.ekf.x, self.ekf.P  # noqa: N806
        self.ekf.gate = self.gate if self.ekf.n_updates >= self.settings.gate_warmup else None
        self.ekf.predict()
        try:
            ok = self.hand.update(self.ekf, q, pose, R, iterations=self.settings.iterations)
        except (ekf_mod.InvalidInputError, ekf_mod.FilterError):
            self.ekf.x, self.ekf.P = x, P       # undo predict: bad input changes nothing
            raise
        self.last_config = q.copy()
        if not ok:
            self.ekf.x, self.ekf.P = x, P       # a gated-out attempt also leaves P as it was
        return Outcome.ACCEPTED if ok else Outcome.REJECTED

    # ----------------------------------------------------------------------------------------
    # Checkpoint and export

    def save_checkpoint(self, path: str | Path) -> None:
        """Write ``x, P``, counters and the last configuration atomically (``.npz``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix='.tmp')
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, x=self.ekf.x, P=self.ekf.P, n_updates=self.ekf.n_updates,
                     n_rejected=self.ekf.n_rejected, n_duplicates=self.n_duplicates,
                     last_config=np.full(self.model.n_joints, np.nan) if self.last_config is None
                     else self.last_config, settings=yaml.safe_dump(asdict(self.settings)))
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore the state written by :meth:`save_checkpoint`."""
        with np.load(Path(path)) as d:
            x, P = d['x'], d['P']  # noqa: N806
            if x.shape != self.ekf.x.shape or P.shape != self.ekf.P.shape:
                raise ValueError(f'checkpoint {path} holds {x.size} parameters, expected {self.ekf.x.size}')
            self.ekf.x, self.ekf.P = x.copy(), P.copy()
            self.ekf.n_updates = int(d['n_updates'])
            self.ekf.n_rejected = int(d['n_rejected'])
            self.n_duplicates = int(d['n_duplicates'])
            last = d['last_config']
            self.last_config = None if np.any(np.isnan(last)) else last.copy()

    def calibrated_model(self) -> ArmModel:
        """The robot with the current DH estimate."""
        return self.model.with_dh(self.dh)

    def export(self, directory: str | Path, stem: str = 'calibrated') -> tuple[Path, Path]:
        """Write ``<stem>_dh.yaml`` (table with one-sigma, :mod:`calibration_interfaces.dh_file`) and
        ``<stem>.urdf``; return both paths."""
        directory = Path(directory)
        sigma = np.sqrt(np.diag(self.P)).reshape(self.model.dh.shape)
        yaml_path = write_dh_file(directory / f'{stem}_dh.yaml', self.dh, self.model.joint_names,
                                  self.model.name, sigma, extra={'updates': self.counters})
        urdf_path = directory / f'{stem}.urdf'
        urdf_path.write_text(model_urdf(self.calibrated_model()))
        return yaml_path, urdf_path
