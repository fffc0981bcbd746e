"""Active selection of the next joint configuration (paper sec. III-B, plus extensions).

Information gain. With ``H`` the 6 x n pose Jacobian w.r.t. the DH parameters at ``theta``,
``B = H P`` (6 x n) and ``S = H P H^T + R(theta)`` (``R`` the noise model's prediction for the hand
pose the current estimate expects at ``theta``), one observation removes

    g(theta) = tr(S^-1 B A B^T)

from ``tr(A P)``, the weighted uncertainty that a criterion measures:

* ``criterion='a_optimal'`` (the paper's, eq. costPmatrix): ``A = I``, so ``g = tr(P) - C0`` with
  ``C0 = tr(P_post)`` the expected trace after the update;
* ``criterion='v_optimal'`` (beyond the paper): ``A = mean_i J_i^T W J_i`` over ``M`` box
  configurations (``J_i`` the pose Jacobian at configuration ``i``, ``W = diag(1/s_pos^2 I3,
  1/s_rot^2 I3)`` with the detector's noise scales), so ``tr(A P)`` is the predicted hand-pose
  variance averaged over the calibration box, in units of the detector's noise, and ``g`` its
  expected reduction. ``A`` is computed once per cost (per selection) at the current estimate.

Occlusion (``eta`` the occlusion model's success probability) and the penalty for hands behind
the body (root x points backward), ``pen = a * arctan(b * p_x)``, combine as

* ``occlusion_mode='paper'`` (eq. changedActiveLearning): ``C = (tr(A P) - g) / eta + pen``;
* ``occlusion_mode='expected'``: the expected posterior uncertainty when the attempt fails with
  probability ``1 - eta``, ``C = tr(A P) - eta g + pen``;
* ``occlusion_mode='gain'``: ``C = -eta g / tr(A P) + pen``: occlusion discounts a pick's value
  instead of dividing the whole (mostly constant) trace. The gain is taken relative to the current
  uncertainty so the penalty keeps the same weight as ``P`` shrinks over a run: ``eta g / tr(A P)``
  is the expected fraction of the uncertainty one attempt removes. Measured over the box on recorded
  AL states (iterations 10-45), it spans about 0.02-0.09 (a-optimal) and 0.04-0.17 (v-optimal)
  between its 5th and 95th percentiles, while ``0.05 arctan(10 p_x)`` spans 0.006-0.014: the
  default penalty breaks near-ties towards hands in front of the body without overriding the gain.
  (In the paper's form ``1 / eta`` varies about twice as much, in log terms, as ``C0`` does, so
  the occlusion model rather than the information decides the pick.)

``eta`` is the occlusion model's posterior mean; with a :class:`~body_schema.occlusion.VisibilityPrior`
its prior mean at each candidate is the geometric prediction from the current estimate (markers
facing the camera inside the image), widened by the predicted hand-pose covariance ``H P H^T``
already computed for the gain, instead of the paper's flat ``a0 / (a0 + b0)``.

Two cameras (the iCub's eyes, whose images the detector combines): the cost takes both poses;
``eta``'s prior is the probability that either eye sees the hand, and ``g`` the expected gain of
the detection the attempt gives when it succeeds: the stereo one when both eyes see the hand, one
eye's when only it does (:meth:`AcquisitionCost.terms_batch`). With one occlusion model per eye
(``eye_occlusion``), each eye's probability is its own model's posterior mean over that eye's
geometric prior, and ``eta`` the probability that either sees the hand.

Strategies:

* ``random`` (R): uniform in the calibration box.
* ``al`` (AL, eq. ALgeneralCost): minimise ``C`` over the box.
* ``ucsal`` (UCSAL, eq. csALgeneralCost): minimise ``C + gamma * d(theta, theta_prev)``, with ``d``
  the **L1 norm in normalised joint space** (each joint scaled to [0, 1] by the box), the same
  norm as the accumulated-movement metric, made unit-free so joints with wide ranges do not
  dominate.
* ``ccsal`` (CCSAL, eq. ALConstrained): minimise ``C`` over ``box ∩ [u_prev - delta, u_prev + delta]``
  in normalised units.

Optimisers: ``optimizer='direct'`` is the paper's global DIRECT family through NLopt (DIRECT-L by
default; deterministic, the randomised variant seeded through ``nlopt.srand``), one configuration
per evaluation. ``optimizer='batch'`` evaluates a seeded scrambled Sobol set of candidates in one
vectorised pass (batched frames, Jacobians, noise prediction, 6x6 solves, occlusion means), then
refines the best few with a short bounded derivative-free NLopt search (BOBYQA by default).

Safety: with a :class:`SafetyCheck` (e.g. :class:`body_schema.collision.CollisionModel`) the
selection never returns a configuration inside the collision margins, nor one whose straight
joint-space path from where the arm is leaves them. The search itself is unchanged (its cost
would not allow a check at every evaluation); its evaluated points are checked best-first (the
batch optimiser's refinement starts and local steps too, which are few) and the best safe one is
selected. :attr:`Selection.refused` and :attr:`Selection.refused_paths` count the better points
refused on the way.

No repeats: a configuration within ``repeat_tolerance`` (max-abs over joints, rad) of any visited
configuration is never selected (DIRECT sees a huge value there, the batch masks it), since the
simulator would render the same image and the observation would teach nothing new.
"""
from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import nlopt
import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg
from scipy.spatial import cKDTree
from scipy.stats import qmc

from . import kinematics
from .extrinsics import Extrinsics
from .noise import ConstantNoise, MarkerView, NoiseModel, stereo_covariance, view_geometry
from .occlusion import OcclusionModel, VisibilityPrior
from .robot import MarkerPlacement
from .sampling import as_rng

__all__ = ['Strategy', 'DIRECT_ALGORITHMS', 'LOCAL_ALGORITHMS', 'CRITERIA', 'OCCLUSION_MODES',
           'OPTIMIZERS', 'DETECTOR_NOISE_SCALES', 'information_gain', 'expected_trace',
           'box_pose_weight', 'AcquisitionCost', 'SelectorConfig', 'Selection', 'SafetyCheck', 'UnsafeSelection',
           'JointSelector']

class SafetyCheck(Protocol):
    """What the selector asks before it returns a target (see :class:`body_schema.collision.CollisionModel`)."""

    def clear(self, q: ArrayLike) -> NDArray[np.bool_] | bool:
        """Whether configurations (L,) or (N, L) keep the margins."""

    def path_clear(self, q0: ArrayLike, q1: ArrayLike) -> object:
        """Whether the straight joint-space path from ``q0`` (where the arm is) to ``q1`` keeps them
        (an object with a boolean ``clear``)."""


