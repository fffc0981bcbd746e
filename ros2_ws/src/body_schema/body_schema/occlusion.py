"""Non-parametric occlusion model: kernel-smoothed Beta posterior (paper sec. III-C).

Each measurement attempt at joints ``theta_k`` records a success (marker detected) or a failure.
The probability ``eta`` of success at a new ``theta_*`` has the posterior

    Be(eta; sum_k K(theta_*, theta_k) S_k + a0,  sum_k K(theta_*, theta_k) U_k + b0)

with a squared-exponential kernel in normalised joint space (each joint scaled to [0, 1] by the
box), ``K = exp(-||u_* - u_k||^2 / (2 l^2))``, so ``K = 1`` at a visited configuration and decays
with distance. Repeated attempts at one configuration add to that configuration's counts, as in
the paper's ``S_k, U_k``. The posterior mean (eq. finalbeta) is what the acquisition uses.

Beyond the paper, the prior need not be flat: :class:`VisibilityPrior` predicts from the current
kinematic estimate whether a marker would face the camera inside its image, blurred by the
estimate's own uncertainty about the hand, and :meth:`OcclusionModel.mean` can take that
probability ``p`` as the prior mean, ``Be(c p, c (1 - p))`` with the strength ``c = a0 + b0``:
geometry says where the hand can be seen, the counts learn what geometry misses (the arm hiding the
hand, detection failures), and a visited configuration's outcome outweighs the prior there.
Geometry computed from a badly wrong estimate predicts the hand where it is not; so the prior used
is a mixture of the geometric and the flat one, weighted by :meth:`OcclusionModel.geometric_evidence`,
the posterior probability that the model with the geometric prior predicted the attempts so far,
each from the ones before it, better than the model with the flat prior did.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.distance import cdist
from scipy.special import expit, ndtr

from .noise import view_geometry
from .robot import CameraIntrinsics

__all__ = ['OcclusionModel', 'VisibilityPrior']


class OcclusionModel:
    """Kernel-smoothed Beta model of the probability that the hand is detected.

    Parameters
    ----------
    box : array_like, shape (L, 2)
        Joint box used to normalise configurations to [0, 1]^L.
    length_scale : float
        Kernel length scale ``l`` in normalised units.
    a0, b0 : float
        Beta prior pseudo-counts for success and failure.
    """

    def __init__(self, box: ArrayLike, length_scale: float = 0.1, a0: float = 1.0, b0: float = 1.0) -> None:
        box = np.asarray(box, dtype=float)
        if box.ndim != 2 or box.shape[1] != 2 or np.any(box[:, 1] <= box[:, 0]):
            raise ValueError(f'box must be (L, 2) with min < max per joint, got {box.tolist()}')
        for name, v in (('length_scale', length_scale), ('a0', a0), ('b0', b0)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'OcclusionModel.{name} must be finite and > 0, got {v}')
        self.lower = box[:, 0]
        self.span = box[:, 1] - box[:, 0]
        self.length_scale = float(length_scale)
        self.a0, self.b0 = float(a0), float(b0)
        self._u = np.zeros((0, box.shape[0]))       # normalised visited configurations
        self._s = np.zeros(0)                        # successes at each
        self._f = np.zeros(0)                        # failures at each
        self._attempts: list[NDArray[np.float64]] = []   # every attempt in order (joint angles) ...
        self._seen: list[bool] = []                      # ... and its outcome

    @property
    def n_configs(self) -> int:
        """Distinct configurations with recorded attempts."""
        return self._u.shape[0]

    @property
    def attempts(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Every recorded attempt in order: configurations (K, L) and whether each saw the hand (K,)."""
        return (np.array(self._attempts).reshape(-1, self.lower.size), np.array(self._seen, dtype=bool))

    @property
    def counts(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Successes and failures per recorded configuration, each shape (K,)."""
        return self._s.copy(), self._f.copy()

    def normalise(self, theta: ArrayLike) -> NDArray[np.float64]:
        """Joint angles -> [0, 1]^L box coordinates, shape preserved."""
        return (np.asarray(theta, dtype=float) - self.lower) / self.span

    def add(self, theta: ArrayLike, success: bool) -> None:
        """Record one attempt at ``theta`` (shape (L,)).

        An attempt at an already recorded configuration (to 1e-9 in normalised units) adds to
        its counts rather than creating a twin.
        """
        theta = np.asarray(theta, dtype=float)
        if theta.shape != self.lower.shape or not np.all(np.isfinite(theta)):
            raise ValueError(f'theta must be {self.lower.size} finite joint angles, got {theta!r}')
        self._attempts.append(theta.copy())
        self._seen.append(bool(success))
        u = self.normalise(theta)
        if self.n_configs:
            hit = np.nonzero(np.all(np.abs(self._u - u) < 1e-9, axis=1))[0]
            if hit.size:
                (self._s if success else self._f)[hit[0]] += 1.0
                return
        self._u = np.vstack([self._u, u])
        self._s = np.append(self._s, 1.0 if success else 0.0)
        self._f = np.append(self._f, 0.0 if success else 1.0)

    def kernel(self, theta: ArrayLike) -> NDArray[np.float64]:
        """Kernel weights to every recorded configuration.

        Parameters
        ----------
        theta : array_like, shape (L,) or (M, L)

        Returns
        -------
        ndarray, shape (K,) or (M, K)
        """
        u = self.normalise(theta)
        return self._kernel(np.atleast_2d(u), self._u).reshape(u.shape[:-1] + (self.n_configs,))

    def _kernel(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Kernel matrix (N, K) between normalised configurations (N, L) and (K, L)."""
        # cdist: ~10x faster than broadcasting (M, K, L) for the selector's thousands of candidates.
        return np.exp(-0.5 * cdist(u, v, 'sqeuclidean') / self.length_scale ** 2)

    def posterior(self, theta: ArrayLike, prior: ArrayLike | None = None) -> tuple[NDArray[np.float64],
                                                                                  NDArray[np.float64]]:
        """Beta parameters ``(alpha, beta)`` at ``theta`` (shape (L,) or (M, L)).

        ``prior`` (shape () or (M,), in (0, 1)), if given, replaces the flat prior's mean
        ``a0 / (a0 + b0)`` at each configuration, keeping its strength ``a0 + b0``.
        """
        k = self.kernel(theta)
        if prior is None:
            a0, b0 = self.a0, self.b0
        else:
            c = self.a0 + self.b0
            a0 = c * np.asarray(prior, dtype=float)
            b0 = c - a0
        return k @ self._s + a0, k @ self._f + b0

    def geometric_evidence(self, p_geometric: ArrayLike) -> float:
        """Posterior probability of the geometric prior against the flat one, from the recorded attempts.

        Bayesian model comparison (even prior odds) by prequential likelihood: attempt ``k`` is
        predicted by this kernel model from attempts ``0 .. k-1`` only, once with the flat prior
        ``Be(a0, b0)`` and once with the geometric prior mean ``p_k`` (same strength). Failures the
        kernel has already learned around (the arm hiding the hand in a region) cost both models
        alike; failures where geometry keeps expecting the hand cost the geometric one.

        Parameters
        ----------
        p_geometric : array_like, shape (K,)
            Geometric detection probabilities at the configurations of :attr:`attempts` (as the
            current estimate predicts them), in (0, 1).

        Returns
        -------
        float
            In [0, 1]; 0.5 without attempts.
        """
        thetas, seen = self.attempts
        p = np.asarray(p_geometric, dtype=float).ravel()
        if p.size != seen.size:
            raise ValueError(f'p_geometric must have one entry per recorded attempt ({seen.size}), got {p.size}')
        if np.any(~((p > 0) & (p < 1))):
            raise ValueError(f'p_geometric must lie in (0, 1), got values in [{p.min()}, {p.max()}]')
        u = self.normalise(thetas)
        k = np.tril(self._kernel(u, u), -1)
        s, f = k @ seen, k @ ~seen                                  # evidence before each attempt
        c = self.a0 + self.b0
        q_geo = (s + c * p) / (s + f + c)
        q_flat = (s + self.a0) / (s + f + c)
        log_geo = np.where(seen, np.log(q_geo), np.log1p(-q_geo)).sum()
        log_flat = np.where(seen, np.log(q_flat), np.log1p(-q_flat)).sum()
        return float(expit(log_geo - log_flat))

    def mean(self, theta: ArrayLike, prior: ArrayLike | None = None) -> NDArray[np.float64]:
        """Posterior mean success probability ``eta_bar``, shape () or (M,) (``prior``: see :meth:`posterior`)."""
        a, b = self.posterior(theta, prior)
        return a / (a + b)


@dataclass(frozen=True)
class VisibilityPrior:
    """Probability that the hand is detected, predicted from the kinematic estimate.

    A marker counts as seen when it faces the camera (viewing angle ``phi`` below
    ``max_view_angle_deg``) and its centre projects at least ``margin`` (a fraction of the image
    width, so any resolution with the same field of view gives the same answer) inside the image.
    Both steps are Gaussian-smoothed: by their own softness, widened by the predicted standard
    deviation of the hand's orientation [deg] and of its lateral image position (position std
    times ``fx / (z W)``), so an uncertain estimate predicts a soft boundary rather than a wrong
    sharp one. The hand is seen if any marker is (independent markers); the result is mapped
    into ``[floor, ceiling]``: geometry never rules a configuration in or out completely.

    The defaults are a maximum-likelihood grid fit to 1200 rendered and detected configurations of
    the iCub's calibration box (three real robots, true tables); ``python -m tools.visibility_fit``
    repeats it on another draw: mean log-likelihood -0.386 for the defaults, -0.382 for that draw's
    best fit, -0.681 for a constant rate; none of the 275 configurations predicted below 0.1 was seen.

    Parameters
    ----------
    camera : CameraIntrinsics
    max_view_angle_deg, angle_softness_deg : float
    margin, margin_softness : float
        In fractions of the image width.
    floor, ceiling : float
        Range of the returned probability, ``0 < floor < ceiling < 1``.
    marker_side : float or None
        The markers' side length [m]. Given, the viewing-angle limit of each marker is where its
        foreshortened width ``fx side cos(phi) / r`` falls to ``min_width_px`` (capped at
        ``max_view_angle_deg``), so a large or near marker is seen more obliquely than a small or
        far one; None: the fixed ``max_view_angle_deg``. The iCub's 3 cm marker at 0.33 m (the
        median over its box) in its 320x240 eye (23 px) reaches 7.5 px at 71 deg, about the
        defaults' limit; the Panda's 8 cm marker at 1.8 m in a 1280x1024 camera (53 px) was
        detected up to 81 deg (8.8 px) in the rendered measurement, and not at 85 deg (5.7 px).
    min_width_px : float
        The foreshortened width [px] below which a marker is taken as not detected (with ``marker_side``).
    margin_marker_widths : float
        With ``marker_side``: the margin grows by this many head-on marker widths ``fx side / r``
        (in fractions of the image width), so a near marker, which is large in the image, must lie
        further inside it for all its corners to be seen (0.5: the whole marker inside, beyond
        ``margin``). Scored on the attempts AL makes on the iCub (``tools.visibility_attempts``):
        the eye-views a fixed 6 % margin rated 0.8 or more were seen in 83 %, those the whole
        marker with a 2 % margin rated so in 91 % (docs/selector.md).
    """

    camera: CameraIntrinsics
    max_view_angle_deg: float = 70.0
    angle_softness_deg: float = 8.0
    margin: float = 0.06
    margin_softness: float = 0.02
    floor: float = 0.02
    ceiling: float = 0.9
    marker_side: float | None = None
    min_width_px: float = 7.5
    margin_marker_widths: float = 0.0

    def __post_init__(self) -> None:
        for name in ('max_view_angle_deg', 'angle_softness_deg', 'margin_softness'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'VisibilityPrior.{name} must be finite and > 0, got {v}')
        if not np.isfinite(self.margin):
            raise ValueError(f'VisibilityPrior.margin must be finite, got {self.margin}')
        for name in ('marker_side', 'min_width_px'):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f'VisibilityPrior.{name} must be finite and > 0, got {v}')
        if not (np.isfinite(self.margin_marker_widths) and self.margin_marker_widths >= 0):
            raise ValueError(f'VisibilityPrior.margin_marker_widths must be finite and >= 0, '
                             f'got {self.margin_marker_widths}')
        if self.margin_marker_widths and self.marker_side is None:
            raise ValueError('VisibilityPrior.margin_marker_widths needs marker_side')
        if not 0.0 < self.floor < self.ceiling < 1.0:
            raise ValueError(f'VisibilityPrior needs 0 < floor < ceiling < 1, got {self.floor}, {self.ceiling}')

    def probability(self, camera_pose: ArrayLike, marker_poses: ArrayLike, position_std: ArrayLike = 0.0,
                    orientation_std_deg: ArrayLike = 0.0,
                    view: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None) -> NDArray[np.float64]:
        """Predicted detection probability of a hand.

        Parameters
        ----------
        camera_pose : array_like, shape (4, 4)
            Camera optical frame (z forward, x right, y down) in the root frame.
        marker_poses : array_like, shape (..., M, 4, 4)
            The hand's ``M`` markers in the root frame, as the estimate predicts them.
        position_std : array_like, shape (...) or ()
            Predicted standard deviation of the hand position [m].
        orientation_std_deg : array_like, shape (...) or ()
            Predicted standard deviation of the hand orientation [deg].
        view : tuple of ndarray, optional
            ``view_geometry(camera_pose, marker_poses)`` when the caller has it already (the
            selector's cost computes it once for the noise law and this prior).

        Returns
        -------
        ndarray, shape (...)
        """
        cam = np.asarray(camera_pose, dtype=float)
        poses = np.asarray(marker_poses, dtype=float)
        r, phi = view_geometry(cam, poses) if view is None else view             # (..., M)
        limit, margin = self.max_view_angle_deg, self.margin
        if self.marker_side is not None:
            width = self.camera.fx * self.marker_side / np.maximum(r, 1e-6)        # head-on width [px]
            limit = np.minimum(limit, np.degrees(np.arccos(np.minimum(self.min_width_px / width, 1.0))))
            margin = margin + self.margin_marker_widths * width / self.camera.width
        rot = cam[:3, :3]
        p_cam = (poses[..., :3, 3] - cam[:3, 3]) @ rot                             # (..., M, 3)
        z = np.maximum(p_cam[..., 2], 1e-6)
        c = self.camera
        u = c.fx * p_cam[..., 0] / z + c.cx
        v = c.fy * p_cam[..., 1] / z + c.cy
        inside = np.minimum(np.minimum(u, c.width - u), np.minimum(v, c.height - v)) / c.width
        inside = np.where(p_cam[..., 2] > 0, inside, -1.0)                         # behind the camera
        pos_std = np.asarray(position_std, dtype=float)[..., None] * c.fx / (z * c.width)
        rot_std = np.asarray(orientation_std_deg, dtype=float)[..., None]
        p_marker = (ndtr((limit - phi) / np.hypot(self.angle_softness_deg, rot_std))
                    * ndtr((inside - margin) / np.hypot(self.margin_softness, pos_std)))
        p = 1.0 - np.multiply.reduce(1.0 - p_marker, axis=-1)                    # np.prod without its wrapper
        return self.floor + (self.ceiling - self.floor) * p

