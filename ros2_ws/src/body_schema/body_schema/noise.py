"""Measurement-noise models for hand-pose observations from fiducial markers (paper sec. IV-A-1).

The paper models the observation covariance as ``R = sigma^2 I`` with

    sigma^2 = a r^2 + b (phi - 45 deg)^2,

where ``r`` is the camera-to-marker distance [m] and ``phi`` [deg] the angle between the marker's
normal and the line from the marker's centre to the camera. Position (metres) and orientation
(radians) errors of ArUco poses differ by orders of magnitude, so :class:`PoseDependentNoise`
keeps one such law for each block, ``R = diag(s_p^2 I3, s_o^2 I3)``, plus a small floor so ``R``
stays positive definite at ``phi = 45 deg, r -> 0``. With equal coefficients and no floor it is
the paper's law exactly. :class:`ConstantNoise` is the paper's CN baseline.

A single camera measures a marker's position along its line of sight far worse than across it
(the depth comes from the marker's apparent size): on the Panda's 1280x1024 camera at 2 m the
residuals of a calibrated run were 2.5 mm RMS along the line of sight and 0.3 mm across it. With
``depth_ratio = k`` the position block is ``s_p^2 (I - l l^T) + k^2 s_p^2 l l^T``, ``l`` the unit
line of sight from the camera to the marker in the root frame, and the law's ``s_p`` is the
standard deviation across it; ``k = 1`` (the default) is the isotropic law above.

Two eyes that see the hand give one detection from both images' marker corners
(``marker_detector.detection.refine_stereo``): the baseline fixes the depth that one eye guesses from
the marker's size. Its covariance is the eyes' covariances fused as if independent,
``(R_1^-1 + R_2^-1)^-1``, with the position block scaled by the law's ``stereo_pos`` and the
orientation block by ``stereo_rot`` (variance ratios fitted by ``tools.fit_noise``;
:func:`stereo_covariance`).

Observations are ordered ``(p_x, p_y, p_z, w_x, w_y, w_z)`` as in :mod:`body_schema.kinematics`.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .robot import ArmModel, MarkerPlacement

__all__ = ['view_geometry', 'MarkerView', 'NoiseModel', 'PoseDependentNoise', 'ConstantNoise', 'NOISE_MODELS',
           'noise_model', 'sample_pose', 'line_of_sight_covariance', 'stereo_covariance', 'InnovationCheck',
           'innovation_check', 'CAUTION_ALPHA']

#: phi beyond which a marker is seen edge-on or from behind and cannot be detected [deg].
MAX_VIEW_ANGLE_DEG = 90.0

#: Significance of each test of a noise law against a run's innovations (:meth:`InnovationCheck.findings`):
#: a right law fails one in about twice this fraction of runs.
CAUTION_ALPHA = 1e-3


def view_geometry(camera_pose: ArrayLike, marker_pose: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Distance and viewing angle of marker(s) seen from a camera.

    Parameters
    ----------
    camera_pose : array_like, shape (4, 4)
        Camera frame in the root frame (only its origin matters).
    marker_pose : array_like, shape (..., 4, 4)
        Marker frame(s) in the root frame, z out of the printed face.

    Returns
    -------
    r : ndarray, shape (...)
        Distance camera-to-marker centre [m].
    phi : ndarray, shape (...)
        Angle between the marker normal and the direction marker -> camera [deg]; 0 is head-on,
        above 90 means the marker faces away.
    """
    cam = np.asarray(camera_pose, dtype=float)[:3, 3]
    m = np.asarray(marker_pose, dtype=float)
    to_cam = cam - m[..., :3, 3]
    # norm's and clip's own arithmetic without their wrappers: this runs four times in every cost evaluation.
    r = np.sqrt(np.add.reduce(to_cam * to_cam, axis=-1))
    normal = m[..., :3, 2]
    cos_phi = np.einsum('...i,...i->...', normal, to_cam) / np.maximum(r, 1e-12)
    return r, np.degrees(np.arccos(np.minimum(np.maximum(cos_phi, -1.0), 1.0)))


