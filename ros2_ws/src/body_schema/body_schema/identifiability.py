"""Which DH parameter combinations hand-pose measurements can and cannot separate (pure).

A standard DH table of an arm with parallel consecutive axes (a UR's shoulder-lift, elbow and
wrist-1 joints) holds combinations no measurement of the hand can separate: the ``d`` of links
whose joint axes are parallel all translate along one line, so only their sum is observed. An
estimator left to itself drifts along such a direction (or its covariance explodes). This module
finds them from the stacked pose Jacobian over configurations of the calibration box, as
FIGAROH's base parameters do: a rank-revealing QR (``scipy.linalg.qr(pivoting=True)``) picks
the independent ("base") columns; every other column is a combination of those, and each such
dependency is one unidentifiable direction, named by its parameters.

:func:`analyse` gives an :class:`Identifiability`; its :attr:`~Identifiability.null_space`
goes to :class:`body_schema.map_estimator.MapEstimator` (``fixed_directions``), which keeps the
estimate at its prior along it, and :func:`subspace_nees` scores an estimate's consistency on the
identifiable rest.

With a camera pose and a marker offset estimated too (:class:`body_schema.extrinsics.Extrinsics`),
the Jacobian gains their columns; those are taken as base columns first (the pivoted QR then runs
on the DH columns with the corrections' span projected out), so every dependency names a DH
parameter the corrections absorb (the first link's ``d`` and ``offset``, the last link's row) and
:attr:`Identifiability.held_directions` holds those DH parameters themselves, leaving the
camera and the marker free: the base frame and the flange frame stay the table's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from . import kinematics
from .extrinsics import Extrinsics
from .kinematics import PARAMS_PER_LINK
from .robot import ArmModel
from .sampling import uniform_configs

__all__ = ['DH_FIELDS', 'Identifiability', 'parameter_names', 'analyse', 'analyse_jacobian',
           'parallel_axis_groups', 'subspace_nees', 'average_nees_band']

#: Names of a link's four DH parameters, in the order of a table row.
DH_FIELDS = ('a', 'd', 'alpha', 'offset')

#: Relative tolerance on |diag(R)| below which a pivoted QR column counts as dependent. The
#: Jacobian of an exact dependency is dependent to rounding (~1e-15 relative); a merely poorly
#: identifiable parameter of a small box stays far above this.
RANK_TOL = 1e-9

#: Coefficients of a dependency below this are printed as zero.
_COEF_TOL = 1e-6


def parameter_names(joint_names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``<joint>.<field>`` for every DH parameter, in the estimator's order (4 L,)."""
    return tuple(f'{j}.{f}' for j in joint_names for f in DH_FIELDS)