class UnsafeSelection(RuntimeError):
    """No evaluated configuration was safe to command (all inside a margin or behind one)."""


class Strategy(str, enum.Enum):
    """Joint-selection strategies of the paper."""

    RANDOM = 'random'
    AL = 'al'
    UCSAL = 'ucsal'
    CCSAL = 'ccsal'

    @classmethod
    def parse(cls, name: str) -> 'Strategy':
        try:
            return cls(name.lower())
        except ValueError:
            raise ValueError(f'unknown strategy {name!r}; expected one of '
                             f'{[s.value for s in cls]}') from None


#: NLopt global algorithms accepted by name (``optimizer='direct'``).
DIRECT_ALGORITHMS = {
    'DIRECT': nlopt.GN_DIRECT,
    'DIRECT_L': nlopt.GN_DIRECT_L,
    'DIRECT_L_RAND': nlopt.GN_DIRECT_L_RAND,
    'DIRECT_NOSCAL': nlopt.GN_DIRECT_NOSCAL,
    'DIRECT_L_NOSCAL': nlopt.GN_DIRECT_L_NOSCAL,
    'ORIG_DIRECT': nlopt.GN_ORIG_DIRECT,
    'ORIG_DIRECT_L': nlopt.GN_ORIG_DIRECT_L,
}

#: NLopt bounded derivative-free local algorithms for the batch optimiser's refinement.
LOCAL_ALGORITHMS = {
    'BOBYQA': nlopt.LN_BOBYQA,
    'SBPLX': nlopt.LN_SBPLX,
    'NELDERMEAD': nlopt.LN_NELDERMEAD,
    'COBYLA': nlopt.LN_COBYLA,
}

CRITERIA = ('a_optimal', 'v_optimal')
OCCLUSION_MODES = ('paper', 'expected', 'gain')
OPTIMIZERS = ('direct', 'batch')

#: Position [m] and orientation [rad] noise scales of the detector (the constant fitted to its
#: errors, :class:`~body_schema.noise.ConstantNoise`): v-optimality's weights ``W``.
DETECTOR_NOISE_SCALES = (ConstantNoise.sigma_pos, ConstantNoise.sigma_rot)

#: What DIRECT sees at a visited or non-finite point: worse than any real cost, never chosen.
_EXCLUDED = 1e300


