"""The online DH estimator behind the node (pure Python, no rclpy).

Wraps one of two estimators with what an online calibration needs: the online MAP estimator
(:class:`body_schema.map_estimator.MapEstimator`, the default: re-solves prior + observations
after each one, robust loss, adapts to a changing body) or the paper's EKF
(:class:`body_schema.ekf.ExtendedKalmanFilter`, ``estimator='ekf'``, ``iterations=1`` for the
paper's form); plus one update per static configuration (a repeated observation of the same configuration is not new
evidence), counters, an atomic checkpoint of ``(x, P, counters)`` to resume after a crash, and
export of the calibrated model as a DH-table YAML with one-sigma uncertainties and as a URDF.
Parameter combinations the box cannot identify (:mod:`body_schema.identifiability`) are held at
the initial guess by the MAP estimator and named in the export (``identifiability``).

With ``camera_prior`` / ``marker_prior`` set (MAP only), the pose of the primary camera
(``left``) in the root frame and the marker's offset on the flange are estimated with the table
(:mod:`body_schema.extrinsics`), from the description's poses (the ones the detector uses) and
the stated prior. The DH parameters they absorb (the first link's ``d`` and ``offset``, the
last link's row) are held at the description's values, which define the base and flange frames;
the export adds the camera pose and marker offset with their one-sigma and
``<stem>_camera_static_transform.yaml`` (tf2_ros ``static_transform_publisher`` arguments).
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.linalg
import yaml
from numpy.typing import ArrayLike, NDArray

from body_schema import ArmModel
from body_schema import ekf as ekf_mod
from body_schema import extrinsics as extrinsics_mod
from body_schema import identifiability
from body_schema.map_estimator import COVARIANCES, LOSS_SCALE_RANGE, LOSSES, MapEstimator, MapSettings
from body_schema.urdf import FixedLink, model_urdf, transform_to_xyz_rpy
from calibration_interfaces.contract import optical_frame
from calibration_interfaces.dh_file import modified_section, write_dh_file
from calibration_interfaces.outcome import Outcome
from calibration_interfaces.parameters import setting
from calibration_interfaces.robot_formats import write_exports

__all__ = ['EstimatorSettings', 'OnlineEstimator', 'ESTIMATORS']

#: Estimator back ends: the online MAP smoother (default) and the paper's EKF.
ESTIMATORS = ('map', 'ekf')
_MAP = MapSettings()
#: Standard deviation [m or rad per unit direction] of the prior holding unidentifiable directions.
FIXED_STD = 1e-6
#: The camera whose pose can be estimated: the contract's primary slot.
CAMERA = 'left'


@dataclass(frozen=True)
class EstimatorSettings:
    """Estimator settings.

    Attributes
    ----------
    estimator : str
        ``'map'`` (online MAP smoother, default) or ``'ekf'`` (the paper's filter).
    q_length, q_angle : float
        Random-walk (process-noise) variances per observation for lengths [m^2] and angles
        [rad^2], for both estimators.
    gate_probability : float
        EKF: chi-square probability of the Mahalanobis gate; 0 disables gating.
    iterations : int
        EKF: linearisations per update (1: the paper's EKF; more: iterated EKF).
    loss, loss_scale, outlier_probability, window, change_probability, change_window,
    change_separation_deg, jump_length, jump_angle, change_confirm, max_nfev, verdict_nfev :
        MAP: see :class:`body_schema.map_estimator.MapSettings`.
    same_config_tol : float
        Max-abs joint difference [rad] under which a configuration counts as the previous one.
    gate_warmup : int
        Accepted updates before the gate may reject. Far from the truth the linearised ``S``
        underestimates the real spread of innovations (measured: the very first observation of
        a paper-wide initial guess can sit at Mahalanobis 4.9 > the 99.9% gate of 4.7), so an
        early gate would throw away the most informative samples.
    """

    estimator: str = setting('map', "Estimator: 'map' re-solves prior + observations after each one (robust "
                                    "loss, adapts to a changing body); 'ekf' is the paper's filter",
                             choices=ESTIMATORS)
    q_length: float = setting(0.0, 'Random-walk (process-noise) variance per observation for a, d [m^2]', (0.0, 1.0))
    q_angle: float = setting(0.0, 'Random-walk variance per observation for alpha, offset [rad^2]', (0.0, 1.0))
    gate_probability: float = setting(0.999, 'EKF: chi-square gate probability (0 disables gating)', (0.0, 0.999999))
    iterations: int = setting(1, "EKF: linearisations per update (1: the paper's EKF; >1: iterated EKF)", (1, 50))
    same_config_tol: float = setting(1e-3, 'Closer than this to the previous attempt = same configuration [rad]',
                                     (0.0, 0.5), name='same_config_tolerance')
    gate_warmup: int = setting(10, 'EKF: accepted updates before the gate may reject', (0, 100000))
    loss: str = setting(_MAP.loss, 'MAP: robust loss on the whitened residual', choices=LOSSES)
    loss_scale: float = setting(-1.0, 'MAP: whitened residual where the robust loss departs from the square '
                                      "[sigma]; negative: the robot description's (noise_model.loss_scale, for "
                                      f'a heavy-tailed law), else {_MAP.loss_scale:g}', (-1.0, LOSS_SCALE_RANGE[1]))
    outlier_probability: float = setting(_MAP.outlier_probability, 'MAP: chi-square probability (6 dof) beyond '
                                                                   'which an observation is reported an outlier',
                                         (0.5, 0.999999))
    window: int = setting(_MAP.window, 'MAP: observations kept in the nonlinear problem, older ones folded into '
                                       'the prior (0: all)', (0, 1000000))
    change_probability: float = setting(_MAP.change_probability, 'MAP: chi-square probability (6 dof) an '
                                        'innovation must exceed to count towards a body change (0: no change '
                                        'detection)', (0.0, 0.999999))
    change_window: int = setting(_MAP.change_window, 'MAP: innovations looked at by the change test', (1, 100))
    change_count: int = setting(_MAP.change_count, 'MAP: of those, how many must exceed for a change', (1, 100))
    change_separation_deg: float = setting(float(np.degrees(_MAP.change_separation)),
                                           'MAP: exceedances at configurations within this largest joint difference '
                                           '[deg] count once towards a change (the same view repeats its '
                                           'detection error)', (0.0, 180.0))
    warmup: int = setting(_MAP.warmup, 'MAP: updates with the Huber loss and no change test, while the estimate '
                                       'is still far from the truth', (0, 100000))
    jump_length: float = setting(_MAP.jump_length, 'MAP: standard deviation of a detected change for a, d [m]',
                                 (1e-6, 1.0))
    jump_angle: float = setting(_MAP.jump_angle, 'MAP: standard deviation of a detected change for alpha, '
                                'offset [rad]', (1e-6, 3.2))
    max_nfev: int = setting(_MAP.max_nfev, 'MAP: residual evaluations per re-solve', (1, 10000))
    verdict_nfev: int = setting(_MAP.verdict_nfev, 'MAP: when a re-solve stopped at max_nfev with the new '
                                'observation beyond the outlier bound, solve on for up to this many more '
                                'evaluations before the verdict (0: judge the truncated solve)', (0, 100000))
    covariance: str = setting('', "MAP: posterior covariance, 'sandwich' (the robust estimate's own, with the "
                              "residuals' spread measured at the solution: consistent when the noise law is "
                              "right only up to its scale or tails), 'sandwich_hc3' (the spread of "
                              "leverage-corrected residuals: also when few observations inform a "
                              "direction), 'sandwich_blocks' (that spread pooled separately over the "
                              "position rows and the orientation rows: also when the law misjudges the two "
                              "by different factors), 'sandwich_white' (each residual row's own spread: also when "
                              "the law's shape is wrong), 'sandwich_white_hc2' or 'sandwich_white_hc3' (each row's "
                              "own leverage-corrected spread, HC2 or HC3) or 'gauss_newton' (the stated noise "
                              "taken as exact); empty: the robot description's noise_model.covariance, else "
                              f"'{_MAP.covariance}'", choices=('',) + COVARIANCES)
    camera_prior: str = setting('', 'MAP: estimate the camera pose with the table, prior one-sigma per axis '
                                '"<m> <deg>" (e.g. "0.02 2" for a tape-measured tripod); empty or 0: known')
    marker_prior: str = setting('', 'MAP: estimate the marker offset on the flange, prior one-sigma per axis '
                                '"<m> <deg>" (e.g. "0.005 5"); empty or 0: known')
    parallel_std: float = setting(-1.0, 'MAP: standard deviation [m] of the prior holding the combinations only '
                                  "exactly parallel joint axes hide (a UR's d along joints 2-4); negative: the "
                                  "initial covariance's own spread along each (a real arm's axes are parallel "
                                  'to a fraction of a degree, so pinning them at a wrong guess biases the rest); 0: '
                                  'pinned like the exact ones',
                                  (-1.0, 1.0))
    twin_moves: bool = setting(_MAP.twins, 'MAP: after each re-solve move to the exact DH twin nearest the prior (the '
                                      'same hand poses, angles within a turn of the guess, no frame turned by pi '
                                      'that the prior does not turn): the camera cannot tell twins apart')
    change_confirm: bool = setting(_MAP.change_confirm, 'MAP: a declared change stands only if the re-solve with '
                                   'the jump explains most of the exceeding observations (within the outlier '
                                   'bound); else the jump is withdrawn')
    restart_after: int = setting(_MAP.restart_after, 'MAP: after this many consecutive outliers also solve from '
                                 'the prior mean and keep the lower objective (a far guess can lead the solver '
                                 'into a wrong basin); 0: never', (0, 1000))

    @property
    def extrinsic_priors(self) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
        """Parsed ``camera_prior``, ``marker_prior`` ((m, rad) or None: known)."""
        return (extrinsics_mod.parse_std(self.camera_prior, 'camera_prior'),
                extrinsics_mod.parse_std(self.marker_prior, 'marker_prior'))

    def map_settings(self, covariance: str = '', loss_scale: float = 0.0) -> MapSettings:
        """The MAP estimator's settings (validated there); ``covariance`` (the description's) is used
        where :attr:`covariance` is empty, ``loss_scale`` (the description's, if > 0) where
        :attr:`loss_scale` is negative."""
        scale = self.loss_scale if self.loss_scale >= 0 else (loss_scale if loss_scale > 0 else _MAP.loss_scale)
        return MapSettings(loss=self.loss, loss_scale=scale,
                           outlier_probability=self.outlier_probability, max_nfev=self.max_nfev,
                           verdict_nfev=self.verdict_nfev,
                           window=self.window, q_length=self.q_length, q_angle=self.q_angle,
                           change_probability=self.change_probability, change_window=self.change_window,
                           change_count=self.change_count,
                           change_separation=float(np.radians(self.change_separation_deg)), warmup=self.warmup,
                           jump_length=self.jump_length,
                           jump_angle=self.jump_angle, change_confirm=self.change_confirm, twins=self.twin_moves,
                           restart_after=self.restart_after,
                           covariance=self.covariance or covariance or _MAP.covariance)

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ValueError(f'estimator must be one of {ESTIMATORS}, got {self.estimator!r}')
        if self.loss not in LOSSES:
            raise ValueError(f'loss must be one of {LOSSES}, got {self.loss!r}')
        if self.q_length < 0 or self.q_angle < 0:
            raise ValueError(f'process noise must be >= 0, got {self.q_length}, {self.q_angle}')
        if not 0.0 <= self.gate_probability < 1.0:
            raise ValueError(f'gate_probability must be in [0, 1), got {self.gate_probability}')
        if self.gate_warmup < 0:
            raise ValueError(f'gate_warmup must be >= 0, got {self.gate_warmup}')
        if self.iterations < 1:
            raise ValueError(f'iterations must be >= 1, got {self.iterations}')
        if 0.0 <= self.loss_scale < LOSS_SCALE_RANGE[0]:
            raise ValueError(f'loss_scale must be negative (the description\'s) or >= {LOSS_SCALE_RANGE[0]:g}, '
                             f'got {self.loss_scale}')
        if any(p is not None for p in self.extrinsic_priors) and self.estimator != 'map':
            raise ValueError(f'camera_prior / marker_prior need estimator map, got {self.estimator!r}')


class OnlineEstimator:
    """Online DH estimate (MAP or EKF) with one update per configuration.

    Parameters
    ----------
    model : ArmModel
        The robot (its ``dh`` is not used as the estimate; ``x0`` is). Its joint limits bound
        the configurations the MAP estimator accepts.
    x0 : array_like, shape (L, 4) or (4 L,)
        Initial DH guess (the prior mean).
    P0 : array_like, shape (4 L, 4 L)
        Initial covariance.
    settings : EstimatorSettings
    """

    def __init__(self, model: ArmModel, x0: ArrayLike, P0: ArrayLike,  # noqa: N803
                 settings: EstimatorSettings = EstimatorSettings()) -> None:
        self.model = model
        self.settings = settings
        n = model.n_params
        x0 = np.asarray(x0, dtype=float).ravel()
        if x0.size != n:
            raise ValueError(f'initial guess has {x0.size} parameters, the model {n}')
        self.ekf: ekf_mod.ExtendedKalmanFilter | None = None
        self.map: MapEstimator | None = None
        cam_std, marker_std = settings.extrinsic_priors
        self.extrinsics: extrinsics_mod.Extrinsics | None = None
        if cam_std is not None or marker_std is not None:
            self.extrinsics = extrinsics_mod.Extrinsics(model.camera_pose(CAMERA), model.markers[0].hand_T_marker,
                                                        cam_std, marker_std)
            # What the camera / marker absorb is not calibrated: the description's values define
            # the base and flange frames (the estimate is scored in that gauge).
            x0 = x0.copy()
            absorbed = list(extrinsics_mod.absorbed_parameters(model.n_joints, cam_std is not None,
                                                               marker_std is not None))
            x0[absorbed] = model.dh.ravel()[absorbed]
            x0 = np.concatenate([x0, np.zeros(self.extrinsics.n)])
            P0 = scipy.linalg.block_diag(P0, np.diag(self.extrinsics.prior_std() ** 2))  # noqa: N806
        # Combinations of the table no hand pose over the box separates (a UR's parallel axes, what
        # the camera or the marker absorbs): the MAP estimator holds them at the initial guess,
        # the export and the report name them.
        self.identifiability = identifiability.analyse(model, extrinsics=self.extrinsics)
        if settings.estimator == 'map':
            exact, parallel = self.identifiability.held_groups()
            # What the camera / marker absorb is exact for any table: pinned. What only parallel
            # axes hide is not, on a real arm: held at the guess with the guess's own uncertainty.
            spread = np.sqrt(np.einsum('ik,ij,jk->k', parallel, P0, parallel)) if settings.parallel_std < 0 \
                else np.full(parallel.shape[1], max(settings.parallel_std, FIXED_STD))
            self.map = MapEstimator(model.base, x0, P0,
                                    settings.map_settings(model.noise_covariance, model.noise_loss_scale),
                                    limits=model.limits, fixed_directions=np.hstack([exact, parallel]),
                                    fixed_std=np.concatenate([np.full(exact.shape[1], FIXED_STD), spread]),
                                    extrinsics=self.extrinsics)
        else:
            per_link = np.array([settings.q_length, settings.q_length, settings.q_angle, settings.q_angle])
            self.gate = ekf_mod.chi2_gate(6, settings.gate_probability) if settings.gate_probability > 0 else None
            self.ekf = ekf_mod.ExtendedKalmanFilter(x0, P0, Q=np.diag(np.tile(per_link, model.n_joints)))
            self.hand = ekf_mod.HandPoseModel(model.base, model.n_joints)
        self.last_config: NDArray[np.float64] | None = None
        self.n_duplicates = 0
        #: NIS (squared Mahalanobis distance, 6 dof) of every update's innovation, in order (since
        #: this object was made; not checkpointed): the noise law's check that needs no truth.
        self.innovations: list[float] = []

    @property
    def x(self) -> NDArray[np.float64]:
        """Current estimate, shape (4 L,)."""
        return self.map.x if self.map is not None else self.ekf.x

    @property
    def dh(self) -> NDArray[np.float64]:
        """Current estimate, shape (L, 4)."""
        return self.x[:self.model.n_params].reshape(self.model.dh.shape)

    def extrinsic_poses(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Estimated camera pose (root frame) and marker placement (flange frame), or None."""
        if self.extrinsics is None:
            return None
        return self.extrinsics.poses(self.x[self.model.n_params:])

    @property
    def P(self) -> NDArray[np.float64]:  # noqa: N802
        return self.map.P if self.map is not None else self.ekf.P

    @property
    def P_dh(self) -> NDArray[np.float64]:  # noqa: N802
        """The table's block of the covariance, shape (4 L, 4 L) (marginal over any extrinsics)."""
        n = self.model.n_params
        return self.P[:n, :n]

    @property
    def mahalanobis(self) -> float:
        """Mahalanobis distance of the last offered observation's innovation (before its update)."""
        if self.map is not None:
            return 0.0 if self.map.last is None else self.map.last.mahalanobis
        return self.ekf.mahalanobis

    @property
    def counters(self) -> dict[str, int]:
        if self.map is not None:
            return {'updates': self.map.n_updates, 'rejected': 0, 'duplicates': self.n_duplicates,
                    'outliers': self.map.n_outliers, 'changes': self.map.n_changes,
                    'twin_moves': self.map.n_twin_moves, 'restarts': self.map.n_restarts,
                    'resolved': self.map.n_resolved, 'outlier_verdicts': self.map.n_outlier_verdicts,
                    'withdrawn_changes': self.map.n_changes_withdrawn}
        return {'updates': self.ekf.n_updates, 'rejected': self.ekf.n_rejected,
                'duplicates': self.n_duplicates, 'outliers': self.ekf.n_rejected, 'changes': 0, 'twin_moves': 0,
                'restarts': 0, 'resolved': 0, 'outlier_verdicts': self.ekf.n_rejected, 'withdrawn_changes': 0}

    def describe_last(self) -> str:
        """One line on the last offered observation, for logs and status messages."""
        if self.map is not None and self.map.last is not None:
            u = self.map.last
            text = f'mahalanobis {u.mahalanobis:.3f}, residual chi2 {u.residual_chi2:.2f}'
            if u.outlier:
                text += f' beyond the {self.settings.outlier_probability:.1%} bound: outlier'
            if u.change_detected:
                text += '; change detected, older evidence aged'
            if u.change_withdrawn:
                text += '; the change test fired but the re-solved body left its evidence beyond the bound: withdrawn'
            if u.twin_move:
                text += '; moved to the twin nearest the prior'
            if u.restart:
                text += (f'; solved again from the prior mean after {self.settings.restart_after} outliers '
                         'in a row: a lower objective, kept')
            return text
        return f'mahalanobis {self.mahalanobis:.3f}'

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
            On NaN, mis-shaped or out-of-limits input; nothing changes.
        body_schema.ekf.FilterError
            If the estimator cannot use it (nothing changes).
        """
        q = np.asarray(q, dtype=float)
        if q.shape != (self.model.n_joints,):
            raise ekf_mod.InvalidInputError(f'joint configuration must have shape ({self.model.n_joints},), '
                                            f'got {q.shape}')
        if self.is_duplicate(q):
            self.n_duplicates += 1
            return Outcome.DUPLICATE
        if self.map is not None:
            u = self.map.update(q, pose, R)
            self.last_config = q.copy()
            self.innovations.append(u.nis)
            return Outcome.OUTLIER if u.outlier else Outcome.ACCEPTED
        x, P = self.ekf.x, self.ekf.P  # noqa: N806
        self.ekf.gate = self.gate if self.ekf.n_updates >= self.settings.gate_warmup else None
        self.ekf.predict()
        try:
            ok = self.hand.update(self.ekf, q, pose, R, iterations=self.settings.iterations)
        except (ekf_mod.InvalidInputError, ekf_mod.FilterError):
            self.ekf.x, self.ekf.P = x, P       # undo predict: bad input changes nothing
            raise
        self.last_config = q.copy()
        self.innovations.append(self.ekf.mahalanobis ** 2)
        if not ok:
            self.ekf.x, self.ekf.P = x, P       # a gated-out attempt also leaves P as it was
        return Outcome.ACCEPTED if ok else Outcome.REJECTED

    # ----------------------------------------------------------------------------------------
    # Checkpoint and export

    def save_checkpoint(self, path: str | Path) -> None:
        """Write the estimator's state, counters and the last configuration atomically (``.npz``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix='.tmp')
        state = self.map.state_dict() if self.map is not None else {
            'x': self.ekf.x, 'P': self.ekf.P, 'n_updates': self.ekf.n_updates, 'n_rejected': self.ekf.n_rejected}
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, estimator=self.settings.estimator, n_duplicates=self.n_duplicates,
                     last_config=np.full(self.model.n_joints, np.nan) if self.last_config is None
                     else self.last_config, settings=yaml.safe_dump(asdict(self.settings)), **state)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore the state written by :meth:`save_checkpoint` (same estimator kind)."""
        with np.load(Path(path)) as d:
            kind = str(d['estimator']) if 'estimator' in d else 'ekf'
            if kind != self.settings.estimator:
                raise ValueError(f'checkpoint {path} was written by the {kind!r} estimator, '
                                 f'this one is {self.settings.estimator!r}')
            if self.map is not None:
                self.map.load_state_dict(dict(d))
            else:
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

    def _extrinsics_export(self, poses: tuple[NDArray[np.float64], NDArray[np.float64]],
                           sigma: NDArray[np.float64]) -> dict[str, object]:
        """The estimated camera pose / marker offset with one-sigma (mm, deg) for the DH YAML."""
        out: dict[str, object] = {}
        for i, block in enumerate(self.extrinsics.blocks):
            pose = poses[0] if block == 'camera' else poses[1]
            nominal = self.extrinsics.camera if block == 'camera' else self.extrinsics.marker
            xyz, rpy = transform_to_xyz_rpy(pose)
            s = sigma[6 * i:6 * i + 6]
            delta = extrinsics_mod.pose_delta(pose, nominal)
            out[block] = {
                'frame': f'{self.model.root_frame} -> {optical_frame(CAMERA)}' if block == 'camera'
                else 'flange (hand) -> marker',
                'xyz': [float(v) for v in xyz], 'rpy_deg': [float(v) for v in np.degrees(rpy)],
                'correction_mm_deg': [float(v) for v in np.concatenate([1e3 * delta[:3], np.degrees(delta[3:])])],
                'sigma_mm_deg': [float(v) for v in np.concatenate([1e3 * s[:3], np.degrees(s[3:])])],
                'note': 'correction: position added, rotation vector applied about the frame origin, both in '
                        'the parent frame; sigma per component of it'}
        return out

    def _held_text(self) -> str:
        """How the MAP estimator holds the unidentifiable directions, for the export."""
        exact, parallel = self.identifiability.held_groups()
        std = self.map.fixed_std
        text = (f'at the initial guess by a prior of standard deviation {FIXED_STD:g} along each exact '
                f'direction ({exact.shape[1]})')
        if parallel.shape[1]:
            text += (f'; the {parallel.shape[1]} only parallel axes hide with standard deviation '
                     + ', '.join(f'{v:.3g}' for v in std[exact.shape[1]:]) + ' m (MAP)')
        return text

    def export(self, directory: str | Path, stem: str = 'calibrated') -> tuple[Path, Path]:
        """Write ``<stem>_dh.yaml`` (table with one-sigma, :mod:`calibration_interfaces.dh_file`; with a
        ``modified_dh`` section for a description in Craig's convention) and ``<stem>.urdf``, the formats
        of the description's ``exports`` (:func:`calibration_interfaces.robot_formats.write_exports`)
        and, for a description read from a URDF, that URDF with its joint origins corrected
        (``<stem>_<urdf name>.urdf``, :func:`body_schema.urdf_model.write_calibrated_urdf`); return the
        first two paths."""
        directory = Path(directory)
        n_dh = self.model.n_params
        sigma_all = np.sqrt(np.diag(self.P))
        sigma = sigma_all[:n_dh].reshape(self.model.dh.shape)
        ident = self.identifiability.as_dict()
        if self.identifiability.n_unidentifiable:
            ident['held'] = (self._held_text() if self.map is not None
                             else 'not held (EKF): the filter may drift along them')
            if self.extrinsics is not None:
                ident['held'] += ("; what the camera / marker absorb at the description's values")
        extra: dict[str, object] = {'updates': self.counters, 'identifiability': ident}
        if self.model.convention == 'modified':      # the estimate in the description's own convention
            mdh, flange = self.model.modified_table(self.dh)
            extra['modified_dh'] = modified_section(mdh, flange, self.model.joint_names, sigma)
        poses = self.extrinsic_poses()
        if poses is not None:
            extra.update(self._extrinsics_export(poses, sigma_all[n_dh:]))
        yaml_path = write_dh_file(directory / f'{stem}_dh.yaml', self.dh, self.model.joint_names,
                                  self.model.name, sigma, extra=extra)
        if poses is not None and 'camera' in self.extrinsics.blocks:
            tf = extrinsics_mod.static_transform(poses[0], self.model.root_frame, optical_frame(CAMERA))
            (directory / f'{stem}_camera_static_transform.yaml').write_text(yaml.safe_dump(tf, sort_keys=False))
        urdf_path = directory / f'{stem}.urdf'
        urdf_path.write_text(model_urdf(self.calibrated_model(), extra_links=self.frame_links()))
        # The robot stack's own formats the description asks for (UR kinematics YAML, iKin .ini).
        write_exports(directory, self.model, self.dh, stem)
        if self.model.urdf is not None:              # the description's own URDF, joint origins corrected
            from body_schema.urdf_model import write_calibrated_urdf

            write_calibrated_urdf(self.model, self.dh,
                                  directory / f'{stem}_{self.model.urdf.path.name.split(".")[0]}.urdf')
        return yaml_path, urdf_path

    def frame_links(self) -> tuple[FixedLink, ...]:
        """The fixed cameras' optical frames (on the root link) and the markers' frames (on the
        hand) for the calibrated URDF: where they are estimated, at the estimate, else at the
        description's poses. A head's eyes move with its joints and are not in the arm's URDF.

        The marker board's estimated offset ``M`` moves every marker with it:
        ``hand_T_marker_i = M M_nom^-1 hand_T_marker_i,nom``.
        """
        poses = self.extrinsic_poses()
        cameras = dict(self.model.fixed_cameras)
        board = np.eye(4)
        if poses is not None:
            if 'camera' in self.extrinsics.blocks and CAMERA in cameras:
                cameras[CAMERA] = poses[0]
            if 'marker' in self.extrinsics.blocks:
                board = poses[1] @ np.linalg.inv(self.extrinsics.marker)
        return tuple([FixedLink(optical_frame(name), self.model.root_frame, pose)
                      for name, pose in sorted(cameras.items())]
                     + [FixedLink(f'marker_{m.name}', 'hand', board @ m.hand_T_marker) for m in self.model.markers])