#: A camera's view of a hand's markers: their poses (..., M, 4, 4) and their :func:`view_geometry`
#: ``r``, ``phi`` (..., M). Computed once per cost evaluation, shared by the noise law and the
#: visibility prior.
MarkerView = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def _assemble(var_pos: ArrayLike, var_rot: ArrayLike) -> NDArray[np.float64]:
    """``diag(s_p^2 I3, s_o^2 I3)`` for variances of shape (...) -> (..., 6, 6)."""
    if np.ndim(var_pos) == 0 and np.ndim(var_rot) == 0:      # one pose: 5x cheaper (the selector's local search)
        out = np.zeros((6, 6))
        out.flat[0:21:7], out.flat[21::7] = var_pos, var_rot               # the two diagonal blocks
        return out
    vp, vo = np.broadcast_arrays(np.asarray(var_pos, dtype=float), np.asarray(var_rot, dtype=float))
    return np.stack([vp, vp, vp, vo, vo, vo], axis=-1)[..., None] * np.eye(6)


def line_of_sight_covariance(var_pos: ArrayLike, var_rot: ArrayLike, los: ArrayLike,
                             depth_ratio: float) -> NDArray[np.float64]:
    """``diag(s_p^2 (I - l l^T) + k^2 s_p^2 l l^T, s_o^2 I3)``: a position error ``k`` times larger
    along the line of sight ``l``.

    Parameters
    ----------
    var_pos, var_rot : array_like, shape (...)
        Position variance across the line of sight [m^2], orientation variance [rad^2].
    los : array_like, shape (..., 3)
        Line of sight from the camera to the marker (normalised here).
    depth_ratio : float
        ``k``, standard deviation along the line of sight over that across it.

    Returns
    -------
    ndarray, shape (..., 6, 6)
    """
    cov = _assemble(var_pos, var_rot)
    if depth_ratio == 1.0:
        return cov
    los = np.asarray(los, dtype=float)
    unit = los / np.linalg.norm(los, axis=-1, keepdims=True)
    outer = unit[..., :, None] * unit[..., None, :]
    vp = np.asarray(var_pos, dtype=float)[..., None, None]
    cov = np.array(cov)
    cov[..., :3, :3] = vp * (np.eye(3) + (depth_ratio ** 2 - 1.0) * outer)
    return cov