@dataclass(frozen=True)
class Identifiability:
    """What the measurements can separate.

    Attributes
    ----------
    names : tuple of str, length n
        Parameter names (:func:`parameter_names`).
    singular_values : ndarray, shape (n,)
        Of the stacked Jacobian, descending.
    rank : int
        Number of identifiable combinations (base parameters).
    base : tuple of int
        Indices of the base parameters the pivoted QR chose.
    null_space : ndarray, shape (n, n - rank)
        Orthonormal basis of the unidentifiable directions.
    dependencies : tuple of ndarray (n,)
        One per dependent parameter: ``e_dep - sum beta_i e_base_i`` (not normalised), the
        direction along which the hand does not move.
    reasons : tuple of str
        Why, one per dependency, where the geometry explains it (parallel consecutive axes).
    n_dh : int
        How many of the parameters are the DH table's (the rest are extrinsic corrections).
    approximate : tuple of bool
        One per dependency: True where only the exact parallelism of joint axes makes it one. A
        real arm's axes are parallel only to a fraction of a degree, so these combinations are
        weakly observable rather than exact gauge freedoms (what the camera or the marker
        absorbs is exact for any table).
    """

    names: tuple[str, ...]
    singular_values: NDArray[np.float64]
    rank: int
    base: tuple[int, ...]
    null_space: NDArray[np.float64]
    dependencies: tuple[NDArray[np.float64], ...]
    reasons: tuple[str, ...]
    n_dh: int = -1
    approximate: tuple[bool, ...] = ()

    @property
    def n_unidentifiable(self) -> int:
        return self.null_space.shape[1]

    @property
    def held_directions(self) -> NDArray[np.float64]:
        """Orthonormal directions an estimator holds, shape (n, n - rank): the dependencies with
        their extrinsic components dropped (equal to :attr:`null_space` without extrinsics)."""
        if self.n_dh < 0 or self.n_dh == len(self.names) or not self.dependencies:
            return self.null_space
        deps = np.array(self.dependencies).T.copy()
        deps[self.n_dh:] = 0.0
        return scipy.linalg.orth(deps)

    def held_groups(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:attr:`held_directions` split in two orthonormal sets, shapes (n, k_exact), (n, k_approx).

        The second spans the DH parts of the :attr:`approximate` dependencies (parallel axes),
        the first the rest, orthogonal to the second; together they span what
        :attr:`held_directions` spans.
        """
        n = len(self.names)
        flags = self.approximate or (False,) * len(self.dependencies)
        deps = [np.where(np.arange(n) < (self.n_dh if self.n_dh >= 0 else n), v, 0.0) for v in self.dependencies]
        approx = [v for v, a in zip(deps, flags) if a]
        va = scipy.linalg.orth(np.array(approx).T) if approx else np.zeros((n, 0))
        exact = np.array([v - va @ (va.T @ v) for v, a in zip(deps, flags) if not a]).T
        ve = scipy.linalg.orth(exact) if exact.size else np.zeros((n, 0))
        return ve, va

    @property
    def identifiable_basis(self) -> NDArray[np.float64]:
        """Orthonormal basis of the identifiable subspace, shape (n, rank)."""
        return scipy.linalg.null_space(self.null_space.T) if self.n_unidentifiable else np.eye(len(self.names))

    @property
    def condition_number(self) -> float:
        """Of the identifiable part: largest over smallest kept singular value."""
        return float(self.singular_values[0] / self.singular_values[self.rank - 1])

    def combinations(self) -> list[str]:
        """Each unidentifiable direction as a signed combination, e.g. ``'elbow_joint.d - shoulder_lift_joint.d'``."""
        return [_combination(v, self.names) for v in self.dependencies]

    def describe(self) -> list[str]:
        """One line per unidentifiable direction: the combination and why."""
        if not self.dependencies:
            return [f'all {len(self.names)} parameters identifiable over the box '
                    f'(condition number {self.condition_number:.3g})']
        return [f'{c}: {why}' for c, why in zip(self.combinations(), self.reasons)]

    def as_dict(self) -> dict[str, object]:
        """For a YAML export or a report."""
        return {'parameters': len(self.names), 'identifiable': self.rank,
                'unidentifiable': [{'direction': c, 'why': w} for c, w in zip(self.combinations(), self.reasons)]}


def _combination(v: NDArray[np.float64], names: tuple[str, ...]) -> str:
    terms = []
    for i in sorted(range(len(v)), key=lambda k: (-round(abs(float(v[k])), 9), float(v[k]) < 0)):
        c = float(v[i])
        if abs(c) < _COEF_TOL:
            continue
        mag = '' if abs(abs(c) - 1.0) < _COEF_TOL else f'{abs(c):.4g} '
        terms.append(('- ' if c < 0 else '+ ') + mag + names[i])
    text = ' '.join(terms)
    return text[2:] if text.startswith('+ ') else '-' + text[1:]


def parallel_axis_groups(dh: ArrayLike, tol: float = 1e-6) -> list[list[int]]:
    """Runs of consecutive links whose joint axes are parallel.

    Joint ``i + 1`` turns about ``z_i``; ``z_i`` is parallel to ``z_{i-1}`` when link ``i``'s
    ``alpha`` is 0 or pi. Returns lists of link indices (0-based, length >= 2), e.g.
    ``[[1, 2, 3]]`` for a UR arm.
    """
    alpha = np.asarray(dh, dtype=float)[:, 2]
    parallel = np.abs(np.sin(alpha)) < tol          # z_i parallel to z_{i-1}
    groups: list[list[int]] = []
    run: list[int] = []
    for i in range(len(alpha) - 1):
        if parallel[i]:
            run = run or [i]
            run.append(i + 1)
        elif run:
            groups.append(run)
            run = []
    if run:
        groups.append(run)
    return groups


def _parallel_only(v: NDArray[np.float64], dh: NDArray[np.float64]) -> bool:
    """True if ``v`` moves only the d of one run of parallel joint axes."""
    idx = set(np.flatnonzero(np.abs(v) >= _COEF_TOL).tolist())
    return any(idx <= {k * PARAMS_PER_LINK + 1 for k in group} for group in parallel_axis_groups(dh))


def _reason(v: NDArray[np.float64], dh: NDArray[np.float64], joint_names: tuple[str, ...]) -> str:
    idx = set(np.flatnonzero(np.abs(v) >= _COEF_TOL).tolist())
    for group in parallel_axis_groups(dh):
        ds = {k * PARAMS_PER_LINK + 1 for k in group}
        if idx <= ds:
            joints = ', '.join(joint_names[k] for k in group)
            return (f'the axes of joints {joints} are parallel (alpha = 0 or 180 deg between them): '
                    f'their d all translate along that common axis, so only their sum is observed')
    n_dh = dh.size
    dh_idx = {i for i in idx if i < n_dh}
    if idx - dh_idx and dh_idx <= {1, 3}:
        return (f'a turn about and a shift along the first joint axis ({joint_names[0]}) commute with the '
                f'joint: the camera pose absorbs them, held in the table')
    last = set(range(n_dh - PARAMS_PER_LINK, n_dh))
    if idx - dh_idx and dh_idx <= last:
        return (f'everything of the last link after its joint ({joint_names[-1]}) is one fixed transform: '
                f'the marker offset absorbs it, held in the table')
    return 'the pose Jacobian columns are linearly dependent over the box (no geometric rule matched)'


def analyse_jacobian(J: ArrayLike, names: tuple[str, ...], dh: ArrayLike | None = None,  # noqa: N803
                     joint_names: tuple[str, ...] = (), rank_tol: float = RANK_TOL,
                     n_extra: int = 0) -> Identifiability:
    """Identifiability from a stacked Jacobian.

    Parameters
    ----------
    J : array_like, shape (M, n)
        Stacked pose Jacobian (6 rows per configuration) w.r.t. the n parameters.
    names : tuple of str, length n
    dh : array_like, shape (L, 4), optional
        The table ``J`` was taken at; used only to explain dependencies geometrically.
    joint_names : tuple of str
        For the explanations.
    rank_tol : float
        Relative tolerance of the rank decision on the pivoted QR's diagonal.
    n_extra : int
        The last ``n_extra`` columns are extrinsic corrections, taken as base columns first
        (needs ``dh``).
    """
    J = np.asarray(J, dtype=float)  # noqa: N806
    if J.ndim != 2 or J.shape[1] != len(names) or not np.all(np.isfinite(J)):
        raise ValueError(f'J must be a finite (M, {len(names)}) matrix, got shape {J.shape}')
    if J.shape[0] < J.shape[1]:
        raise ValueError(f'J has {J.shape[0]} rows for {J.shape[1]} parameters: use more configurations')
    n = J.shape[1]
    n_dh = n if dh is None or n_extra == 0 else np.asarray(dh).size
    if n_extra:
        # The corrections first: their span projected out, the pivoted QR picks among the DH columns.
        q_e = scipy.linalg.orth(J[:, n_dh:])
        _q, r, piv = scipy.linalg.qr(J[:, :n_dh] - q_e @ (q_e.T @ J[:, :n_dh]), mode='economic', pivoting=True)
        scale = np.linalg.norm(J[:, :n_dh], axis=0)[piv]
        diag = np.abs(np.diag(r))
        keep = diag > rank_tol * max(float(np.max(scale)), 1e-300)
        dh_rank = int(np.sum(keep)) if diag[0] > 0 else 0
        base = np.concatenate([piv[:dh_rank], np.arange(n_dh, n)])
        dep = piv[dh_rank:]
        rank = dh_rank + q_e.shape[1]
    else:
        _q, r, piv = scipy.linalg.qr(J, mode='economic', pivoting=True)
        diag = np.abs(np.diag(r))
        rank = int(np.sum(diag > rank_tol * diag[0])) if diag[0] > 0 else 0
        base, dep = piv[:rank], piv[rank:]
    deps = []
    if dep.size:
        beta = np.linalg.lstsq(J[:, base], J[:, dep], rcond=None)[0]     # (rank, k)
        beta[np.abs(beta) < _COEF_TOL] = 0.0
        for j, col in enumerate(dep):
            v = np.zeros(n)
            v[col] = 1.0
            v[base] = -beta[:, j]
            deps.append(v)
    null = scipy.linalg.orth(np.array(deps).T) if deps else np.zeros((n, 0))
    table = None if dh is None else np.asarray(dh, dtype=float)
    reasons = tuple(_reason(v, table, joint_names) if table is not None
                    else 'the pose Jacobian columns are linearly dependent over the box' for v in deps)
    approximate = tuple(table is not None and _parallel_only(v, table) for v in deps)
    sv = scipy.linalg.svdvals(J)
    return Identifiability(tuple(names), sv, rank, tuple(int(i) for i in base), null, tuple(deps), reasons,
                           n - n_extra if n_extra else n, approximate)


def analyse(model: ArmModel, n: int = 200, seed: int = 0, dh: ArrayLike | None = None,
            box: ArrayLike | None = None, extrinsics: Extrinsics | None = None) -> Identifiability:
    """Identifiability of a robot's DH table from full hand poses over its calibration box.

    Parameters
    ----------
    model : ArmModel
    n : int
        Uniform configurations of the box stacked (the result does not depend on them beyond a
        few dozen: exact dependencies hold at every configuration).
    seed : int
    dh : array_like, shape (L, 4), optional
        Table to linearise at (default: the model's).
    box : array_like, shape (L, 2), optional
        Joint box [rad] (default: the model's calibration box).
    extrinsics : Extrinsics, optional
        Camera / marker corrections estimated with the table (their columns at zero correction).
    """
    table = model.dh if dh is None else np.asarray(dh, dtype=float)
    qs = uniform_configs(model.calibration_box if box is None else box, n, seed)
    names = parameter_names(model.joint_names)
    if extrinsics is None or not extrinsics.n:
        J = model.with_dh(table).jacobian_dh(qs).reshape(-1, table.size)  # noqa: N806
        return analyse_jacobian(J, names, table, model.joint_names)
    frames = kinematics.chain_frames(model.base, table, qs)
    J = extrinsics.predict(frames, np.zeros(extrinsics.n))[1].reshape(-1, table.size + extrinsics.n)  # noqa: N806
    return analyse_jacobian(J, names + extrinsics.names, table, model.joint_names, n_extra=extrinsics.n)


def subspace_nees(error: ArrayLike, P: ArrayLike, basis: ArrayLike) -> float:  # noqa: N803
    """NEES of an estimate's error restricted to a subspace (chi-square with ``basis.shape[1]`` dof).

    Parameters
    ----------
    error : array_like, shape (n,)
        Estimate minus truth.
    P : array_like, shape (n, n)
        The estimate's covariance.
    basis : array_like, shape (n, k)
        Orthonormal basis of the subspace (e.g. :attr:`Identifiability.identifiable_basis`).
    """
    u = np.asarray(basis, dtype=float)
    e = u.T @ np.asarray(error, dtype=float)
    return float(e @ np.linalg.solve(u.T @ np.asarray(P, dtype=float) @ u, e))


def average_nees_band(dofs: Sequence[int], probability: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the average NEES over independent runs (Bar-Shalom, Li and Kirubarajan,
    *Estimation with Applications to Tracking and Navigation*, 2001, sec. 5.4.2).

    The sum of the NEES of consistent runs with ``dofs`` degrees of freedom is chi-square with
    ``sum(dofs)``; the band of their mean is that distribution's band over the number of runs.
    It is the test of consistency over many runs; one run's NEES in its own 95 % band is a much
    weaker statement (a consistent estimator has all of 10 runs inside with probability 0.6).

    Parameters
    ----------
    dofs : sequence of int, length N >= 1
        Degrees of freedom of each run's NEES.
    probability : float
        Coverage of the band.

    Raises
    ------
    ValueError
        If ``dofs`` is empty or holds a value below 1, or ``probability`` is not in (0, 1).
    """
    k = np.asarray(dofs, dtype=float)
    if k.size == 0 or np.any(k < 1):
        raise ValueError(f'average_nees_band: dofs must be >= 1 and not empty, got {list(dofs)}')
    if not 0.0 < probability < 1.0:
        raise ValueError(f'average_nees_band: probability must be in (0, 1), got {probability}')
    tail = (1.0 - probability) / 2.0
    lo, hi = chi2.ppf([tail, 1.0 - tail], k.sum()) / k.size
    return float(lo), float(hi)
