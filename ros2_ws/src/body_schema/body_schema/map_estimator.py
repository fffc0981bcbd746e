"""Online maximum-a-posteriori (MAP) estimation of the DH parameters (pure Python, no rclpy).

The EKF of the paper linearises each observation once, about the estimate of the moment, and
freezes that linearisation into ``P``. From the paper's wide initial spread (46 mm, 54 deg) the
first updates are linearised far from the truth, so ``P`` ends up claiming more certainty than the
data support and later, good observations look like outliers. :class:`MapEstimator` instead keeps
the observations and, after each new one, re-solves the whole problem

    x* = argmin  sum_j rho( (L_p (x - x_p))_j^2 )  +  sum_i sum_k rho( (L_i (z_i (-) h(x, q_i)))_k^2 )

(``L`` the whitening of the prior covariance ``P_p`` and of each observation's ``R_i``) by
nonlinear least squares (``scipy.optimize.least_squares``, trust-region reflective),
warm-started from the previous solution, so every observation is always linearised at the best
current estimate. ``least_squares`` applies the robust loss to every residual component, the
prior's whitened rows included: within the loss scale (3 sigma) the prior is nearly Gaussian,
beyond it its pull fades as the data's does. The posterior covariance is taken at the
solution (:attr:`MapSettings.covariance`). ``rho`` is a robust loss on the whitened residual
(Cauchy by default): it replaces the EKF's hard chi-square gate. An observation whose whitened residual at the solution stays beyond
the ``outlier_probability`` chi-square bound is reported as an outlier (counted, in the update
report) but kept: if a later solution explains it, it stops being one.

Adaptation to a body that changes (wear, a bent link, a tool) uses the paper's own process
model ``x_{k+1} = x_k + w_k``:

* a random walk ``Q = diag(q_length, q_length, q_angle, q_angle)`` per observation: every stored
  observation ``i`` and the prior carry the drift accumulated since they were taken,
  ``R_i <- R_i + H_i D_i H_i^T`` and ``P_p <- P_p + D_p``, so old evidence weighs less;
* change detection on the innovations: when at least ``change_count`` of the last
  ``change_window`` normalised innovations squared (NIS) lie beyond their ``change_probability``
  chi-square bound (6 dof), a jump ``diag(jump_length^2, jump_length^2, jump_angle^2,
  jump_angle^2)`` is added to the drift of every older observation and to the prior, which lets the
  estimate move to the new body quickly at no price on a body that does not change. Counting
  exceedances, not summing NIS, keeps a single gross detection error (a planar flip has NIS in the
  thousands) from passing for a change: a changed body makes the innovations large one after
  another. Exceedances at configurations closer than ``change_separation`` count once:
  the same view gives the same detection error, so a selector that tries a spot again repeats the
  evidence rather than adding to it (a cost-sensitive run tried one view three times, each 190
  sigma off, and was derailed by the alarm). A change stands only if the re-solve with the jump
  explains most of the exceeding observations (``change_confirm``): a changed body is explained
  at once, detection errors that repeat at neighbouring views are not, and their jump is withdrawn;
* an optional sliding window: beyond ``window`` observations the oldest is folded into the
  Gaussian prior (linearised at the current solution), bounding the cost of an update.

A DH chain has exact twins (:func:`body_schema.kinematics.twin_tables`): every angle modulo
2 pi, and any inner frame turned half a revolution about its ``z`` axis, with a free marker
absorbing the flange's turn. The camera cannot tell twins apart, so only the prior can; but a
local solver stays on whichever branch the first, far-linearised observations led it to (a Panda
run from a 442 mm / 61 deg guess settled on a twin with its flange turned 180 deg and angles two
turns from the prior). With ``twins`` on, after each re-solve the estimate moves to the twin of
lowest objective (the data's share is the same for every twin by construction, and is checked;
the prior's decides) and is re-solved there: a step that can only lower the MAP objective. An
estimate near its prior stays where it is (on 40 synthetic iCub and 40 UR5e runs from the
paper-wide guess it never fired).

A wrong basin that is no twin shows as outliers one after another: the robust loss, which the
re-solve applies to the prior's rows too, lets an estimate far from both the data and the prior
stay there. After ``restart_after`` consecutive outliers the problem is also solved cold from
the prior mean, and the solution with the lower objective is kept (a multi-start of the same
objective).

A re-solve that stops at ``max_nfev`` has not converged, and its residuals judge the solver, not
the data: in a UR5e warm-up a 0.26 mm detection was an outlier at chi-square 3251 after 30
evaluations, all four stored observations beyond the bound with it, and fitted at 0.02 once
solved to convergence (38 evaluations). With ``verdict_nfev`` set, such a verdict waits for the
solve to go on.

Parameter combinations the measurements cannot separate (``fixed_directions``, from
:func:`body_schema.identifiability.analyse`: e.g. the ``d`` of a UR's three parallel joints) are
held at the initial guess by an explicit prior of standard deviation ``fixed_std`` along each
direction (one for all, or one each), a residual block of its own (so a jump or a fold into the
prior never loosens it): the estimate does not drift along them and its covariance says they
were not estimated. :class:`dh_estimator.estimator.OnlineEstimator` pins what a camera or marker
absorbs (exact for any table) and holds what only parallel axes hide by the guess's own spread:
on a real arm those axes are a fraction of a degree apart, and a pin at a guess centimetres off
biases every other parameter (``test_identifiability``).

``x`` is the flattened DH table, row-major ``(a_0, d_0, alpha_0, offset_0, a_1, ...)``, followed,
when ``extrinsics`` estimates them (:class:`body_schema.extrinsics.Extrinsics`), by the 6-D
corrections of the camera's pose and the marker's offset (prior mean 0; the predicted hand pose
is then ``E FK F``); the observation is a hand pose compared on SO(3):
``(p_z - p_h, log(R_z R_h^T))``, the residual of :class:`body_schema.ekf.HandPoseModel`. The
random walk and the change jumps act on the DH block only.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from . import kinematics
from .ekf import FilterError, InvalidInputError
from .extrinsics import Extrinsics, pose_delta

__all__ = ['MapSettings', 'MapUpdate', 'MapEstimator', 'LOSSES', 'COVARIANCES', 'LOSS_SCALE_RANGE',
           'sandwich_covariance']

#: Robust losses of ``scipy.optimize.least_squares`` accepted by :class:`MapSettings`.
LOSSES = ('linear', 'huber', 'soft_l1', 'cauchy', 'arctan')

#: IRLS weight ``rho'(z)`` of each loss at ``z = (f / scale)^2`` (scipy's definitions).
_IRLS_WEIGHT = {
    'linear': lambda z: np.ones_like(z),
    'huber': lambda z: np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0))),
    'soft_l1': lambda z: 1.0 / np.sqrt(1.0 + z),
    'cauchy': lambda z: 1.0 / (1.0 + z),
    'arctan': lambda z: 1.0 / (1.0 + z ** 2),
}

#: Each loss ``rho(z)`` at ``z = (f / scale)^2`` (scipy's definitions; the cost is ``0.5 scale^2 sum rho``).
_RHO = {
    'linear': lambda z: z,
    'huber': lambda z: np.where(z <= 1.0, z, 2.0 * np.sqrt(np.maximum(z, 1.0)) - 1.0),
    'soft_l1': lambda z: 2.0 * (np.sqrt(1.0 + z) - 1.0),
    'cauchy': lambda z: np.log1p(z),
    'arctan': lambda z: np.arctan(z),
}

#: Slope of each loss's influence function, ``psi'(u) = rho'(z) + 2 z rho''(z)`` at ``z = (u / scale)^2``.
_PSI_SLOPE = {
    'linear': lambda z: np.ones_like(z),
    'huber': lambda z: np.where(z <= 1.0, 1.0, 0.0),
    'soft_l1': lambda z: (1.0 + z) ** -1.5,
    'cauchy': lambda z: (1.0 - z) / (1.0 + z) ** 2,
    'arctan': lambda z: (1.0 - 3.0 * z ** 2) / (1.0 + z ** 2) ** 2,
}

#: How the posterior covariance is computed (:attr:`MapSettings.covariance`).
COVARIANCES = ('sandwich', 'sandwich_hc3', 'sandwich_blocks', 'sandwich_white', 'sandwich_white_hc2', 'sandwich_white_hc3', 'gauss_newton')

#: Group of each of a detection's six whitened residual rows: position 0, orientation 1.
_POSE_BLOCKS = np.array([0, 0, 0, 1, 1, 1])

#: Loss scales [standard deviations] a robot description or the estimator's parameter may set.
LOSS_SCALE_RANGE = (0.1, 100.0)


def sandwich_covariance(jp: NDArray[np.float64], jo: NDArray[np.float64], u: NDArray[np.float64], loss: str,
                        scale: float, min_dof: float = 12.0, leverage: bool = False, per_row: bool = False,
                        groups: NDArray[np.int_] | None = None, leverage_power: int = 2
                        ) -> NDArray[np.float64] | None:
    """Huber's sandwich covariance of a robust MAP estimate, ``A^-1 B A^-1``.

    With whitened observation residuals ``u`` that share one distribution, whatever its shape,
    the M-estimate's covariance is ``kappa (J^T J)^-1`` with ``kappa = E[psi^2] / E[psi']^2``
    (Huber, Robust Statistics, 1981, sec. 7.6); with a Gaussian prior,
    ``A = Jp^T Jp + E[psi'] Jo^T Jo`` and ``B = Jp^T Jp + E[psi^2] Jo^T Jo``. The expectations are
    estimated from the residuals at the solution, ``E[psi^2]`` over the residual degrees of freedom
    ``u.size - tr(A^-1 E[psi'] Jo^T Jo)``. It is the consistent covariance when the noise law is
    right only up to its scale or its tails (a variance-matched Gaussian law for heavy-tailed
    errors claims too little precision); with Gaussian residuals of the stated scale it is the
    Gauss-Newton covariance within a few per cent.

    With ``leverage`` the spread is the mean of ``psi_k^2 / (1 - h_k)^2`` over the whitened
    residual rows, ``h_k = E[psi'] j_k A^-1 j_k^T`` the row's leverage: the jackknife (HC3) form of
    the pooled spread (MacKinnon and White, 1985), each residual as it would be had its
    observation been left out, instead of all of them divided by the residual degrees of freedom.
    The two agree when every observation weighs alike; they part when a few observations inform
    a direction alone (an active selector picks exactly those), whose residuals the fit shrinks
    and the degrees-of-freedom form then takes for quiet ones. For Gaussian errors of the stated
    scale it is the Gauss-Newton covariance or a little wider (``test_map_estimator``).

    With ``per_row`` the spread is not pooled: ``B = Jp^T Jp + c sum_k psi_k^2 j_k^T j_k`` with
    ``c = k / dof``, White's heteroskedasticity-consistent estimator with the degrees-of-freedom
    factor (HC1; MacKinnon and White, 1985), ``A`` as above; with ``leverage`` as well, each row's
    own correction instead, ``psi_k^2 / (1 - h_k)^2`` (their HC3), which HC1 lacks where a few
    rows carry a direction; ``leverage_power`` 1 makes it ``psi_k^2 / (1 - h_k)`` (HC2, unbiased
    when the rows share one variance; HC3 errs wide). It follows a
    law whose shape is wrong, some residual rows wider than others relative to their stated
    variance (one whitened component of a detection overstated more than the rest), which one
    pooled scale cannot; it is noisier than the pooled spread with few rows per parameter, and
    with very unequal spreads the pooled slope leaves a bias (the wider rows sit further down the
    loss's slope).

    With ``groups`` (and not ``per_row``) the spread is pooled within each group of rows and
    not across them: ``B = Jp^T Jp + sum_g s_g Jo_g^T Jo_g``, ``s_g`` the group's spread (its
    rows' leverage-corrected mean with ``leverage``, else over its share of the residual degrees
    of freedom). Between one pooled scale and a scale per row: right when the law's scale is
    wrong by a different factor for each group (a detection's position and its orientation),
    and still pooled over many rows, so not as noisy as the per-row form with few rows per
    parameter nor as optimistic where a few rows carry a direction alone.

    Parameters
    ----------
    jp : ndarray, shape (m, n)
        Whitened prior rows of the Jacobian (Gaussian: they enter ``A`` and ``B`` in full).
    jo : ndarray, shape (k, n)
        Whitened observation rows.
    u : ndarray, shape (k,)
        Whitened observation residuals at the solution.
    loss : str
        One of :data:`LOSSES`; ``scale`` its ``f_scale``.
    min_dof : float
        Fewer residual degrees of freedom than this, or a mean influence slope below 0.05 (most
        residuals beyond the loss scale): None (too little to estimate the spread from).
    leverage, per_row : bool
        See above.
    groups : ndarray of int, shape (k,), optional
        Each observation row's group (labels ``0 .. G - 1``).
    leverage_power : int
        Exponent of ``1 - h_k`` in the leverage correction, of any form (2: HC3, 1: HC2).

    Returns
    -------
    ndarray, shape (n, n), or None
    """
    if leverage_power not in (1, 2):
        raise ValueError(f'leverage_power must be 1 (HC2) or 2 (HC3), got {leverage_power}')
    z = (u / scale) ** 2
    slope = float(np.mean(_PSI_SLOPE[loss](z))) if u.size else 0.0
    if slope < 0.05:
        return None
    prior, data = jp.T @ jp, jo.T @ jo
    try:
        ca_inv = np.linalg.inv(np.linalg.cholesky(prior + slope * data))
    except np.linalg.LinAlgError:
        return None
    a_inv = ca_inv.T @ ca_inv
    dof = u.size - slope * float(np.sum(a_inv * data))           # tr(A^-1 slope data): parameters the data fit
    if dof < min_dof:
        return None
    psi = _IRLS_WEIGHT[loss](z) * u
    if groups is not None and not per_row:
        groups = np.asarray(groups)
        if groups.shape != u.shape:
            raise ValueError(f'groups must have shape {u.shape} (one label per row), got {groups.shape}')
    if leverage:
        # Each row's psi^2 as it would be had its observation been left out (HC3; HC2 halfway).
        h = slope * np.einsum('ki,ij,kj->k', jo, a_inv, jo)
        corrected = psi ** 2 / np.clip(1.0 - h, 0.05, 1.0) ** leverage_power   # clip: a row the fit alone sets
    if per_row:
        # The slope stays pooled: a row's own psi' at the solution overstates the curvature where
        # the fit has pulled the residual in (the informative rows), which made the covariance
        # optimistic on the iCub's tuning runs (NEES median 34 against 28).
        b = (prior + (jo * corrected[:, None]).T @ jo if leverage
             else prior + (u.size / dof) * (jo * (psi ** 2)[:, None]).T @ jo)
    elif groups is not None:
        terms = corrected if leverage else psi ** 2 * (u.size / dof)
        b = prior.copy()
        for g in np.unique(groups):
            rows = groups == g
            b += float(np.mean(terms[rows])) * (jo[rows].T @ jo[rows])
    else:
        spread = float(np.mean(corrected)) if leverage else float(psi @ psi) / dof
        b = prior + spread * data
    p = a_inv @ b @ a_inv
    return 0.5 * (p + p.T)


@dataclass(frozen=True)
class MapSettings:
    """Settings of :class:`MapEstimator`.

    Attributes
    ----------
    loss : str
        Robust loss on the whitened residual components (one of :data:`LOSSES`).
    loss_scale : float
        Whitened residual (in standard deviations) where the robust loss departs from the square.
    outlier_probability : float
        Chi-square probability (6 dof) beyond which an observation's whitened residual at the
        solution is reported as an outlier.
    max_nfev : int
        Residual evaluations per re-solve (the warm start usually needs 2-4).
    verdict_nfev : int
        When a re-solve stopped at ``max_nfev`` (not converged) and the new observation lies
        beyond the outlier bound, solve on for up to this many more evaluations before the
        verdict; 0: judge the truncated solve.
    window : int
        Observations kept in the nonlinear problem; older ones are folded into the prior, which
        bounds the cost of an update (measured: 5.7 ms at 500 observations against 23.5 ms
        with all of them kept). 0 keeps all.
    q_length, q_angle : float
        Random-walk variance per observation for lengths [m^2] and angles [rad^2].
    change_probability : float
        Chi-square probability (6 dof) an innovation's NIS must exceed to count towards a change;
        0 disables change detection.
    change_window, change_count : int
        A change is declared when ``change_count`` of the last ``change_window`` NIS exceed it,
        at ``change_count`` distinct configurations (see ``change_separation``).
        3 of 4: a detector whose errors cross the 99.99 % bound a fraction ``e`` of the time
        raises a false alarm with probability about ``4 e^3`` per update (``3 e^2`` for 2 of 3);
        the simulated ArUco detector at 1.7 m has ``e`` near 4 % (``tools.fit_noise``), where
        2 of 3 falsely fired in 3 of 24 replayed runs and 3 of 4 in none
        (``tools.error_replay``).
    warmup : int
        Updates while the estimate is still far from the truth: the residuals of the first
        observations of a paper-wide prior are tens of standard deviations because the estimate
        is far, not because the data are bad. During the warm-up the loss is Huber (whose pull
        does not vanish for large residuals; a redescending loss such as Cauchy would dismiss
        every early observation as an outlier) and the change test does not fire (measured on
        rendered runs: the only false alarms fell at observations 4-5).
    change_separation : float
        Two exceedances of the change test whose largest joint difference is below this [rad] are
        at the same configuration and count once (0: every exceedance counts).
    jump_length, jump_angle : float
        Standard deviation of the jump added when a change is detected [m], [rad].
    change_confirm : bool
        A change the test declares stands only if the re-solve with the jump explains most of
        its evidence (more than half of the exceeding observations within the outlier bound);
        otherwise the jump is withdrawn, the observation is taken as if the test had not fired
        and the judged exceedances leave the test's window. A changed body is explained at once
        (synthetic: after a 10 mm, 3 deg change every exceeding observation was at chi-square
        2.0 or less in all of 20 runs); detection errors that repeat at neighbouring views are not.
    covariance : str
        ``'sandwich'``: the robust estimate's own covariance, with the residuals' spread measured
        at the solution (:func:`sandwich_covariance`; Gauss-Newton while too few observations);
        ``'sandwich_hc3'``: the same with the spread of leverage-corrected residuals (right also
        when a few selected observations inform a direction alone); ``'sandwich_blocks'``: that
        spread pooled separately over the detections' position rows and their orientation rows
        (right also when the law misjudges the two by different factors); ``'sandwich_white'``: each
        residual row's own spread (White's HC1 form: right also when the law's shape, not only
        its scale, is wrong); ``'sandwich_white_hc2'`` and ``'sandwich_white_hc3'``: each row's own
        leverage-corrected spread (their HC2 and HC3 forms; the iCub's description takes HC2);
        ``'gauss_newton'``: the
        inverse Gauss-Newton information, inliers as Gaussian evidence
        of the stated covariance, outliers at their robust weight.
    twins : bool
        After each re-solve, move to the exact twin of the estimate (angles modulo 2 pi, inner
        frames turned by pi, a free marker taking the flange's turn) nearest the prior, and
        re-solve there.
    restart_after : int
        After this many consecutive outliers, also solve from the prior mean (cold) and keep
        whichever solution has the lower objective; 0: never. From a far initial guess the
        first observations can lead the warm-started solver into a wrong basin, where every new
        observation is an outlier and the robust loss lets the estimate stay (a Panda run:
        39 outliers in a row). Under the stated noise law 3 in a row has probability
        ``(1 - outlier_probability)^3``; a restart that finds nothing lower changes nothing.
    """

    loss: str = 'cauchy'
    loss_scale: float = 3.0
    outlier_probability: float = 0.999
    max_nfev: int = 30
    verdict_nfev: int = 0
    window: int = 100
    q_length: float = 0.0
    q_angle: float = 0.0
    change_probability: float = 0.9999
    change_window: int = 4
    change_count: int = 3
    change_separation: float = float(np.radians(1.0))
    warmup: int = 10
    jump_length: float = 0.01
    jump_angle: float = float(np.radians(3.0))
    change_confirm: bool = True
    covariance: str = 'sandwich'
    twins: bool = True
    restart_after: int = 3

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f'loss must be one of {LOSSES}, got {self.loss!r}')
        if self.covariance not in COVARIANCES:
            raise ValueError(f'covariance must be one of {COVARIANCES}, got {self.covariance!r}')
        for name in ('loss_scale', 'jump_length', 'jump_angle'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        for name in ('q_length', 'q_angle'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f'{name} must be finite and >= 0, got {v}')
        if not 0.0 < self.outlier_probability < 1.0:
            raise ValueError(f'outlier_probability must be in (0, 1), got {self.outlier_probability}')
        if not 0.0 <= self.change_probability < 1.0:
            raise ValueError(f'change_probability must be in [0, 1), got {self.change_probability}')
        if self.max_nfev < 1:
            raise ValueError(f'max_nfev must be >= 1, got {self.max_nfev}')
        if self.verdict_nfev < 0:
            raise ValueError(f'verdict_nfev must be >= 0, got {self.verdict_nfev}')
        if self.window < 0 or (0 < self.window < 2):
            raise ValueError(f'window must be 0 (all) or >= 2, got {self.window}')
        if self.change_window < 1:
            raise ValueError(f'change_window must be >= 1, got {self.change_window}')
        if self.restart_after < 0:
            raise ValueError(f'restart_after must be >= 0, got {self.restart_after}')
        if self.warmup < 0:
            raise ValueError(f'warmup must be >= 0, got {self.warmup}')
        if not (np.isfinite(self.change_separation) and self.change_separation >= 0):
            raise ValueError(f'change_separation must be finite and >= 0 [rad], got {self.change_separation}')
        if not 1 <= self.change_count <= self.change_window:
            raise ValueError(f'change_count must be in [1, change_window={self.change_window}], '
                             f'got {self.change_count}')


class _UnexplainedChange(Exception):
    """The change test fired and the re-solve with the jump does not explain its evidence."""


@dataclass(frozen=True)
class MapUpdate:
    """What one :meth:`MapEstimator.update` did.

    Attributes
    ----------
    innovation : ndarray, shape (6,)
        ``z (-) h(x, q)`` at the estimate before the update.
    S : ndarray, shape (6, 6)
        Its predicted covariance ``H P H^T + R``.
    nis : float
        ``innovation^T S^-1 innovation`` (chi-square with 6 dof when consistent).
    mahalanobis : float
        ``sqrt(nis)``.
    residual_chi2 : float
        The new observation's whitened residual squared at the new solution.
    outlier : bool
        ``residual_chi2`` beyond the ``outlier_probability`` bound.
    change_detected : bool
        The change test fired at this observation and the change stands (a jump was added).
    nfev : int
        Residual evaluations of the re-solve.
    twin_move : bool
        The estimate moved to a twin nearer the prior (:attr:`MapSettings.twins`).
    restart : bool
        A solve from the prior mean found a lower objective and was kept
        (:attr:`MapSettings.restart_after`).
    resolved : bool
        The re-solve stopped at ``max_nfev`` with the observation beyond the bound and was
        continued before the verdict (:attr:`MapSettings.verdict_nfev`).
    change_withdrawn : bool
        The change test fired, but the re-solve with the jump left most of its evidence beyond
        the outlier bound: the jump was withdrawn (:attr:`MapSettings.change_confirm`).
    """

    innovation: NDArray[np.float64]
    S: NDArray[np.float64]
    nis: float
    mahalanobis: float
    residual_chi2: float
    outlier: bool
    change_detected: bool
    nfev: int
    twin_move: bool = False
    restart: bool = False
    resolved: bool = False
    change_withdrawn: bool = False


def _inv_chol(m: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """``L^-1`` with ``m = L L^T``; whitening by it makes residuals unit-covariance."""
    try:
        c = np.linalg.cholesky(m)
    except np.linalg.LinAlgError as exc:
        raise InvalidInputError(f'{name} is not symmetric positive definite') from exc
    return np.linalg.inv(c)


def pose_residuals(z: NDArray[np.float64], hand: NDArray[np.float64]) -> NDArray[np.float64]:
    """SO(3)-aware residuals ``(p_z - p_h, log(R_z R_h^T))`` of N pose pairs.

    Parameters
    ----------
    z, hand : ndarray, shape (N, 4, 4)

    Returns
    -------
    ndarray, shape (N, 6)
    """
    rot = kinematics.rotation_vector_error(z[:, :3, :3], hand[:, :3, :3])
    return np.concatenate([z[:, :3, 3] - hand[:, :3, 3], np.reshape(rot, (-1, 3))], axis=1)


class MapEstimator:
    """Online MAP estimate of a DH table from hand-pose observations.

    Parameters
    ----------
    base : array_like, shape (4, 4)
        Root to the frame before the first estimated link.
    x0 : array_like, shape (L, 4) or (4 L + e,)
        Prior mean (the initial guess); with ``extrinsics``, followed by its ``e = extrinsics.n``
        corrections.
    P0 : array_like, shape (n, n), n = 4 L + e
        Prior covariance (symmetric positive definite).
    settings : MapSettings
    limits : array_like, shape (L, 2), optional
        Joint limits [rad]; observations outside them are refused.
    fixed_directions : array_like, shape (4 L, k), optional
        Orthonormal directions the data cannot inform, held at ``x0`` (none by default).
    fixed_std : float or array_like, shape (k,)
        Standard deviation of that prior along each direction (one for all, or one each) [m or
        rad per unit direction].
    extrinsics : Extrinsics, optional
        Camera / marker corrections estimated with the table (none by default: the hand pose is
        ``FK`` exactly as before).

    Attributes
    ----------
    x : ndarray, shape (4 L,)
        Current MAP estimate.
    P : ndarray, shape (4 L, 4 L)
        Its covariance (inverse Gauss-Newton information at ``x``).
    fixed_directions : ndarray, shape (n, k)
        The held directions, as given.
    fixed_std : ndarray, shape (k,)
        The prior's standard deviation along each.
    last : MapUpdate or None
        Report of the last update.
    n_updates, n_changes, n_changes_withdrawn, n_marginalised, n_twin_moves, n_restarts, n_resolved, \
    n_outlier_verdicts : int
        Observations used, changes detected (and standing), changes withdrawn
        (:attr:`MapSettings.change_confirm`), observations folded into the prior, moves to a
        twin nearer the prior, restarts kept, truncated solves continued before a verdict,
        updates judged an outlier (:attr:`n_outliers` counts those still beyond the bound now).
    outlier_run : int
        Consecutive outliers up to the last update.
    converged : bool
        The last re-solve ended before its evaluation cap (scipy's status other than 0).
    """

    def __init__(self, base: ArrayLike, x0: ArrayLike, P0: ArrayLike,  # noqa: N803
                 settings: MapSettings = MapSettings(), limits: ArrayLike | None = None,
                 fixed_directions: ArrayLike | None = None, fixed_std: float | ArrayLike = 1e-6,
                 extrinsics: Extrinsics | None = None) -> None:
        self.base = np.asarray(base, dtype=float)
        self.extrinsics = extrinsics if extrinsics is not None and extrinsics.n else None
        n_extra = 0 if self.extrinsics is None else self.extrinsics.n
        x0 = np.array(x0, dtype=float).ravel()
        if (x0.size - n_extra) % kinematics.PARAMS_PER_LINK or x0.size <= n_extra or not np.all(np.isfinite(x0)):
            raise InvalidInputError(f'x0 must hold 4 finite parameters per link and {n_extra} extrinsic '
                                    f'corrections, got {x0.size} values')
        self.n = x0.size
        self.n_dh = self.n - n_extra
        self.n_links = self.n_dh // kinematics.PARAMS_PER_LINK
        P0 = np.array(P0, dtype=float)  # noqa: N806
        if P0.shape != (self.n, self.n) or not np.all(np.isfinite(P0)) or \
                np.max(np.abs(P0 - P0.T)) > 1e-9 * np.max(np.abs(P0)):
            raise InvalidInputError(f'P0 must be a finite symmetric ({self.n}, {self.n}) matrix, got {P0.shape}')
        _inv_chol(P0, 'P0')
        v = np.zeros((self.n, 0)) if fixed_directions is None else np.array(fixed_directions, dtype=float)
        if v.ndim != 2 or v.shape[0] != self.n or not np.all(np.isfinite(v)) or \
                not np.allclose(v.T @ v, np.eye(v.shape[1]), atol=1e-8):
            raise InvalidInputError(f'fixed_directions must be an orthonormal ({self.n}, k) matrix, got shape {v.shape}')
        std = np.broadcast_to(np.asarray(fixed_std, dtype=float), (v.shape[1],)) if np.ndim(fixed_std) == 0 \
            else np.asarray(fixed_std, dtype=float)
        if std.shape != (v.shape[1],) or not np.all(np.isfinite(std) & (std > 0)):
            raise InvalidInputError(f'fixed_std must be one or {v.shape[1]} finite values > 0, got {fixed_std!r}')
        # Rows of the fixing prior: V^T (x - x0) / std ~ N(0, I).
        self._fix_rows = v.T / std[:, None]
        self._fix_anchor = x0.copy()
        self.fixed_directions = v
        self.fixed_std = std.copy()
        self.settings = settings
        self.limits = None if limits is None else np.asarray(limits, dtype=float)
        per_link = np.array([settings.q_length, settings.q_length, settings.q_angle, settings.q_angle])
        self._q = np.concatenate([np.tile(per_link, self.n_links), np.zeros(n_extra)])
        jump = np.array([settings.jump_length, settings.jump_length, settings.jump_angle, settings.jump_angle])
        self._jump = np.concatenate([np.tile(jump ** 2, self.n_links), np.zeros(n_extra)])
        self._outlier_bound = float(chi2.ppf(settings.outlier_probability, 6))
        self._change_bound = float(chi2.ppf(settings.change_probability, 6)) \
            if settings.change_probability > 0 else np.inf
        # The problem: prior (x_p, P_p) and the observations in the window.
        self.x_p = x0.copy()
        self.P_p = P0.copy()
        self.qs = np.zeros((0, self.n_links))
        self.zs = np.zeros((0, 4, 4))
        self.Rs = np.zeros((0, 6, 6))
        self.drift = np.zeros((0, self.n))         # diagonal drift accumulated since each was taken
        self.x = x0.copy()
        self.P = P0.copy()
        self.last: MapUpdate | None = None
        self.n_updates = 0
        self.n_changes = 0
        self.n_changes_withdrawn = 0              # changes the re-solve did not explain (change_confirm)
        self.n_marginalised = 0
        self.n_twin_moves = 0
        self.n_restarts = 0
        self.n_resolved = 0                       # truncated solves continued before an outlier verdict
        self.n_outlier_verdicts = 0
        self.converged = True                     # the last re-solve ended before its evaluation cap
        self.outlier_run = 0                      # consecutive outliers, for the restart
        self._recent_nis: list[float] = []
        self._recent_q: list[NDArray[np.float64]] = []    # the configurations of _recent_nis

    # ------------------------------------------------------------------------------------------
    # Model

    def table(self, x: ArrayLike | None = None) -> NDArray[np.float64]:
        """``x`` (default: the estimate) as a DH table, shape (L, 4)."""
        x = self.x if x is None else np.asarray(x)
        return np.reshape(x[:self.n_dh], (self.n_links, kinematics.PARAMS_PER_LINK))

    def _model(self, x: NDArray[np.float64], qs: NDArray[np.float64], jacobian: bool = True
               ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Predicted hand poses (N, 4, 4) at ``qs`` (N, L) and their Jacobian (N, 6, n) or None."""
        frames = kinematics.chain_frames(self.base, self.table(x), qs)
        if self.extrinsics is not None:
            return self.extrinsics.predict(frames, x[self.n_dh:], jacobian)
        return frames[:, -1], kinematics.pose_jacobian_from_frames(frames) if jacobian else None

    def predict(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Predicted hand pose (4, 4) at joints ``q`` (L,) and its Jacobian ``H`` (6, n)."""
        hands, J = self._model(self.x, np.asarray(q, dtype=float)[None])  # noqa: N806
        return hands[0], J[0]

    @property
    def n_observations(self) -> int:
        """Observations in the nonlinear problem (the window)."""
        return self.qs.shape[0]

    # ------------------------------------------------------------------------------------------
    # Update

    def _check(self, q: ArrayLike, pose: ArrayLike, R: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:  # noqa: N803
        q = np.array(q, dtype=float)
        pose = np.array(pose, dtype=float)
        R = np.array(R, dtype=float)  # noqa: N806
        if q.shape != (self.n_links,):
            raise InvalidInputError(f'joint configuration must have shape ({self.n_links},), got {q.shape}')
        if pose.shape != (4, 4):
            raise InvalidInputError(f'pose observation must be a 4x4 transform, got {pose.shape}')
        if R.shape != (6, 6):
            raise InvalidInputError(f'R must have shape (6, 6), got {R.shape}')
        for name, a in (('joint configuration', q), ('pose observation', pose), ('R', R)):
            if not np.all(np.isfinite(a)):
                raise InvalidInputError(f'{name} contains NaN or inf: {np.array2string(a, threshold=12)}')
        if np.max(np.abs(R - R.T)) > 1e-8 * np.max(np.abs(R)) + 1e-15:
            raise InvalidInputError('R is not symmetric')
        if np.linalg.eigvalsh(R)[0] <= 0:
            raise InvalidInputError(f'R is not positive definite (eigenvalues {np.linalg.eigvalsh(R)})')
        rot = pose[:3, :3]
        if np.max(np.abs(rot @ rot.T - np.eye(3))) > 1e-6 or abs(np.linalg.det(rot) - 1.0) > 1e-6:
            raise InvalidInputError('pose observation has no proper rotation block')
        if self.limits is not None:
            out = (q < self.limits[:, 0] - 1e-9) | (q > self.limits[:, 1] + 1e-9)
            if np.any(out):
                j = int(np.argmax(out))
                raise InvalidInputError(f'joint {j} at {np.degrees(q[j]):.3f} deg is outside its limits '
                                        f'[{np.degrees(self.limits[j, 0]):.3f}, {np.degrees(self.limits[j, 1]):.3f}] deg')
        return q, pose, R

    def innovation(self, q: ArrayLike, pose: ArrayLike, R: ArrayLike) -> tuple[NDArray, NDArray]:  # noqa: N803
        """Innovation (6,) and its covariance ``S`` (6, 6) of an observation, without using it."""
        q, pose, R = self._check(q, pose, R)  # noqa: N806
        hand, H = self.predict(q)  # noqa: N806
        y = pose_residuals(pose[None], hand[None])[0]
        return y, H @ self.P @ H.T + R

    def update(self, q: ArrayLike, pose: ArrayLike, R: ArrayLike) -> MapUpdate:  # noqa: N803
        """Add one hand-pose observation and re-solve.

        Parameters
        ----------
        q : array_like, shape (L,)
            Joint configuration [rad].
        pose : array_like, shape (4, 4)
            Observed hand pose in the root frame.
        R : array_like, shape (6, 6)
            Its covariance (position [m], rotation vector [rad]).

        Raises
        ------
        InvalidInputError
            On NaN, mis-shaped, non-SPD or out-of-limits input; nothing changes.
        FilterError
            If the re-solve fails (nothing changes).
        """
        q, pose, R = self._check(q, pose, R)  # noqa: N806
        saved = self._state()
        try:
            try:
                return self._update(q, pose, R)
            except _UnexplainedChange:
                # The jump let the estimate move and the new body still leaves most of the evidence
                # beyond the bound: detection errors, not a change. Update as if the test had not
                # fired, and drop the judged exceedances (else the next update would count them again).
                self._restore(saved)
                u = replace(self._update(q, pose, R, allow_change=False), change_withdrawn=True)
                self._recent_nis, self._recent_q = [], []
                self.n_changes_withdrawn += 1
                self.last = u
                return u
        except Exception:
            self._restore(saved)
            raise

    def _distinct_exceedances(self, beyond: list[bool]) -> int:
        """How many of the recent exceedances lie at distinct configurations: each one counts
        unless an earlier exceedance in the window is closer than ``change_separation`` to it."""
        sep = self.settings.change_separation
        seen: list[NDArray[np.float64]] = []
        for q, b in zip(self._recent_q, beyond):
            # NaN configurations (an old checkpoint's) are never "the same": they count.
            if b and not any(np.max(np.abs(q - o)) < sep for o in seen):
                seen.append(q)
        return len(seen)

    def _update(self, q: NDArray, pose: NDArray, R: NDArray, allow_change: bool = True) -> MapUpdate:  # noqa: N803
        s = self.settings
        # Random walk between observations: old evidence and the prior age by Q.
        if np.any(self._q > 0):
            self.drift += self._q
            self.P_p = self.P_p + np.diag(self._q)
            self.P = self.P + np.diag(self._q)
        hand, H = self.predict(q)  # noqa: N806
        y = pose_residuals(pose[None], hand[None])[0]
        S = H @ self.P @ H.T + R  # noqa: N806
        nis = float(y @ np.linalg.solve(S, y))
        change = False
        self._recent_nis = (self._recent_nis + [nis])[-s.change_window:]
        self._recent_q = (self._recent_q + [q])[-s.change_window:]
        beyond = [v > self._change_bound for v in self._recent_nis]
        if allow_change and self.n_updates >= s.warmup and self._distinct_exceedances(beyond) >= s.change_count:
            # The body changed: everything known so far (prior and stored observations) may be
            # off by a jump. The stored observations since the first exceedance are evidence of
            # the new body, so they are not aged.
            keep = len(beyond) - 1 - beyond.index(True)
            old = max(0, self.n_observations - keep)
            self.drift[:old] += self._jump
            self.P_p = self.P_p + np.diag(self._jump)
            self.n_changes += 1
            evidence = np.flatnonzero(beyond) - len(beyond)      # the exceedances, as stored rows from the end
            self._recent_nis, self._recent_q = [], []
            change = True
        self.qs = np.vstack([self.qs, q[None]])
        self.zs = np.concatenate([self.zs, pose[None]])
        self.Rs = np.concatenate([self.Rs, R[None]])
        self.drift = np.vstack([self.drift, np.zeros((1, self.n))])
        if s.window and self.n_observations > s.window:
            self._marginalise_oldest()
        nfev = self._solve()
        moved = s.twins and self._move_to_nearest_twin()
        if moved:
            nfev += self._solve()
        r_new = self._whitened(self.x)[-1]
        chi = float(r_new @ r_new)
        resolved = False
        if s.verdict_nfev and chi > self._outlier_bound and not self.converged:
            nfev += self._solve(s.verdict_nfev)
            resolved = True
            self.n_resolved += 1
            r_new = self._whitened(self.x)[-1]
            chi = float(r_new @ r_new)
        self.n_updates += 1
        outlier = chi > self._outlier_bound
        self.outlier_run = self.outlier_run + 1 if outlier else 0
        restart = False
        if s.restart_after and self.outlier_run >= s.restart_after:
            restart, used = self._restart()
            nfev += used
            if restart:
                r_new = self._whitened(self.x)[-1]
                chi = float(r_new @ r_new)
                outlier = chi > self._outlier_bound
                self.outlier_run = int(outlier)
        if change and s.change_confirm:
            # The exceedances are the change's evidence: a new body explains most of them at once.
            # (Those a window shorter than the test's has folded into the prior are not judged.)
            rows = evidence[evidence >= -self.n_observations]
            judged = np.sum(self._whitened(self.x)[rows] ** 2, axis=1)
            if rows.size and 2 * int(np.sum(judged <= self._outlier_bound)) <= rows.size:
                raise _UnexplainedChange
        self.n_outlier_verdicts += int(outlier)
        self.last = MapUpdate(y, S, nis, float(np.sqrt(nis)), chi, outlier, change, nfev, moved, restart, resolved)
        return self.last

    def _restart(self) -> tuple[bool, int]:
        """Solve from the prior mean; keep it if its objective is lower. Returns (kept, evaluations)."""
        kept = self._state()
        w = self._effective_whitening()
        current = self.objective(self.x, w)
        self.x = self.x_p.copy()
        try:
            nfev = self._solve(max(200, self.settings.max_nfev))
            if self.settings.twins and self._move_to_nearest_twin():
                nfev += self._solve()
        except FilterError:
            self._restore(kept)
            return False, 0
        if self.objective(self.x, w) < current:
            self.n_restarts += 1
            return True, nfev
        self._restore(kept)
        return False, nfev

    def solve_batch(self, qs: ArrayLike, poses: ArrayLike, Rs: ArrayLike, max_nfev: int = 200) -> int:  # noqa: N803
        """Add many observations and solve once (the batch MAP of prior + all of them).

        Parameters
        ----------
        qs : array_like, shape (N, L)
        poses : array_like, shape (N, 4, 4)
        Rs : array_like, shape (N, 6, 6)
        max_nfev : int
            Residual evaluations allowed for the solve (a cold start needs more than an update).

        Returns
        -------
        int
            Residual evaluations used.
        """
        checked = [self._check(q, z, r) for q, z, r in zip(qs, poses, Rs)]
        if not checked:
            return 0
        self.qs = np.vstack([self.qs] + [c[0][None] for c in checked])
        self.zs = np.concatenate([self.zs] + [c[1][None] for c in checked])
        self.Rs = np.concatenate([self.Rs] + [c[2][None] for c in checked])
        self.drift = np.vstack([self.drift, np.zeros((len(checked), self.n))])
        self.n_updates += len(checked)
        nfev = self._solve(max_nfev)
        if self.settings.twins and self._move_to_nearest_twin():
            nfev += self._solve(max_nfev)
        return nfev

    # ------------------------------------------------------------------------------------------
    # The nonlinear least-squares problem

    def _effective_whitening(self) -> NDArray[np.float64]:
        """``L_i^-1`` (N, 6, 6) of ``R_i + H_i D_i H_i^T``, with ``H_i`` at the warm start."""
        R = self.Rs  # noqa: N806
        if np.any(self.drift > 0):
            J = self._model(self.x, self.qs)[1]  # noqa: N806
            R = R + np.einsum('nij,nj,nkj->nik', J, self.drift, J)  # noqa: N806
        c = np.linalg.cholesky(R)
        return np.linalg.inv(c)

    def _whitened(self, x: NDArray[np.float64], w: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Whitened observation residuals at ``x``, shape (N, 6)."""
        w = self._effective_whitening() if w is None else w
        hand = self._model(x, self.qs, jacobian=False)[0]
        return np.einsum('nij,nj->ni', w, pose_residuals(self.zs, hand))

    def _solve(self, max_nfev: int | None = None) -> int:
        w = self._effective_whitening()
        lp = _inv_chol(self.P_p, 'prior covariance')
        qs, zs, x_p = self.qs, self.zs, self.x_p

        # Prior rows first (the fixing prior's below the DH prior's): n + k rows ahead of the observations.
        anchor = np.concatenate([lp @ x_p, self._fix_rows @ self._fix_anchor])
        lp = np.vstack([lp, self._fix_rows])
        m = lp.shape[0]

        def fun(x: NDArray[np.float64]) -> NDArray[np.float64]:
            hand = self._model(x, qs, jacobian=False)[0]
            r = np.einsum('nij,nj->ni', w, pose_residuals(zs, hand))
            return np.concatenate([lp @ x - anchor, r.ravel()])

        def jac(x: NDArray[np.float64]) -> NDArray[np.float64]:
            J = self._model(x, qs)[1]  # noqa: N806
            # d(z (-) h)/dx = -H (first order on SO(3), as in the EKF).
            return np.vstack([lp, -np.einsum('nij,njk->nik', w, J).reshape(-1, self.n)])

        s = self.settings
        loss = self._loss()
        try:
            res = least_squares(fun, self.x, jac=jac, method='trf', loss=loss, f_scale=s.loss_scale,
                                max_nfev=max_nfev or s.max_nfev, x_scale='jac')
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise FilterError(f'MAP re-solve failed: {exc}') from exc
        if not np.all(np.isfinite(res.x)):
            raise FilterError('MAP re-solve produced a non-finite estimate')
        # Posterior information: Gauss-Newton at the solution. Observations the solution explains
        # (within the outlier bound) count in full, as Gaussian evidence; only outliers keep their
        # robust (IRLS) weight. scipy's robust-scaled Jacobian would also shrink the weight of
        # 1-2 sigma residuals and so overstate the uncertainty.
        jr = jac(res.x)
        # The noise law is block-diagonal, so the whitening keeps each detection's position rows
        # (0-2) and orientation rows (3-5) apart (a detected change's jump, added to older
        # observations' covariance, mixes them a little).
        groups = np.tile(_POSE_BLOCKS, len(zs)) if s.covariance == 'sandwich_blocks' else None
        P = (sandwich_covariance(jr[:m], jr[m:], res.fun[m:], loss, s.loss_scale,  # noqa: N806
                                 leverage=s.covariance in ('sandwich_hc3', 'sandwich_blocks', 'sandwich_white_hc2',
                                                           'sandwich_white_hc3'),
                                 per_row=s.covariance.startswith('sandwich_white'), groups=groups,
                                 leverage_power=1 if s.covariance == 'sandwich_white_hc2' else 2)
             if s.covariance.startswith('sandwich') else None)
        if P is None:
            r = res.fun[m:].reshape(-1, 6)               # unscaled residuals at the solution
            weights = np.ones_like(r)
            outlier = np.einsum('ni,ni->n', r, r) > self._outlier_bound
            weights[outlier] = _IRLS_WEIGHT[loss]((r[outlier] / s.loss_scale) ** 2)
            jo = jr[m:] * np.sqrt(weights.reshape(-1, 1))
            info = jr[:m].T @ jr[:m] + jo.T @ jo
            try:
                c = np.linalg.cholesky(info)
            except np.linalg.LinAlgError as exc:
                raise FilterError('information matrix at the solution is not positive definite') from exc
            ci = np.linalg.inv(c)
            P = ci.T @ ci  # noqa: N806
        self.x = res.x
        self.P = P
        self.converged = res.status != 0            # 0: stopped at max_nfev
        return int(res.nfev)

    def _loss(self) -> str:
        """The robust loss of the next solve (Huber during the warm-up)."""
        s = self.settings
        return s.loss if self.n_updates >= s.warmup else 'huber'

    def objective(self, x: ArrayLike, w: NDArray[np.float64] | None = None) -> float:
        """What the re-solve minimises at ``x``: ``0.5 scale^2 sum rho`` over the prior, held and
        whitened observation rows (scipy applies the robust loss to every row, the prior's too).

        Parameters
        ----------
        x : array_like, shape (n,)
        w : ndarray, shape (N, 6, 6), optional
            The observations' whitening (default: at the estimate, as the re-solve takes it).
        """
        x = np.asarray(x, dtype=float)
        rows = [self._prior_rows(x)]
        if self.n_observations:
            rows.append(self._whitened(x, w).ravel())
        return float(self._robust_cost(np.concatenate(rows)))

    def _robust_cost(self, rows: NDArray[np.float64]) -> NDArray[np.float64]:
        """``0.5 scale^2 sum rho((rows / scale)^2)`` over the last axis, with the next solve's loss."""
        scale = self.settings.loss_scale
        return 0.5 * scale ** 2 * np.sum(_RHO[self._loss()]((rows / scale) ** 2), axis=-1)

    def _prior_rows(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Whitened prior and held-direction residuals at ``x`` (n,) or (K, n), shape (..., n + k)."""
        lp = _inv_chol(self.P_p, 'prior covariance')
        return np.concatenate([(x - self.x_p) @ lp.T, (x - self._fix_anchor) @ self._fix_rows.T], axis=-1)

    def prior_cost(self, x: ArrayLike) -> NDArray[np.float64]:
        """Squared whitened distance of ``x`` from the prior (Gaussian prior and held directions).

        Parameters
        ----------
        x : array_like, shape (n,) or (K, n)

        Returns
        -------
        ndarray, shape () or (K,)
        """
        return np.sum(self._prior_rows(np.asarray(x, dtype=float)) ** 2, axis=-1)

    def twins(self, x: ArrayLike | None = None) -> NDArray[np.float64]:
        """Every exact twin of ``x`` (default: the estimate), angles nearest the prior's.

        The DH block takes each table of :func:`body_schema.kinematics.twin_tables`. Where the
        marker is estimated, the last link's offset stays (a marker absorbs the last row, which is
        held) and the marker's correction takes its turn instead: the last link turned by pi after
        its joint is ``K^-1 Rz(pi) K`` at the flange, ``K = Tx(a) Rx(alpha)``. Angles are then
        written within pi of the prior mean, and the corrections' rotation vectors with norm at
        most pi. Every row gives the same hand pose as ``x`` at every configuration.

        Returns
        -------
        ndarray, shape (K, n)
            Row 0 is ``x`` itself, rewritten only by the wraps.
        """
        x = self.x if x is None else np.asarray(x, dtype=float)
        tables, _ = kinematics.twin_tables(self.table(x))
        xs = np.repeat(x[None], len(tables), axis=0)
        ex = self.extrinsics
        if ex is not None and 'marker' in ex.blocks:
            turned = ~np.isclose(tables[:, -1, 3], x[self.n_dh - 1])
            tables[:, -1, 3] = x[self.n_dh - 1]
            a, alpha = x[self.n_dh - 4], x[self.n_dh - 2]
            k = np.array([[1.0, 0.0, 0.0, a], [0.0, np.cos(alpha), -np.sin(alpha), 0.0],
                          [0.0, np.sin(alpha), np.cos(alpha), 0.0], [0.0, 0.0, 0.0, 1.0]])
            half = np.diag([-1.0, -1.0, 1.0, 1.0])                  # Rz(pi)
            i = self.n_dh + 6 * ex.blocks.index('marker')
            _, marker = ex.poses(x[self.n_dh:])
            xs[turned, i:i + 6] = pose_delta(np.linalg.inv(k) @ half @ k @ marker, ex.marker)
        xs[:, :self.n_dh] = tables.reshape(len(tables), -1)
        angles = np.zeros(self.n, dtype=bool)
        angles[:self.n_dh] = np.tile([False, False, True, True], self.n_links)
        xs[:, angles] = self.x_p[angles] + kinematics.wrap_angle(xs[:, angles] - self.x_p[angles])
        if ex is not None:
            for j in range(len(ex.blocks)):
                rot = slice(self.n_dh + 6 * j + 3, self.n_dh + 6 * j + 6)
                xs[:, rot] = Rotation.from_rotvec(xs[:, rot]).as_rotvec()
        return xs

    def _move_to_nearest_twin(self) -> bool:
        """Move the estimate to its twin of lowest prior cost; whether it moved.

        The twin is chosen by the objective's prior share (its data share is the same for all);
        it must lower it and keep the data's cost (the construction is exact; the check guards it).
        """
        xs = self.twins()
        # The objective's prior share: row 0 the estimate as it stands, then every twin.
        cost = self._robust_cost(self._prior_rows(np.vstack([self.x[None], xs])))
        best = int(np.argmin(cost[1:]))
        if not cost[1 + best] < cost[0] - 1e-9:
            return False
        w = self._effective_whitening()
        before = float(np.sum(self._whitened(self.x, w) ** 2))
        after = float(np.sum(self._whitened(xs[best], w) ** 2))
        if abs(after - before) > 1e-6 * max(1.0, before):
            return False
        self.x = xs[best]
        self.n_twin_moves += 1
        return True

    def _marginalise_oldest(self) -> None:
        """Fold the oldest observation into the Gaussian prior, linearised at the estimate.

        An observation that is an outlier at the estimate is dropped instead, so a bad sample
        never becomes part of the prior.
        """
        w = self._effective_whitening()[0]
        hands, jac = self._model(self.x, self.qs[:1])
        r = w @ pose_residuals(self.zs[:1], hands)[0]
        if float(r @ r) <= self._outlier_bound:
            J = w @ jac[0]  # noqa: N806
            lam = np.linalg.inv(self.P_p)
            info = lam + J.T @ J
            # r(x) ~ r - J (x - x_hat): the folded prior keeps the observation's pull at x_hat.
            rhs = lam @ self.x_p + J.T @ (r + J @ self.x)
            self.P_p = np.linalg.inv(info)
            self.P_p = 0.5 * (self.P_p + self.P_p.T)
            self.x_p = self.P_p @ rhs
        self.qs, self.zs, self.Rs, self.drift = self.qs[1:], self.zs[1:], self.Rs[1:], self.drift[1:]
        self.n_marginalised += 1

    # ------------------------------------------------------------------------------------------
    # Diagnostics

    def residual_chi2(self) -> NDArray[np.float64]:
        """Whitened residual squared of each stored observation at the estimate, shape (N,)."""
        if self.n_observations == 0:
            return np.zeros(0)
        r = self._whitened(self.x)
        return np.einsum('ni,ni->n', r, r)

    @property
    def n_outliers(self) -> int:
        """Stored observations beyond the outlier bound at the current estimate."""
        return int(np.sum(self.residual_chi2() > self._outlier_bound))

    # ------------------------------------------------------------------------------------------
    # State (checkpoint / resume)

    _ARRAYS = ('x', 'P', 'x_p', 'P_p', 'qs', 'zs', 'Rs', 'drift')
    _COUNTS = ('n_updates', 'n_changes', 'n_changes_withdrawn', 'n_marginalised', 'n_twin_moves', 'n_restarts',
               'n_resolved', 'n_outlier_verdicts', 'outlier_run')

    def _state(self) -> dict[str, object]:
        d: dict[str, object] = {k: np.copy(getattr(self, k)) for k in self._ARRAYS}
        d.update({k: getattr(self, k) for k in self._COUNTS})
        d['recent_nis'] = list(self._recent_nis)
        d['recent_q'] = list(self._recent_q)
        d['last'] = self.last
        return d

    def _restore(self, d: dict[str, object]) -> None:
        for k in self._ARRAYS + self._COUNTS:
            setattr(self, k, d[k])
        self._recent_nis = list(d['recent_nis'])  # type: ignore[arg-type]
        self._recent_q = list(d['recent_q'])  # type: ignore[arg-type]
        self.last = d['last']  # type: ignore[assignment]

    def state_dict(self) -> dict[str, NDArray]:
        """Arrays that restore this estimator exactly (for ``numpy.savez``)."""
        d = {f'map_{k}': np.asarray(getattr(self, k)) for k in self._ARRAYS + self._COUNTS}
        d['map_recent_nis'] = np.asarray(self._recent_nis, dtype=float)
        d['map_recent_q'] = np.array(self._recent_q, dtype=float).reshape(len(self._recent_q), self.qs.shape[1])
        return d

    def load_state_dict(self, d: dict[str, NDArray]) -> None:
        """Restore what :meth:`state_dict` wrote; shapes must match this estimator."""
        for k in ('x', 'x_p'):
            if d[f'map_{k}'].shape != (self.n,):
                raise ValueError(f'state holds {d[f"map_{k}"].size} parameters, expected {self.n}')
        for k in self._ARRAYS:
            setattr(self, k, np.array(d[f'map_{k}'], dtype=float))
        for k in self._COUNTS:
            setattr(self, k, int(d.get(f'map_{k}', 0)))         # a checkpoint written before a count existed
        self._recent_nis = [float(v) for v in d['map_recent_nis']]
        # A checkpoint written before the configurations were kept: each exceedance counts.
        recent_q = d.get('map_recent_q')
        self._recent_q = ([np.array(v, dtype=float) for v in recent_q] if recent_q is not None
                          and len(recent_q) == len(self._recent_nis) else
                          [np.full(self.qs.shape[1], np.nan) for _ in self._recent_nis])
        self.last = None