def information_gain(hp: NDArray[np.float64], s: NDArray[np.float64],
                     weight: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Expected reduction ``tr(S^-1 B A B^T)`` of ``tr(A P)`` by one observation.

    Parameters
    ----------
    hp : ndarray, shape (..., m, n)
        ``B = H P``.
    s : ndarray, shape (..., m, m)
        Innovation covariance ``H P H^T + R``.
    weight : ndarray, shape (n, n), optional
        Symmetric ``A``; ``None`` is the identity (A-optimality).

    Returns
    -------
    ndarray, shape (...)
    """
    bw = hp if weight is None else hp @ weight                   # B A, (..., m, n)
    # Solve against the m x m product B A B^T rather than B: m right-hand sides instead of n.
    m = bw @ np.swapaxes(hp, -1, -2)
    return np.einsum('...ii->...', np.linalg.solve(s, m))


def expected_trace(P: NDArray[np.float64], H: NDArray[np.float64], R: NDArray[np.float64],  # noqa: N803
                   trace_P: float | None = None) -> float:  # noqa: N803
    """Trace of the covariance after one update, without forming it.

    Parameters
    ----------
    P : ndarray, shape (n, n)
    H : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
    trace_P : float, optional
        ``tr(P)`` if already known.

    Returns
    -------
    float
        ``tr(P) - tr((H P)^T S^-1 (H P))``.
    """
    hp = H @ P
    gain = float(information_gain(hp, hp @ H.T + R))
    return (float(np.trace(P)) if trace_P is None else trace_P) - gain


def box_pose_weight(base: ArrayLike, dh: ArrayLike, box_configs: ArrayLike,
                    noise_scales: tuple[float, float] = DETECTOR_NOISE_SCALES) -> NDArray[np.float64]:
    """``A = mean_i J_i^T W J_i``: hand-pose variance over configurations per unit parameter covariance.

    ``tr(A P)`` is the predicted hand-pose variance averaged over ``box_configs``, position and
    orientation each in units of the detector's noise.

    Parameters
    ----------
    base : array_like, shape (4, 4)
    dh : array_like, shape (L, 4)
    box_configs : array_like, shape (M, L)
    noise_scales : (float, float)
        ``(s_pos [m], s_rot [rad])``; ``W = diag(1/s_pos^2 I3, 1/s_rot^2 I3)``.

    Returns
    -------
    ndarray, shape (4 L, 4 L)
    """
    s_pos, s_rot = (float(v) for v in noise_scales)
    if not (np.isfinite(s_pos) and np.isfinite(s_rot) and s_pos > 0 and s_rot > 0):
        raise ValueError(f'noise_scales must be two finite positive numbers, got {noise_scales}')
    q = np.asarray(box_configs, dtype=float)
    if q.ndim != 2 or q.shape[0] == 0:
        raise ValueError(f'box_configs must have shape (M, L) with M >= 1, got {q.shape}')
    jac = kinematics.pose_jacobian_dh(base, dh, q)               # (M, 6, n)
    w = np.array([s_pos ** -2] * 3 + [s_rot ** -2] * 3)
    return np.einsum('mki,k,mkj->ij', jac, w, jac) / q.shape[0]


@dataclass
class AcquisitionCost:
    """The selection cost ``C(theta)`` for the current estimate (see the module docstring).

    Parameters
    ----------
    base : ndarray, shape (4, 4)
    dh : ndarray, shape (L, 4)
        Current DH estimate.
    P : ndarray, shape (4 L, 4 L)
        Current estimate covariance.
    noise : NoiseModel
        Predicts ``R(theta)`` from the expected hand pose.
    camera_pose : ndarray, shape (4, 4) or (2, 4, 4)
        Camera optical frame in the root frame; two stacked for a stereo pair whose images give one
        detection (an attempt succeeds when either camera sees the hand; see :meth:`terms_batch`).
    markers : sequence of MarkerPlacement
    occlusion : OcclusionModel, optional
        ``eta(theta)``; ``None`` means ``eta = 1`` (or the visibility prior alone, if given).
    visibility : VisibilityPrior, optional
        Geometric prior mean of ``eta`` from the current estimate and its predicted hand-pose
        covariance ``H P H^T``; ``None``: the occlusion model's flat prior.
    visibility_weight : float
        Weight ``w`` of the geometric prior: ``eta``'s prior mean is ``w p_geo + (1 - w) a0 / (a0 + b0)``
        (see :meth:`~body_schema.occlusion.OcclusionModel.geometric_evidence`).
    penalty_a, penalty_b : float
        ``a * arctan(b * p_x)`` penalty (``a = 0`` disables it).
    occlusion_mode : {'paper', 'expected', 'gain'}
    criterion : {'a_optimal', 'v_optimal'}
    box_configs : ndarray, shape (M, L), optional
        Configurations the v-optimal criterion averages over (required for it).
    noise_scales : (float, float)
        Detector noise scales ``(s_pos [m], s_rot [rad])`` weighting v-optimality.
    extrinsics : Extrinsics, optional
        Camera / marker corrections the estimator estimates with the table: ``P`` is then
        ``(4 L + e)`` square (table first), the observation Jacobian includes their columns (at zero
        correction) and only the table's uncertainty is scored, so a configuration whose
        information would go to the camera pose is not mistaken for one that calibrates the arm.
        One camera only.
    eye_correlation : float
        With two cameras, how the visibility of one follows the other's, in [0, 1]: the
        probability both see the hand is ``c min(p_1, p_2) + (1 - c) p_1 p_2`` (0: independent, 1:
        the camera that sees less sees only when the other does).
    eye_occlusion : (OcclusionModel, OcclusionModel), optional
        With two cameras: one occlusion model per camera, each learning where its own camera saw
        the hand. Given, each camera's ``p_k`` is its model's posterior mean (with that camera's
        geometric prior, when there is a visibility prior) and the attempt's success probability
        ``eta`` is the probability that either camera sees the hand; ``occlusion`` is then not used.
    eye_visibility_weights : (float, float)
        Per camera, what ``visibility_weight`` is for the shared model (with ``eye_occlusion``).
    """

    base: NDArray[np.float64]
    dh: NDArray[np.float64]
    P: NDArray[np.float64]
    noise: NoiseModel
    camera_pose: NDArray[np.float64]
    markers: Sequence[MarkerPlacement]
    occlusion: OcclusionModel | None = None
    visibility: VisibilityPrior | None = None
    visibility_weight: float = 1.0
    penalty_a: float = 0.0
    penalty_b: float = 1.0
    occlusion_mode: str = 'paper'
    criterion: str = 'a_optimal'
    box_configs: NDArray[np.float64] | None = None
    noise_scales: tuple[float, float] = DETECTOR_NOISE_SCALES
    extrinsics: Extrinsics | None = None
    eye_correlation: float = 0.6
    eye_occlusion: tuple[OcclusionModel, OcclusionModel] | None = None
    eye_visibility_weights: tuple[float, float] = (1.0, 1.0)
    weight: NDArray[np.float64] | None = field(init=False, repr=False)
    uncertainty: float = field(init=False, repr=False)
    _marker_frames: NDArray[np.float64] = field(init=False, repr=False)
    _cameras: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.dh = np.asarray(self.dh, dtype=float)
        self.P = np.asarray(self.P, dtype=float)
        self._cameras = np.asarray(self.camera_pose, dtype=float).reshape(-1, 4, 4)
        if not 1 <= len(self._cameras) <= 2 or np.shape(self.camera_pose)[-2:] != (4, 4):
            raise ValueError(f'camera_pose must have shape (4, 4) or (2, 4, 4), got {np.shape(self.camera_pose)}')
        if len(self._cameras) == 2 and self.extrinsics is not None:
            raise ValueError('extrinsics are estimated for one camera; got a stereo pair of camera poses')
        if not 0.0 <= self.eye_correlation <= 1.0:
            raise ValueError(f'eye_correlation must be in [0, 1], got {self.eye_correlation}')
        if self.eye_occlusion is not None and (len(self._cameras) != 2 or len(self.eye_occlusion) != 2):
            raise ValueError(f'eye_occlusion needs two cameras and two models, got {len(self._cameras)} '
                             f'camera(s) and {len(self.eye_occlusion)} model(s)')
        if len(self.eye_visibility_weights) != 2 or not all(0.0 <= w <= 1.0 for w in self.eye_visibility_weights):
            raise ValueError(f'eye_visibility_weights must be two values in [0, 1], got {self.eye_visibility_weights}')
        n_extra = 0 if self.extrinsics is None else self.extrinsics.n
        n = self.dh.size + n_extra
        if self.P.shape != (n, n):
            raise ValueError(f'P must have shape ({n}, {n}) for a {self.dh.shape} DH table'
                             + (f' and {n_extra} extrinsic corrections' if n_extra else '') + f', got {self.P.shape}')
        if not (np.all(np.isfinite(self.dh)) and np.all(np.isfinite(self.P))):
            raise ValueError('estimate or covariance contains NaN or inf')
        self._marker_frames = (np.stack([m.hand_T_marker for m in self.markers]) if self.markers
                               else np.zeros((0, 4, 4)))
        if self.visibility is not None and not self.markers:
            raise ValueError('a visibility prior needs at least one marker placement')
        if not 0.0 <= self.visibility_weight <= 1.0:
            raise ValueError(f'visibility_weight must be in [0, 1], got {self.visibility_weight}')
        if self.occlusion_mode not in OCCLUSION_MODES:
            raise ValueError(f'occlusion_mode must be one of {OCCLUSION_MODES}, got {self.occlusion_mode!r}')
        if self.criterion not in CRITERIA:
            raise ValueError(f'criterion must be one of {CRITERIA}, got {self.criterion!r}')
        if self.criterion == 'v_optimal':
            if self.box_configs is None:
                raise ValueError("criterion 'v_optimal' needs box_configs, the (M, L) configurations "
                                 'it averages the hand-pose variance over')
            self.weight = box_pose_weight(self.base, self.dh, self.box_configs, self.noise_scales)
            if n_extra:
                self.weight = scipy.linalg.block_diag(self.weight, np.zeros((n_extra, n_extra)))
            self.uncertainty = float(np.sum(self.weight * self.P))      # tr(A P), both symmetric
        elif n_extra:
            self.weight = np.diag(np.concatenate([np.ones(self.dh.size), np.zeros(n_extra)]))
            self.uncertainty = float(np.sum(self.weight * self.P))
        else:
            self.weight = None
            self.uncertainty = float(np.trace(self.P))
        if not self.uncertainty > 0:
            raise ValueError(f'the current uncertainty tr(A P) must be > 0, got {self.uncertainty}')

    def terms_batch(self, thetas: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                      NDArray[np.float64]]:
        """Gain, success probability and hand x for a batch of configurations.

        With two cameras, ``gain`` is the expected gain given that the attempt succeeds: over the
        outcomes "both cameras see the hand" (one detection from both images:
        :func:`~body_schema.noise.stereo_covariance`, ``(R_1^-1 + R_2^-1)^-1`` scaled by the law's stereo ratios)
        and "only camera k does" (``R_k``), weighted by the cameras' geometric visibilities
        (:attr:`eye_correlation`) or, without a visibility prior, assuming both see it; the
        visibility prior is then the probability that either camera sees the hand.

        Parameters
        ----------
        thetas : array_like, shape (N, L)

        Returns
        -------
        gain, eta, p_x : ndarray, each shape (N,)
        """
        frames = kinematics.chain_frames(self.base, self.dh, np.atleast_2d(thetas))   # (N, L+1, 4, 4)
        hand = frames[:, -1]
        H = self._jacobian(frames)                                               # (N, 6, n)  # noqa: N806
        hp = H @ self.P
        hph = hp @ np.swapaxes(H, -1, -2)                                        # predicted pose covariance
        views = self._views(hand)
        if len(self._cameras) == 1:
            R = self._covariance(self._cameras[0], hand, views[0])                      # noqa: N806
            gain = information_gain(hp, hph + R, self.weight)
            prior = None if self.visibility is None else self._visibility(hand, hph, view=views[0])
        else:
            gain, prior = self._stereo_terms(hand, hp, hph, thetas, views)
            if self.eye_occlusion is not None:
                return gain, prior, hand[:, 0, 3]                             # each camera's own model
        if self.occlusion is not None:
            if prior is not None and self.visibility_weight < 1.0:
                flat = self.occlusion.a0 / (self.occlusion.a0 + self.occlusion.b0)
                prior = self.visibility_weight * prior + (1.0 - self.visibility_weight) * flat
            eta = np.asarray(self.occlusion.mean(np.atleast_2d(thetas), prior), dtype=float)
        else:
            eta = np.ones(hand.shape[0]) if prior is None else prior
        return gain, eta, hand[:, 0, 3]

    def _views(self, hand: NDArray[np.float64]) -> list[MarkerView | None]:
        """Each camera's view of the markers of hands (N, 4, 4), computed once for the noise law
        and the visibility prior; None for each without markers (those raise where they are used)."""
        if not self.markers:
            return [None] * len(self._cameras)
        poses = hand[:, None] @ self._marker_frames                             # (N, M, 4, 4)
        return [(poses, *view_geometry(cam, poses)) for cam in self._cameras]

    def _covariance(self, camera: NDArray[np.float64], hand: NDArray[np.float64], view: MarkerView | None
                    ) -> NDArray[np.float64]:
        """The noise law's ``R`` (N, 6, 6) of hands (N, 4, 4) seen by ``camera`` (4, 4)."""
        if len(hand) == 1:
            # One pose goes through the noise law's single-pose path (3x cheaper; the local search).
            return self.noise.hand_covariance(camera, hand[0], self.markers,
                                              None if view is None else tuple(v[0] for v in view)).reshape(-1, 6, 6)
        return self.noise.hand_covariance(camera, hand, self.markers, view)

    def _pair_outcomes(self, hand: NDArray[np.float64], hph: NDArray[np.float64],
                       thetas: ArrayLike | None = None, learned: bool = True,
                       views: Sequence[MarkerView | None] | None = None,
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Probabilities (N,) that both cameras, only the first, only the second see the hand: from
        the geometric visibility, or (with :attr:`eye_occlusion` and ``learned``; needs ``thetas``
        (N, L)) each camera's occlusion model with its geometric prior. ``views``: :meth:`_views`
        of ``hand`` when already computed."""
        if self.visibility is not None:
            stds = self._pose_stds(hph)
            views = self._views(hand) if views is None else views
            p1, p2 = (self._visibility(hand, hph, cam, stds, view) for cam, view in zip(self._cameras, views))
        if self.eye_occlusion is not None and learned:
            u = np.atleast_2d(np.asarray(thetas, dtype=float))
            if self.visibility is None:
                p1, p2 = (occ.mean(u) for occ in self.eye_occlusion)
            else:
                p1, p2 = (occ.mean(u, w * p + (1.0 - w) * occ.a0 / (occ.a0 + occ.b0))
                          for occ, p, w in zip(self.eye_occlusion, (p1, p2), self.eye_visibility_weights))
        c = self.eye_correlation
        both = c * np.minimum(p1, p2) + (1.0 - c) * p1 * p2
        return both, p1 - both, p2 - both

    def _pair_covariances(self, hand: NDArray[np.float64], views: Sequence[MarkerView | None] | None = None
                          ) -> list[NDArray[np.float64]]:
        """``R`` (N, 6, 6) of the outcomes both, first only, second only (``views``: see :meth:`_pair_outcomes`)."""
        views = self._views(hand) if views is None else views
        r1, r2 = (self._covariance(cam, hand, view) for cam, view in zip(self._cameras, views))
        return [stereo_covariance(np.stack([r1, r2], axis=-3), self.noise), r1, r2]

    def _stereo_terms(self, hand: NDArray[np.float64], hp: NDArray[np.float64], hph: NDArray[np.float64],
                      thetas: ArrayLike, views: Sequence[MarkerView | None]
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Expected gain given success and the probability of success (None without a visibility
        prior or per-camera occlusion models)."""
        covariances = self._pair_covariances(hand, views)
        if self.visibility is None and self.eye_occlusion is None:
            return information_gain(hp, hph + covariances[0], self.weight), None
        outcomes = self._pair_outcomes(hand, hph, thetas, views=views)
        seen = sum(outcomes)
        # The three outcomes' gains in one stacked solve (3, N): a third of the calls per evaluation.
        gains = information_gain(hp, hph + np.stack(covariances), self.weight)
        gain = sum(w * g for w, g in zip(outcomes, gains))
        return gain / np.maximum(seen, 1e-12), seen

    def _jacobian(self, frames: NDArray[np.float64]) -> NDArray[np.float64]:
        """Observation Jacobian (N, 6, n) at the chain ``frames`` (N, L + 1, 4, 4)."""
        if self.extrinsics is None:
            return kinematics.pose_jacobian_from_frames(frames)
        return self.extrinsics.predict(frames, np.zeros(self.extrinsics.n))[1]

    @staticmethod
    def _pose_stds(hph: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Predicted position [m] and orientation [deg] standard deviations (N,) of pose covariances (N, 6, 6)."""
        var = np.diagonal(hph, axis1=-2, axis2=-1)
        # sum / 3 is ndarray.mean's own arithmetic, without its per-call overhead (every cost evaluation).
        return np.sqrt(var[:, :3].sum(axis=-1) / 3), np.degrees(np.sqrt(var[:, 3:].sum(axis=-1) / 3))

    def _visibility(self, hand: NDArray[np.float64], hph: NDArray[np.float64],
                    camera: NDArray[np.float64] | None = None,
                    stds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
                    view: MarkerView | None = None) -> NDArray[np.float64]:
        """Geometric detection probability (N,) of hands (N, 4, 4) with predicted pose covariances
        (N, 6, 6) by ``camera`` (4, 4); by either camera of a pair when it is None. ``stds``: the
        covariances' :meth:`_pose_stds`, ``view``: that camera's :meth:`_views`, when already computed."""
        if camera is None and len(self._cameras) == 2:
            return sum(self._pair_outcomes(hand, hph, learned=False))
        pos_std, rot_std = self._pose_stds(hph) if stds is None else stds
        camera = self._cameras[0] if camera is None else camera
        if view is None:
            return self.visibility.probability(camera, hand[:, None] @ self._marker_frames, pos_std, rot_std)
        return self.visibility.probability(camera, view[0], pos_std, rot_std, view[1:])

    def visibility_probability(self, thetas: ArrayLike, camera: int | None = None) -> NDArray[np.float64]:
        """The geometric prior alone at configurations (N, L) -> (N,), as the current estimate predicts it:
        for camera number ``camera`` of :attr:`camera_pose`, or (None) for any of them.

        Raises
        ------
        ValueError
            If the cost has no visibility prior.
        """
        if self.visibility is None:
            raise ValueError('this AcquisitionCost has no visibility prior')
        frames = kinematics.chain_frames(self.base, self.dh, np.atleast_2d(thetas))
        H = self._jacobian(frames)                                               # noqa: N806
        hph = H @ self.P @ np.swapaxes(H, -1, -2)
        return self._visibility(frames[:, -1], hph, None if camera is None else self._cameras[camera])

    def posterior(self, theta: ArrayLike) -> NDArray[np.float64]:
        """The covariance after one observation at ``theta`` (L,): ``P - B^T S^-1 B`` with
        ``B = H P``, ``S = H P H^T + R`` (it does not depend on what is measured), shape like ``P``.
        With two cameras ``R`` is that of the likeliest outcome (both, or one camera alone)."""
        frames = kinematics.chain_frames(self.base, self.dh, np.asarray(theta, dtype=float)[None])
        H = self._jacobian(frames)[0]                                            # noqa: N806
        hp = H @ self.P
        hph = hp @ H.T
        if len(self._cameras) == 1:
            R = self.noise.hand_covariance(self._cameras[0], frames[0, -1], self.markers).reshape(6, 6)  # noqa: N806
        else:
            covariances = self._pair_covariances(frames[:, -1])
            likeliest = 0
            if self.visibility is not None or self.eye_occlusion is not None:
                likeliest = int(np.argmax([o[0] for o in self._pair_outcomes(frames[:, -1], hph[None], theta)]))
            R = covariances[likeliest][0]                                        # noqa: N806
        post = self.P - hp.T @ np.linalg.solve(hph + R, hp)
        return 0.5 * (post + post.T)

    def terms(self, theta: ArrayLike) -> tuple[float, float, float]:
        """``(C0, eta, p_x)`` at one configuration ``theta`` (L,); ``C0 = tr(A P) - g``."""
        gain, eta, px = self.terms_batch(np.asarray(theta, dtype=float)[None])
        return self.uncertainty - float(gain[0]), float(eta[0]), float(px[0])

    def evaluate(self, thetas: ArrayLike) -> NDArray[np.float64]:
        """``C`` for a batch of configurations (N, L) -> (N,)."""
        gain, eta, px = self.terms_batch(thetas)
        if self.occlusion_mode == 'paper':
            c = (self.uncertainty - gain) / np.maximum(eta, 1e-12)
        elif self.occlusion_mode == 'expected':
            c = self.uncertainty - eta * gain
        else:
            c = -eta * gain / self.uncertainty
        return c + self.penalty_a * np.arctan(self.penalty_b * px)

    def __call__(self, theta: ArrayLike) -> float:
        """``C(theta)`` at one configuration (L,)."""
        return float(self.evaluate(np.asarray(theta, dtype=float)[None])[0])


@dataclass(frozen=True)
class SelectorConfig:
    """Parameters of a joint selector.

    Attributes
    ----------
    strategy : Strategy
    gamma : float
        UCSAL movement weight on the normalised L1 distance.
    delta : float
        CCSAL half-width of the allowed box per joint, normalised units in (0, 1].
    optimizer : {'direct', 'batch'}
        DIRECT family (the paper's) or batched quasi-random candidates plus local refinement.
    algorithm : str
        A key of :data:`DIRECT_ALGORITHMS` (``optimizer='direct'``).
    max_evals : int
        Cost evaluations per selection (``optimizer='direct'``).
    n_candidates : int
        Sobol candidates per selection, a power of two (``optimizer='batch'``).
    refine_starts : int
        Best candidates refined locally (``optimizer='batch'``; 0 disables refinement).
    refine_evals : int
        Evaluations per local refinement.
    local_algorithm : str
        A key of :data:`LOCAL_ALGORITHMS`.
    repeat_tolerance : float
        A configuration within this max-abs joint distance [rad] of a visited one is never
        selected; 0 disables the check.
    seed : int
        Seeds the random strategy, the Sobol scrambling and randomised DIRECT variants.
    """

    strategy: Strategy = Strategy.AL
    gamma: float = 0.01
    delta: float = 0.4
    optimizer: str = 'batch'
    algorithm: str = 'DIRECT_L'
    max_evals: int = 1000
    n_candidates: int = 512
    refine_starts: int = 1
    refine_evals: int = 75
    local_algorithm: str = 'BOBYQA'
    repeat_tolerance: float = 2e-3
    seed: int = 0

    @property
    def search(self) -> str:
        """What searches the cost, in words (for logs and benchmark tables)."""
        if self.optimizer == 'direct':
            return f'{self.algorithm}, {self.max_evals} evaluations'
        return f'batch: {self.n_candidates} candidates + {self.local_algorithm} {self.refine_evals}'

    def __post_init__(self) -> None:
        object.__setattr__(self, 'strategy', Strategy.parse(str(getattr(self.strategy, 'value', self.strategy))))
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f'unknown optimizer {self.optimizer!r}; expected one of {OPTIMIZERS}')
        if self.algorithm not in DIRECT_ALGORITHMS:
            raise ValueError(f'unknown algorithm {self.algorithm!r}; expected one of {sorted(DIRECT_ALGORITHMS)}')
        if self.local_algorithm not in LOCAL_ALGORITHMS:
            raise ValueError(f'unknown local_algorithm {self.local_algorithm!r}; '
                             f'expected one of {sorted(LOCAL_ALGORITHMS)}')
        if not (np.isfinite(self.gamma) and self.gamma >= 0):
            raise ValueError(f'gamma must be finite and >= 0, got {self.gamma}')
        if not 0.0 < self.delta <= 1.0:
            raise ValueError(f'delta must be in (0, 1], got {self.delta}')
        if self.max_evals < 10:
            raise ValueError(f'max_evals must be at least 10, got {self.max_evals}')
        n = self.n_candidates
        if n < 16 or n & (n - 1):
            raise ValueError(f'n_candidates must be a power of two >= 16 (Sobol balance), got {n}')
        if not 0 <= self.refine_starts <= n:
            raise ValueError(f'refine_starts must be in [0, n_candidates], got {self.refine_starts}')
        if self.refine_evals < 5:
            raise ValueError(f'refine_evals must be at least 5, got {self.refine_evals}')
        if not (np.isfinite(self.repeat_tolerance) and self.repeat_tolerance >= 0):
            raise ValueError(f'repeat_tolerance must be finite and >= 0, got {self.repeat_tolerance}')


@dataclass(frozen=True)
class Selection:
    """The outcome of one selection.

    Attributes
    ----------
    theta : ndarray, shape (L,)
    cost : float
        The objective at ``theta`` (cost plus UCSAL's distance term); NaN for random.
    evaluations : int
        Configurations the objective was evaluated at.
    seconds : float
    bounds : ndarray, shape (L, 2)
    optimizer : str
        ``'random'``, ``'direct:<algorithm>'`` or ``'batch:<local algorithm>'``.
    excluded : int
        Evaluated configurations rejected as repeats of visited ones.
    refused : int
        Configurations the search preferred that were refused: inside a collision margin (better
        candidates checked best-first, refinement starts and steps).
    refused_paths : int
        The same, refused because the straight joint-space path to them leaves a margin.
    safety_seconds : float
        Of ``seconds``, the time spent on those checks.
    """

    theta: NDArray[np.float64]
    cost: float
    evaluations: int
    seconds: float
    bounds: NDArray[np.float64]
    optimizer: str = 'direct:DIRECT_L'
    excluded: int = 0
    refused: int = 0
    refused_paths: int = 0
    safety_seconds: float = 0.0


class JointSelector:
    """Chooses the next configuration with one strategy.

    Parameters
    ----------
    box : array_like, shape (L, 2)
        Calibration box [rad].
    config : SelectorConfig
    """

    def __init__(self, box: ArrayLike, config: SelectorConfig = SelectorConfig()) -> None:
        self.box = np.asarray(box, dtype=float)
        if self.box.ndim != 2 or self.box.shape[1] != 2 or np.any(self.box[:, 1] <= self.box[:, 0]):
            raise ValueError(f'box must be (L, 2) with min < max, got {self.box.tolist()}')
        self.config = config
        self.span = self.box[:, 1] - self.box[:, 0]
        self._rng = as_rng(config.seed)

    def distance(self, theta: ArrayLike, previous: ArrayLike) -> float | NDArray[np.float64]:
        """UCSAL's movement cost: L1 norm of the normalised joint difference, shape () or (N,)."""
        d = np.sum(np.abs((np.asarray(theta) - np.asarray(previous)) / self.span), axis=-1)
        return float(d) if np.ndim(d) == 0 else d

    def bounds(self, previous: ArrayLike | None) -> NDArray[np.float64]:
        """Search bounds (L, 2): the box, or for CCSAL its intersection with the delta box."""
        if self.config.strategy is not Strategy.CCSAL or previous is None:
            return self.box.copy()
        prev = np.clip(np.asarray(previous, dtype=float), self.box[:, 0], self.box[:, 1])
        half = self.config.delta * self.span
        return np.stack([np.maximum(self.box[:, 0], prev - half),
                         np.minimum(self.box[:, 1], prev + half)], axis=1)

    def objective(self, cost: AcquisitionCost, thetas: ArrayLike, previous: ArrayLike | None = None,
                  visited: cKDTree | None = None) -> NDArray[np.float64]:
        """The minimised objective for a batch (N, L) -> (N,); ``inf`` at repeats and non-finite costs.

        Parameters
        ----------
        cost : AcquisitionCost
        thetas : array_like, shape (N, L)
        previous : array_like, shape (L,), optional
            Needed by UCSAL's distance term.
        visited : cKDTree, optional
            Visited configurations (see :meth:`visited_tree`).
        """
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        v = cost.evaluate(thetas)
        if self.config.strategy is Strategy.UCSAL:
            v = v + self.config.gamma * self.distance(thetas, previous)
        v = np.where(np.isfinite(v), v, np.inf)
        if visited is not None:
            v[self.is_repeat(thetas, visited)] = np.inf
        return v

    def visited_tree(self, visited: ArrayLike | None) -> cKDTree | None:
        """A max-norm search tree over visited configurations (K, L); ``None`` if none or disabled."""
        if visited is None or self.config.repeat_tolerance == 0:
            return None
        v = np.asarray(visited, dtype=float)
        if v.size == 0:
            return None
        if v.ndim != 2 or v.shape[1] != self.box.shape[0] or not np.all(np.isfinite(v)):
            raise ValueError(f'visited must be finite configurations of shape (K, {self.box.shape[0]}), '
                             f'got shape {v.shape}')
        return cKDTree(v)

    def is_repeat(self, thetas: ArrayLike, visited: cKDTree) -> NDArray[np.bool_]:
        """Whether each of (N, L) configurations is within ``repeat_tolerance`` of a visited one."""
        thetas = np.atleast_2d(thetas)
        tol = self.config.repeat_tolerance * (1 + 1e-12)
        if thetas.shape[0] <= 8:    # the local search's single points: brute force beats the tree query
            return np.min(np.max(np.abs(visited.data - thetas[:, None, :]), axis=-1), axis=-1) <= tol
        d, _ = visited.query(thetas, k=1, p=np.inf, distance_upper_bound=tol)
        return np.isfinite(d)

    def select(self, cost: AcquisitionCost | None, previous: ArrayLike | None = None,
               visited: ArrayLike | None = None, safety: SafetyCheck | None = None,
               start: ArrayLike | None = None) -> Selection:
        """The next configuration.

        Parameters
        ----------
        cost : AcquisitionCost or None
            The current cost; unused (may be ``None``) for the random strategy.
        previous : array_like, shape (L,), optional
            The previous configuration (needed by UCSAL and CCSAL).
        visited : array_like, shape (K, L), optional
            Every configuration visited (or targeted) so far; none is selected again.
        safety : SafetyCheck, optional
            Refuses configurations inside the collision margins and paths from ``start`` that
            leave them.
        start : array_like, shape (L,), optional
            Where the arm is (the paths' start); ``previous`` if omitted (required with ``safety``).

        Raises
        ------
        RuntimeError
            If every evaluated configuration repeats a visited one.
        UnsafeSelection
            If none of the evaluated configurations is safe to command.
        """
        t0 = time.perf_counter()
        strategy = self.config.strategy
        bounds = self.bounds(previous)
        here = start if start is not None else previous
        if safety is not None and here is None:
            raise ValueError('a safety check needs the configuration the arm starts from')
        guard = None if safety is None else _Guard(safety, np.asarray(here, dtype=float), bounds)
        if strategy is Strategy.RANDOM:
            for _ in range(RANDOM_TRIES):
                theta = self._rng.uniform(bounds[:, 0], bounds[:, 1])
                if guard is None or guard.safe(theta):
                    return Selection(theta, float('nan'), 0, time.perf_counter() - t0, bounds, 'random',
                                     **({} if guard is None else guard.counts()))
            raise UnsafeSelection(f'random: none of {RANDOM_TRIES} uniform configurations of the box is safe to '
                                  f'command ({guard.refused} inside a margin, {guard.refused_paths} behind one)')
        if cost is None:
            raise ValueError(f'strategy {strategy.value} needs an AcquisitionCost')
        if strategy in (Strategy.UCSAL, Strategy.CCSAL) and previous is None:
            raise ValueError(f'strategy {strategy.value} needs the previous configuration')
        prev = None if previous is None else np.asarray(previous, dtype=float)
        tree = self.visited_tree(visited)
        objective = lambda q: self.objective(cost, q, prev, tree)  # noqa: E731
        if self.config.optimizer == 'batch':
            # UCSAL's L1 term has its kinks at the previous configuration: a snap target.
            anchor = prev if strategy is Strategy.UCSAL else None
            theta, value, n_evals, excluded, name, count = self._batch(objective, bounds, anchor, guard)
        else:
            theta, value, n_evals, excluded, name, count = self._direct(objective, bounds)
        if not np.isfinite(value):
            raise RuntimeError(f'{name}: all {n_evals} evaluated configurations repeat a visited one '
                               f'(repeat_tolerance {self.config.repeat_tolerance} rad) or have no finite cost')
        if guard is not None:
            theta, value = guard.best(count.points(), count.values(), name)
        return Selection(np.clip(theta, bounds[:, 0], bounds[:, 1]), value, n_evals,
                         time.perf_counter() - t0, bounds, name, excluded,
                         **({} if guard is None else guard.counts()))

    def _direct(self, objective: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                bounds: NDArray[np.float64]) -> tuple[NDArray[np.float64], float, int, int, str, '_Counted']:
        """DIRECT family over ``bounds``: (theta, value, evaluations, excluded, name, evaluated points)."""
        n_evals = excluded = 0
        best = (np.inf, 0.5 * (bounds[:, 0] + bounds[:, 1]))
        history = _Counted(objective)

        def f(theta: NDArray[np.float64], grad: NDArray[np.float64]) -> float:
            nonlocal n_evals, excluded, best
            n_evals += 1
            v = float(history(theta[None])[0])
            if not np.isfinite(v):
                excluded += 1
                return _EXCLUDED        # keep DIRECT going; such points are never chosen
            if v < best[0]:
                best = (v, theta.copy())
            return v

        opt = nlopt.opt(DIRECT_ALGORITHMS[self.config.algorithm], self.box.shape[0])
        if self.config.algorithm.endswith('RAND'):
            nlopt.srand(int(self._rng.integers(2**31)))
        opt.set_lower_bounds(bounds[:, 0])
        opt.set_upper_bounds(bounds[:, 1])
        opt.set_min_objective(f)
        opt.set_maxeval(self.config.max_evals)
        try:
            opt.optimize(0.5 * (bounds[:, 0] + bounds[:, 1]))
        except nlopt.RoundoffLimited:
            pass  # the best point so far is still valid
        return best[1], best[0], n_evals, excluded, f'direct:{self.config.algorithm}', history

    def _batch(self, objective: Callable[[NDArray[np.float64]], NDArray[np.float64]],
               bounds: NDArray[np.float64], anchor: NDArray[np.float64] | None = None,
               guard: '_Guard | None' = None,
               ) -> tuple[NDArray[np.float64], float, int, int, str, '_Counted']:
        """Sobol candidates in one batch, then two rounds of local refinement and snapping.

        Snapping: the optima of these costs often sit on a face of the search box or, for UCSAL,
        on a kink of the L1 distance (a joint left where it was), which a smooth local model
        approaches only slowly. Greedily setting single joints to a bound or to ``anchor`` (one
        batch of ``<= 3 L`` variants per step) lands there exactly when that is better; the second
        refinement then moves only the joints not snapped. Round 1 refines the best
        ``refine_starts`` candidates with ``refine_evals`` evaluations each, round 2 (only if
        something snapped) the incumbent with half as many.

        With a ``guard`` the starts are the best candidates inside no margin, and the local steps
        and snaps count a configuration inside a margin as excluded (few evaluations: the Sobol
        batch itself is checked best-first afterwards, in :meth:`_Guard.best`).
        """
        cfg = self.config
        lo, hi = bounds[:, 0], bounds[:, 1]
        count = _Counted(objective)
        sobol = qmc.Sobol(d=lo.size, scramble=True, rng=self._rng)
        cand = lo + sobol.random_base2(int(math.log2(cfg.n_candidates))) * (hi - lo)
        values = count(cand)
        order = np.argsort(values)
        finite = [i for i in order if np.isfinite(values[i])]
        if guard is None:
            starts = [cand[i] for i in finite[:max(cfg.refine_starts, 1)]]
        else:
            starts = guard.first_clear(cand, finite, max(cfg.refine_starts, 1))
            count.objective = guard.masked(objective)
        name = f'batch:{cfg.local_algorithm}'
        if not starts:
            return cand[order[0]], float(values[order[0]]), count.evals, count.excluded, name, count
        targets = np.stack([lo, hi] + ([] if anchor is None else [np.clip(anchor, lo, hi)]))   # (T, L)
        for rnd in range(2):
            if cfg.refine_starts > 0:
                free = np.ones(lo.size, bool) if rnd == 0 else ~np.any(targets == count.best_x, axis=0)
                for x0 in (starts if rnd == 0 else [count.best_x]):
                    self._local(count, x0, lo, hi, free, cfg.refine_evals if rnd == 0 else cfg.refine_evals // 2)
            before = count.best_x
            self._snap(count, targets)
            if count.best_x is before:      # nothing snapped: a second round would repeat the first
                break
        return count.best_x, count.best, count.evals, count.excluded, name, count

    def _local(self, count: '_Counted', x0: NDArray[np.float64], lo: NDArray[np.float64],
               hi: NDArray[np.float64], free: NDArray[np.bool_], max_evals: int) -> None:
        """A bounded derivative-free NLopt search from ``x0`` over the ``free`` joints."""
        if not np.any(free):
            return
        f0 = float(count(x0[None])[0])
        # Excluded points look worse than the start (finite, so BOBYQA's model stays sane).
        worse = f0 + abs(f0) + 1.0 if np.isfinite(f0) else _EXCLUDED
        x = x0.copy()

        def f(y: NDArray[np.float64], grad: NDArray[np.float64]) -> float:
            x[free] = y
            v = float(count(x[None])[0])
            return v if np.isfinite(v) else worse

        opt = nlopt.opt(LOCAL_ALGORITHMS[self.config.local_algorithm], int(free.sum()))
        opt.set_lower_bounds(lo[free])
        opt.set_upper_bounds(hi[free])
        opt.set_min_objective(f)
        opt.set_maxeval(max_evals)
        # 5% of each side: a polish around the start (the Sobol cells are ~1/3 per side).
        opt.set_initial_step(0.05 * (hi - lo)[free])
        try:
            opt.optimize(np.clip(x0[free], lo[free], hi[free]))
        except (nlopt.RoundoffLimited, nlopt.ForcedStop):
            pass

    @staticmethod
    def _snap(count: '_Counted', targets: NDArray[np.float64]) -> None:
        """Greedily move single joints of the incumbent onto ``targets`` (T, L) while that improves it."""
        for _ in range(targets.shape[1]):
            x = count.best_x
            t_idx, j_idx = np.nonzero(targets != x)
            if not np.isfinite(count.best) or t_idx.size == 0:
                return
            variants = np.repeat(x[None], t_idx.size, axis=0)
            variants[np.arange(t_idx.size), j_idx] = targets[t_idx, j_idx]
            before = count.best
            count(variants)
            if not count.best < before:
                return


class _Counted:
    """An objective that counts its evaluations and excluded points and keeps the best point."""

    def __init__(self, objective: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> None:
        self.objective = objective
        self.evals = self.excluded = 0
        self.best = np.inf
        self.best_x = np.empty(0)
        self._points: list[NDArray[np.float64]] = []
        self._values: list[NDArray[np.float64]] = []

    def points(self) -> NDArray[np.float64]:
        """Every evaluated configuration, shape (N, L)."""
        return np.concatenate(self._points) if self._points else np.empty((0, 0))

    def values(self) -> NDArray[np.float64]:
        """Their objective values, shape (N,)."""
        return np.concatenate(self._values) if self._values else np.empty(0)

    def __call__(self, thetas: NDArray[np.float64]) -> NDArray[np.float64]:
        thetas = np.atleast_2d(np.array(thetas, dtype=float))
        v = self.objective(thetas)
        self._points.append(thetas)
        self._values.append(np.asarray(v, dtype=float))
        self.evals += v.size
        self.excluded += int(np.sum(np.isinf(v)))
        k = int(np.argmin(v))
        if v[k] < self.best or self.best_x.size == 0:
            self.best, self.best_x = float(v[k]), np.array(thetas[k], dtype=float)
        return v


#: Uniform draws the random strategy tries for a safe configuration before it gives up.
RANDOM_TRIES = 1000


class _Guard:
    """Best-first safety checks of one selection, with their counts and time."""

    def __init__(self, safety: SafetyCheck, start: NDArray[np.float64], bounds: NDArray[np.float64]) -> None:
        self.safety, self.start, self.bounds = safety, start, bounds
        self.refused = self.refused_paths = 0
        self.seconds = 0.0
        self._clear: dict[bytes, bool] = {}

    def clear(self, theta: NDArray[np.float64]) -> bool:
        """Whether one configuration keeps the margins; each one refused is counted once."""
        key = theta.tobytes()
        if key not in self._clear:
            t0 = time.perf_counter()
            self._clear[key] = ok = bool(self.safety.clear(theta))
            self.seconds += time.perf_counter() - t0
            self.refused += not ok
        return self._clear[key]

    def safe(self, theta: NDArray[np.float64]) -> bool:
        """Configuration and path both clear (a path refused is counted)."""
        if not self.clear(theta):
            return False
        t0 = time.perf_counter()
        ok = bool(self.safety.path_clear(self.start, theta).clear)
        self.seconds += time.perf_counter() - t0
        if not ok:
            self.refused_paths += 1
        return ok

    def first_clear(self, cand: NDArray[np.float64], order: Sequence[int], n: int) -> list[NDArray[np.float64]]:
        """The first ``n`` candidates in ``order`` that keep the margins."""
        out = []
        for i in order:
            if self.clear(cand[i]):
                out.append(cand[i])
                if len(out) == n:
                    break
        return out

    def masked(self, objective: Callable[[NDArray[np.float64]], NDArray[np.float64]]
               ) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """``objective`` with ``inf`` at configurations inside a margin (for the few local evaluations)."""
        def f(thetas: NDArray[np.float64]) -> NDArray[np.float64]:
            v = np.array(objective(thetas), dtype=float)
            for k, theta in enumerate(np.atleast_2d(thetas)):
                if np.isfinite(v[k]) and not self.clear(np.clip(theta, self.bounds[:, 0], self.bounds[:, 1])):
                    v[k] = np.inf
            return v
        return f

    def best(self, points: NDArray[np.float64], values: NDArray[np.float64], name: str
             ) -> tuple[NDArray[np.float64], float]:
        """The best evaluated point that is safe to command, checked best-first.

        Raises
        ------
        UnsafeSelection
            If none is.
        """
        seen: set[bytes] = set()
        finite = np.nonzero(np.isfinite(values))[0]
        for i in finite[np.argsort(values[finite], kind='stable')]:
            theta = np.clip(points[i], self.bounds[:, 0], self.bounds[:, 1])
            key = theta.tobytes()
            if key in seen:
                continue
            seen.add(key)
            if self.safe(theta):
                return theta, float(values[i])
        raise UnsafeSelection(f'{name}: none of the {len(seen)} evaluated configurations is safe to command '
                              f'({self.refused} inside a collision margin, {self.refused_paths} with a path that '
                              f'leaves one)')

    def counts(self) -> dict[str, float]:
        return {'refused': self.refused, 'refused_paths': self.refused_paths, 'safety_seconds': self.seconds}