class NoiseModel(Protocol):
    """Anything that predicts the 6x6 covariance of a marker-based hand-pose observation."""

    #: Position standard deviation along the line of sight over that across it (1: isotropic).
    depth_ratio: float
    #: A stereo detection's position and orientation variance over the eyes' fused ones.
    stereo_pos: float
    stereo_rot: float

    def variances(self, r: ArrayLike, phi_deg: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Position [m^2] and orientation [rad^2] variances for distance ``r``, angle ``phi``."""

    def covariance(self, r: ArrayLike, phi_deg: ArrayLike) -> NDArray[np.float64]:
        """Observation covariance, shape (..., 6, 6)."""

    def hand_covariance(self, camera_pose: ArrayLike, hand_pose: ArrayLike,
                        markers: Sequence[MarkerPlacement],
                        view: MarkerView | None = None,
                        ) -> NDArray[np.float64]:
        """Predicted covariance of a hand observation, shape (..., 6, 6)."""


class _Base:
    """Shared plumbing: covariance assembly and prediction from a hand pose."""

    #: Position standard deviation along the line of sight over that across it (1: isotropic).
    depth_ratio: float = 1.0
    #: A stereo detection's variances over the eyes' fused ones (1: the fusion of independent eyes).
    stereo_pos: float = 1.0
    stereo_rot: float = 1.0

    def variances(self, r: ArrayLike, phi_deg: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        raise NotImplementedError

    def covariance(self, r: ArrayLike, phi_deg: ArrayLike) -> NDArray[np.float64]:
        """Observation covariance ``diag(s_p^2 I3, s_o^2 I3)``.

        Parameters
        ----------
        r, phi_deg : array_like, shape (...)

        Returns
        -------
        ndarray, shape (..., 6, 6)
        """
        return _assemble(*self.variances(r, phi_deg))

    def hand_covariance(self, camera_pose: ArrayLike, hand_pose: ArrayLike,
                        markers: Sequence[MarkerPlacement],
                        view: MarkerView | None = None,
                        ) -> NDArray[np.float64]:
        """Predicted covariance for a hand pose: the best-placed marker facing the camera.

        Among the markers facing the camera (``phi < 90 deg``), the one with the smallest
        predicted position variance is assumed to be used; if none faces it, the worst case
        ``phi = 90 deg`` of the nearest marker is returned (the occlusion model, not this one,
        accounts for the likely failure). With a ``depth_ratio`` the position block is stretched
        along that marker's line of sight (:func:`line_of_sight_covariance`).

        Parameters
        ----------
        camera_pose : array_like, shape (4, 4)
        hand_pose : array_like, shape (..., 4, 4)
        markers : sequence of MarkerPlacement
        view : tuple of ndarray, optional
            The markers' poses ``hand_pose @ hand_T_marker`` (..., M, 4, 4) and their
            :func:`view_geometry` ``r, phi`` (..., M), when the caller has them already (the
            selector's cost shares them with the visibility prior).

        Returns
        -------
        ndarray, shape (..., 6, 6)
        """
        if not markers:
            raise ValueError('hand_covariance needs at least one marker placement')
        hand = np.asarray(hand_pose, dtype=float)
        camera = np.asarray(camera_pose, dtype=float)
        if view is None:
            mk = np.stack([m.hand_T_marker for m in markers])      # (M, 4, 4)
            poses = hand[..., None, :, :] @ mk                      # (..., M, 4, 4)
            r, phi = view_geometry(camera_pose, poses)              # (..., M)
        else:
            poses, r, phi = view
        phi = np.minimum(phi, MAX_VIEW_ANGLE_DEG)
        vp, vo = self.variances(r, phi)
        if np.shape(vp) != np.shape(vo):
            vp, vo = np.broadcast_arrays(vp, vo)
        rank = np.where(phi < MAX_VIEW_ANGLE_DEG, vp, np.inf)
        k = self.depth_ratio
        if hand.ndim == 2:          # one pose: plain indexing (this runs in every cost evaluation)
            best = int(np.argmin(rank)) if np.isfinite(rank.min()) else int(np.argmin(r))
            return line_of_sight_covariance(vp[best], vo[best], poses[best, :3, 3] - camera[:3, 3], k)
        best = np.argmin(rank, axis=-1)
        # No marker facing the camera: fall back to the nearest one seen edge-on.
        best = np.where(np.isinf(np.take_along_axis(rank, best[..., None], -1)[..., 0]),
                        np.argmin(r, axis=-1), best)[..., None]
        los = np.take_along_axis(poses[..., :3, 3], best[..., None], -2)[..., 0, :] - camera[:3, 3]
        return line_of_sight_covariance(np.take_along_axis(vp, best, -1)[..., 0],
                                        np.take_along_axis(vo, best, -1)[..., 0], los, k)


#: The built-in law's stereo variance ratios (position, orientation): ``tools.fit_noise.stereo_ratios``
#: against the built-in law, on 300 configurations of the iCub's box (seed 1, no pixel noise) seen by
#: its 320x240 eyes with 3 cm markers.
STEREO_POS, STEREO_ROT = 0.124, 1.40


@functools.lru_cache(maxsize=8)
def _stereo_scale(stereo_pos: float, stereo_rot: float) -> NDArray[np.float64]:
    """Square roots of the stereo ratios per pose component (6,), read-only (every cost evaluation)."""
    scale = np.sqrt(np.repeat([stereo_pos, stereo_rot], 3))
    scale.setflags(write=False)
    return scale


def stereo_covariance(covariances: ArrayLike, model: NoiseModel) -> NDArray[np.float64]:
    """The covariance of one detection from several eyes' marker corners.

    The eyes' covariances fused as if independent, ``(sum_k R_k^-1)^-1``, with the position block
    scaled by ``model.stereo_pos`` and the orientation block by ``model.stereo_rot``: the joint
    refinement measures depth by triangulation, which no fusion of monocular poses does.

    Parameters
    ----------
    covariances : array_like, shape (..., K, 6, 6)
        Each eye's covariance of the hand pose (``K >= 2``).
    model : NoiseModel

    Returns
    -------
    ndarray, shape (..., 6, 6)
    """
    c = np.asarray(covariances, dtype=float)
    if c.ndim < 3 or c.shape[-2:] != (6, 6) or c.shape[-3] < 2:
        raise ValueError(f'stereo_covariance needs (..., K >= 2, 6, 6) covariances, got shape {c.shape}')
    fused = np.linalg.inv(np.linalg.inv(c).sum(axis=-3))
    scale = _stereo_scale(model.stereo_pos, model.stereo_rot)
    fused = fused * scale[:, None] * scale[None, :]
    return 0.5 * (fused + np.swapaxes(fused, -1, -2))


@dataclass(frozen=True)
class PoseDependentNoise(_Base):
    """``s^2 = a r^2 + b (phi - 45)^2 + floor``, one law for position and one for orientation.

    Units: ``a_pos`` [m^2/m^2], ``b_pos`` [m^2/deg^2], ``a_rot`` [rad^2/m^2],
    ``b_rot`` [rad^2/deg^2], floors in [m^2] and [rad^2]. Defaults are fitted to the
    simulator's detector (see the accuracy study in the marker_detector README). ``depth_ratio``
    (> 0): the position's standard deviation along the line of sight over that across it, which
    the position law then describes (1: the isotropic law). ``stereo_pos``, ``stereo_rot`` (> 0): a
    stereo detection's position and orientation variances over the two eyes' fused ones
    (:func:`stereo_covariance`; the defaults are fitted on the iCub's eyes, pixel noise 0).
    """

    a_pos: float = 2.1e-5
    b_pos: float = 0.0
    a_rot: float = 9.6e-4
    b_rot: float = 2.3e-7
    floor_pos: float = 1e-8
    floor_rot: float = 2.7e-7
    depth_ratio: float = 1.0
    stereo_pos: float = STEREO_POS
    stereo_rot: float = STEREO_ROT

    def __post_init__(self) -> None:
        for name in ('a_pos', 'b_pos', 'a_rot', 'b_rot', 'floor_pos', 'floor_rot'):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f'PoseDependentNoise.{name} must be finite and >= 0, got {v}')
        for name in ('depth_ratio', 'stereo_pos', 'stereo_rot'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'PoseDependentNoise.{name} must be finite and > 0, got {v}')
        if self.floor_pos == 0 and self.floor_rot == 0 and (self.b_pos == 0 or self.b_rot == 0):
            raise ValueError('PoseDependentNoise: with zero floors and b = 0 the covariance can be '
                             'singular; give a positive floor')

    @classmethod
    def for_robot(cls, model: ArmModel, **overrides: float) -> 'PoseDependentNoise':
        """The law fitted for a description's camera and marker (its ``noise_model:`` block,
        ``python -m tools.fit_noise``), the built-in defaults for coefficients it does not set,
        then ``overrides`` (e.g. a node's ``pdn_*`` parameters)."""
        return cls(**{**model.noise_law, **overrides})

    @classmethod
    def paper(cls, a: float, b: float) -> 'PoseDependentNoise':
        """The paper's single law ``R = (a r^2 + b (phi - 45)^2) I6`` (no floor)."""
        return cls(a, b, a, b, 0.0, 0.0)

    def variances(self, r: ArrayLike, phi_deg: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        r = np.asarray(r, dtype=float)
        dphi2 = (np.asarray(phi_deg, dtype=float) - 45.0) ** 2
        return (self.a_pos * r ** 2 + self.b_pos * dphi2 + self.floor_pos,
                self.a_rot * r ** 2 + self.b_rot * dphi2 + self.floor_rot)


@dataclass(frozen=True)
class ConstantNoise(_Base):
    """The CN baseline: the same covariance for every observation.

    Defaults are the constant fitted by maximum likelihood to the same detector errors as
    :class:`PoseDependentNoise` (1.53 mm, 0.74 deg), so CN vs pose-dependent compares laws,
    not levels.
    """

    sigma_pos: float = 0.00153
    sigma_rot: float = float(np.radians(0.74))

    def __post_init__(self) -> None:
        for name in ('sigma_pos', 'sigma_rot'):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f'ConstantNoise.{name} must be finite and > 0, got {v}')

    def variances(self, r: ArrayLike, phi_deg: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        shape = np.broadcast(np.asarray(r), np.asarray(phi_deg)).shape
        return (np.full(shape, self.sigma_pos ** 2), np.full(shape, self.sigma_rot ** 2))


#: The names of the noise models, as every node parameter, CLI flag and config file spells them.
NOISE_MODELS: tuple[str, ...] = ('pose_dependent', 'constant')


def noise_model(kind: str, **params: float) -> PoseDependentNoise | ConstantNoise:
    """Build a noise model by name (one of :data:`NOISE_MODELS`): ``"pose_dependent"`` or
    ``"constant"`` (the paper's CN baseline)."""
    if kind == 'pose_dependent':
        return PoseDependentNoise(**params)
    if kind == 'constant':
        return ConstantNoise(**params)
    raise ValueError(f'unknown noise model {kind!r}; expected one of {list(NOISE_MODELS)}')


def sample_pose(pose: ArrayLike, cov: ArrayLike, rng: np.random.Generator) -> NDArray[np.float64]:
    """A noisy observation of ``pose`` drawn from ``N(0, cov)`` in the residual's coordinates.

    The position is offset by ``e[:3]`` and the rotation left-multiplied by ``exp([e[3:]]x)``,
    so ``(p_z - p, log(R_z R^T)) = e``: exactly the noise the estimators' residual assumes.

    Parameters
    ----------
    pose : array_like, shape (4, 4)
    cov : array_like, shape (6, 6)
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (4, 4)
    """
    from scipy.spatial.transform import Rotation

    e = rng.multivariate_normal(np.zeros(6), np.asarray(cov, dtype=float))
    z = np.array(pose, dtype=float)
    z[:3, 3] += e[:3]
    z[:3, :3] = Rotation.from_rotvec(e[3:]).as_matrix() @ z[:3, :3]
    return z


@dataclass(frozen=True)
class InnovationCheck:
    """How a run's innovations compare with what its noise law promises (:func:`innovation_check`).

    Attributes
    ----------
    count : int
        Innovations looked at (those after the skipped warm-up).
    median : float
        Their median NIS; 5.35 (the chi-square median, 6 dof) if the law is right.
    beyond : int
        How many exceed ``bound``.
    probability : float
        The chi-square probability of ``bound``.
    bound : float
        The NIS bound, ``chi2.ppf(probability, 6)``.
    """

    count: int
    median: float
    beyond: int
    probability: float
    bound: float

    @property
    def expected_beyond(self) -> float:
        """How many of :attr:`count` a consistent law puts beyond :attr:`bound`."""
        return self.count * (1.0 - self.probability)

    def text(self) -> str:
        """One line for a report."""
        return (f'innovations after the warm-up: median NIS {self.median:.1f} (5.3 if the noise law is right, '
                f'6 dof), beyond the {self.probability:.2%} bound in {self.beyond} of {self.count} '
                f'({self.expected_beyond:.3f} expected)')

    def tail_p_value(self) -> float:
        """Chance of :attr:`beyond` or more exceedances under a right law (Poisson, mean
        :attr:`expected_beyond`); 1.0 when there is none."""
        from scipy.stats import poisson

        return float(poisson.sf(self.beyond - 1, self.expected_beyond)) if self.beyond > 0 else 1.0

    def high_median_p_value(self) -> float:
        """Chance under a right law of a median NIS as high as :attr:`median` or higher.

        A median at least ``m`` needs at least ``ceil(count / 2)`` of the NIS at or above ``m``
        (odd or even count), each with chi-square(6) probability ``sf(m)``: the binomial tail,
        an upper bound of the p-value.
        """
        from scipy.stats import binom, chi2

        return float(binom.sf(-(-self.count // 2) - 1, self.count, chi2.sf(self.median, 6)))

    def findings(self, alpha: float = CAUTION_ALPHA) -> list[str]:
        """The tests the law fails at significance ``alpha``: ``'tails'`` (too many exceedances,
        :meth:`tail_p_value`) and ``'median'`` (too high a median, :meth:`high_median_p_value`).

        Raises
        ------
        ValueError
            If ``alpha`` is not in (0, 1).
        """
        if not 0.0 < alpha < 1.0:
            raise ValueError(f'InnovationCheck: alpha must be in (0, 1), got {alpha}')
        return [name for name, p in (('tails', self.tail_p_value()), ('median', self.high_median_p_value()))
                if p < alpha]

    def cautions(self, alpha: float = CAUTION_ALPHA) -> list[str]:
        """What the innovations say against the noise law, at significance ``alpha``.

        Two findings make the covariance of the estimate optimistic: exceedances of the bound far
        beyond the expected count (the law is too sure of some observations: a heavy-tailed
        detector; the change test then raises false alarms) and a median NIS above the
        chi-square median (the law understates the typical error, or the estimate's covariance
        ``P`` is too small: the EKF's linearisation). A median below it alone (a
        cautious law) is not reported: it costs precision, not trust.

        Parameters
        ----------
        alpha : float
            Significance of each test, in (0, 1).

        Returns
        -------
        list of str
            One sentence per finding; empty when the innovations agree with the law.

        Raises
        ------
        ValueError
            If ``alpha`` is not in (0, 1).
        """
        found = self.findings(alpha)
        out = []
        if 'tails' in found:
            out.append(f'{self.beyond} of {self.count} innovations beyond the {self.probability:.2%} bound '
                       f'({self.expected_beyond:.3f} expected, p = {self.tail_p_value():.1e}): the noise law is '
                       'too sure of some observations (heavier tails than it assumes), so the final covariance, '
                       'NEES and information limit are optimistic and the change test can raise false alarms')
        if 'median' in found:
            out.append(f'median NIS {self.median:.1f} against 5.3 for a right law (p = '
                       f'{self.high_median_p_value():.1e}): the typical innovation is larger than the noise law '
                       'and the estimate\'s covariance predict (a law that understates the typical error, or an '
                       'estimator too sure of itself), so the final covariance, NEES and information limit are '
                       'optimistic')
        return out


def innovation_check(nis: Sequence[float], skip: int = 0, probability: float = 0.9999) -> InnovationCheck | None:
    """The truth-free consistency check of a noise law: a run's normalised innovations squared.

    Each update's innovation ``y`` (observed minus predicted hand pose, 6 components) with its
    predicted covariance ``S = H P H^T + R`` gives ``NIS = y^T S^-1 y``, chi-square with 6 dof when
    the law's ``R`` and the estimate's ``P`` are right. A law that understates the detector's
    tails puts far more than ``1 - probability`` of them beyond the bound, and the MAP estimator's
    change test, which counts exceedances of that bound, then raises false alarms.

    Parameters
    ----------
    nis : sequence of float, length N
        NIS of each update, in order (``dh_estimator``'s ``OnlineEstimator.innovations``).
    skip : int
        Leading updates left out: the warm-up, whose innovations are large because the guess is
        far (the change test ignores them too).
    probability : float
        Chi-square probability of the bound, in (0, 1) (the change test's ``change_probability``).

    Returns
    -------
    InnovationCheck or None
        None if no innovation remains after ``skip``.

    Raises
    ------
    ValueError
        If ``skip`` is negative or ``probability`` is not in (0, 1).
    """
    from scipy.stats import chi2

    if skip < 0:
        raise ValueError(f'innovation_check: skip must be >= 0, got {skip}')
    if not 0.0 < probability < 1.0:
        raise ValueError(f'innovation_check: probability must be in (0, 1), got {probability}')
    v = np.asarray(nis, dtype=float)[skip:]
    if v.size == 0:
        return None
    bound = float(chi2.ppf(probability, 6))
    return InnovationCheck(int(v.size), float(np.median(v)), int(np.sum(v > bound)), probability, bound)
