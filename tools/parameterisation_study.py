"""Which kinematic parameterisation the hand-pose data can identify (issue #33, item 2).

Three parameterisations of the same arm are compared on each description's calibration box:

* ``dh``: the standard DH table the estimator estimates today (4 per joint; base and tool fixed);
* ``hayati``: the same with Hayati's ``beta`` (a turn about the link frame's y axis,
  ``H = Rz(q + offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)``) in place of ``d`` for every link whose two
  joint axes are parallel or within :data:`body_schema.urdf_model.NEAR_PARALLEL_DEG` (``d`` held);
* ``origins``: corrections to the joint origins of the URDF (the chain written as
  ``C_0 R_0(q_0) C_1 ... C_{L-1} R_{L-1}(q_{L-1}) C_tool``; a table description gets the equivalent
  origins ``C_k = Tz(d) Tx(a) Rx(alpha) Rz(offset)``), 6 per joint and 6 for the tip's fixed joint,
  each ``C_k -> C_k exp(delta_k)``: a shift along and a turn about the joint frame's own axes.

``dh`` and ``hayati`` fix the base and the tool, so they are also given with 12 more columns, a
correction of the base (left) and of the tool (right) as the camera and marker corrections of
:class:`body_schema.extrinsics.Extrinsics` add (``+bt``): with them each set spans every small
error of the arm's geometry (4 per joint + 6, Everett's count), which ``origins`` does alone.

**Conditioning** (:func:`conditioning`). The pose Jacobian (position and base-frame rotation
vector, :mod:`body_schema.kinematics`) at the nominal arm, stacked over uniform configurations of
the box, rows weighted by ``R^(-1/2)`` of the description's noise law (the UR5e's fitted law where
a description has none: the same camera and 8 cm marker; the built-in law is the iCub's eyes),
columns scaled to unit norm; a QR with column pivoting keeps the columns whose ``|R_ii|`` exceed
:data:`RANK_TOL` of the first (the base set); condition number and smallest singular values of
that part.

**The discontinuity** (:func:`tilt_study`): the second axis of the first parallel pair turned by a
small angle about the DH frame's y (the turn DH cannot follow: the axes stay coplanar and meet far
away) or x (``alpha``'s own turn), and both tables derived again from the axes.

**Accuracy** (:func:`accuracy`): a real arm drawn around the nominal one with the simulator's
widths (``perturb_width_length`` 4 mm, ``perturb_width_angle_deg`` 2 deg, full width, as
:func:`body_schema.sampling.perturb_dh` draws) applied to all six components of every joint origin
and the tool: ``perturb_dh``'s four DH components can turn an axis only about the common normal,
never about y where DH is discontinuous. Its hand poses at the box's configurations with the noise
law's errors; each parameterisation fitted by weighted least squares (``scipy.optimize.least_squares``)
from the nominal arm; hand-pose errors over fresh configurations of the box.

Usage (from the repository root)::

    python -m tools.parameterisation_study [--robots panda kuka_iiwa ur5e] [--configs 50] [--seeds 5]
"""
from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from body_schema import kinematics
from body_schema.noise import PoseDependentNoise, sample_pose
from body_schema.robot import ArmModel, load_robot
from body_schema.sampling import PAPER_WIDTH_ANGLE, PAPER_WIDTH_LENGTH, uniform_configs
from body_schema.urdf_model import (NEAR_PARALLEL_DEG, NearlyParallelAxesWarning, UrdfChain, UrdfJoint,
                                    derive_dh, model_chain, next_dh_row)

__all__ = ['RANK_TOL', 'TRUE_WIDTHS', 'OriginChain', 'Parameterisation', 'Conditioning', 'origin_chain',
           'hayati_links', 'parameterisations', 'noise_for', 'conditioning', 'as_urdf_chain', 'derive_hayati',
           'tilt_study', 'accuracy', 'main']

#: Relative tolerance on the pivoted QR's diagonal below which a column is dependent (as
#: :data:`body_schema.identifiability.RANK_TOL`: exact dependencies sit at rounding, ~1e-15).
RANK_TOL = 1e-9
#: Full widths of the real arm's deviation from the nominal one [m], [rad] (the simulator's).
TRUE_WIDTHS = (0.004, float(np.radians(2.0)))
#: The law the descriptions without one use: the UR5e's fit for the same camera and marker.
_FALLBACK_LAW = 'ur5e'


def _pose(v: ArrayLike) -> NDArray[np.float64]:
    """``[Rot(w) | t]`` of ``v = (t, w)``, shape (..., 6) -> (..., 4, 4); first order the SE(3) exp."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (4, 4))
    out[..., :3, :3] = Rotation.from_rotvec(v[..., 3:].reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))
    out[..., :3, 3] = v[..., :3]
    out[..., 3, 3] = 1.0
    return out


def _turn(axis: ArrayLike, angle: ArrayLike) -> NDArray[np.float64]:
    """Rotation by ``angle`` (...) about unit ``axis`` (3,), shape (..., 4, 4)."""
    angle = np.asarray(angle, dtype=float)
    return _pose(np.concatenate([np.zeros(angle.shape + (3,)), angle[..., None] * np.asarray(axis, float)], -1))


def _screw_columns(frames: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hand-pose Jacobian of a shift along and a turn about each frame's axes, (N, 6, 6 K).

    Parameters
    ----------
    frames : ndarray, shape (N, K, 4, 4)
        Where each correction acts (in the root frame).
    p : ndarray, shape (N, 3)
        The hand's position.
    """
    n, k = frames.shape[:2]
    axes = np.swapaxes(frames[..., :3, :3], -1, -2)                 # (N, K, 3 axes, 3)
    arm = (p[:, None, :] - frames[..., :3, 3])[:, :, None, :]       # (N, K, 1, 3)
    cols = np.zeros((n, k, 6, 6))                                   # (N, K, column, row)
    cols[:, :, :3, :3] = axes
    cols[:, :, 3:, :3] = np.cross(axes, arm)
    cols[:, :, 3:, 3:] = axes
    return cols.reshape(n, 6 * k, 6).transpose(0, 2, 1)


@dataclass(frozen=True)
class OriginChain:
    """An arm as joint origins: ``hand(q) = C_0 R_0(q_0) C_1 R_1(q_1) ... C_{L-1} R_{L-1}(q_{L-1}) C_tool``.

    Attributes
    ----------
    origins : ndarray, shape (L, 4, 4)
        ``C_k``: the previous joint's rotating frame (the root for ``k = 0``) to joint ``k``'s frame.
    axes : ndarray, shape (L, 3)
        Unit joint axes in their joint frames.
    tool : ndarray, shape (4, 4)
        The last joint's rotating frame to the hand (the frame the estimator observes).
    names : tuple of str, length L
    """

    origins: NDArray[np.float64]
    axes: NDArray[np.float64]
    tool: NDArray[np.float64]
    names: tuple[str, ...]

    def frames(self, q: ArrayLike, delta: ArrayLike | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Joint frames (before each joint turns) and hand poses.

        Parameters
        ----------
        q : array_like, shape (N, L)
        delta : array_like, shape (L + 1, 6), optional
            Corrections ``C_k -> C_k exp(delta_k)`` (the last: the tool), ``(shift, turn)``.

        Returns
        -------
        joints : ndarray, shape (N, L, 4, 4)
        hand : ndarray, shape (N, 4, 4)
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n_links = len(self.origins)
        corr = _pose(np.zeros((n_links + 1, 6)) if delta is None else np.reshape(delta, (n_links + 1, 6)))
        pose = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4))
        joints = np.empty((q.shape[0], n_links, 4, 4))
        for k in range(n_links):
            pose = pose @ (self.origins[k] @ corr[k])
            joints[:, k] = pose
            pose = pose @ _turn(self.axes[k], q[:, k])
        return joints, pose @ (self.tool @ corr[-1])


def _rz(theta: float) -> NDArray[np.float64]:
    return _turn([0.0, 0.0, 1.0], theta)


def origin_chain(model: ArmModel) -> OriginChain:
    """The description's arm as joint origins: the URDF's own (fixed joints folded into the next
    revolute one's origin, the tip's into the tool), or a table's ``Tz(d) Tx(a) Rx(alpha) Rz(offset)``."""
    if model.urdf is not None:
        chain, derived = model_chain(model)
        acc = model.base @ np.linalg.inv(derived.base)              # the root -> base_link
        origins, axes = [], []
        for j in chain.joints:
            acc = acc @ j.origin
            if j.kind != 'fixed':
                origins.append(acc)
                axes.append(j.axis)
                acc = np.eye(4)
        return OriginChain(np.array(origins), np.array(axes), acc @ np.linalg.inv(model.tool), model.joint_names)
    rest = kinematics.dh_link_transforms(model.dh * [1, 1, 1, 0], np.zeros((1, model.n_joints)))[0]
    origins = [model.base @ _rz(model.dh[0, 3])]
    origins += [rest[k - 1] @ _rz(model.dh[k, 3]) for k in range(1, model.n_joints)]
    axes = np.tile([0.0, 0.0, 1.0], (model.n_joints, 1))
    return OriginChain(np.array(origins), axes, rest[-1], model.joint_names)


def hayati_links(dh: ArrayLike) -> tuple[int, ...]:
    """Links whose two joint axes are parallel or within ``NEAR_PARALLEL_DEG`` (not the last link:
    its far end is the hand, a frame, not an axis)."""
    alpha = np.asarray(dh, dtype=float)[:-1, 2]
    return tuple(int(k) for k in np.flatnonzero(np.abs(np.sin(alpha)) < np.sin(np.radians(NEAR_PARALLEL_DEG))))


def _beta_hand(base: NDArray[np.float64], table: NDArray[np.float64], beta: NDArray[np.float64],
               q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hand (N, 4, 4) of a chain of ``Rz(q + offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)`` links."""
    links = kinematics.dh_link_transforms(table, q) @ _turn([0.0, 1.0, 0.0], beta)
    return kinematics.compose_frames(base, links)[:, -1]


@dataclass(frozen=True)
class Parameterisation:
    """Parameters of an arm's small errors around its nominal geometry.

    Attributes
    ----------
    key : str
    names : tuple of str, length n
    poses : callable
        ``poses(x (n,), q (N, L)) -> (N, 4, 4)``: the hand with the parameters moved by ``x``.
    jacobian : callable
        ``jacobian(q (N, L)) -> (N, 6, n)``: analytic, at ``x = 0``.
    """

    key: str
    names: tuple[str, ...]
    poses: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]
    jacobian: Callable[[NDArray[np.float64]], NDArray[np.float64]]


def _dh_family(model: ArmModel, hayati: tuple[int, ...], ends: bool) -> Parameterisation:
    """``dh`` (``hayati = ()``) or ``hayati``, with the base and tool corrections if ``ends``."""
    size = model.dh.size
    d_slots = [4 * k + 1 for k in hayati]                           # beta takes d's slot; d is held

    def split(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        table = model.dh.ravel() + x[:size]
        beta = np.zeros(model.n_joints)
        beta[list(hayati)] = x[d_slots]
        table[d_slots] = model.dh.ravel()[d_slots]
        ends_x = x[size:] if ends else np.zeros(12)
        return table.reshape(model.dh.shape), beta, ends_x[:6], ends_x[6:]

    def poses(x: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
        table, beta, b, t = split(np.asarray(x, dtype=float))
        return _pose(b) @ _beta_hand(model.base, table, beta, q) @ _pose(t)

    def jacobian(q: NDArray[np.float64]) -> NDArray[np.float64]:
        frames = kinematics.chain_frames(model.base, model.dh, q)
        jac = kinematics.pose_jacobian_from_frames(frames)
        p = frames[:, -1, :3, 3]
        if hayati:                                                  # a turn about the link frame's y
            turns = _screw_columns(frames[:, [k + 1 for k in hayati]], p)
            jac[:, :, d_slots] = turns.reshape(len(q), 6, len(hayati), 6)[:, :, :, 4]
        if ends:
            ends_frames = np.stack([np.broadcast_to(np.eye(4), (len(q), 4, 4)), frames[:, -1]], axis=1)
            jac = np.concatenate([jac, _screw_columns(ends_frames, p)], axis=2)
        return jac

    names = [f'{j}.{f}' for j in model.joint_names for f in ('a', 'd', 'alpha', 'offset')]
    for k in hayati:
        names[4 * k + 1] = f'{model.joint_names[k]}.beta'
    if ends:
        names += [f'{e}.{c}' for e in ('base', 'tool') for c in ('x', 'y', 'z', 'rx', 'ry', 'rz')]
    key = ('hayati' if hayati else 'dh') + ('+bt' if ends else '')
    return Parameterisation(key, tuple(names), poses, jacobian)


def _origins(chain: OriginChain) -> Parameterisation:
    def poses(x: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
        return chain.frames(q, x)[1]

    def jacobian(q: NDArray[np.float64]) -> NDArray[np.float64]:
        joints, hand = chain.frames(q)
        return _screw_columns(np.concatenate([joints, hand[:, None]], axis=1), hand[:, :3, 3])

    names = tuple(f'{j}.{c}' for j in chain.names + ('tool',) for c in ('x', 'y', 'z', 'rx', 'ry', 'rz'))
    return Parameterisation('origins', names, poses, jacobian)


def parameterisations(model: ArmModel) -> dict[str, Parameterisation]:
    """``dh``, ``hayati``, ``dh+bt``, ``hayati+bt`` and ``origins`` of a description's arm."""
    flagged = hayati_links(model.dh)
    out = {p.key: p for ends in (False, True) for p in (_dh_family(model, (), ends), _dh_family(model, flagged, ends))}
    out.setdefault('hayati', _renamed(out['dh'], 'hayati'))
    out.setdefault('hayati+bt', _renamed(out['dh+bt'], 'hayati+bt'))
    out['origins'] = _origins(origin_chain(model))
    return {k: out[k] for k in ('dh', 'hayati', 'dh+bt', 'hayati+bt', 'origins')}


def _renamed(p: Parameterisation, key: str) -> Parameterisation:
    """``p`` under another key (Hayati with no link to change is DH)."""
    return Parameterisation(key, p.names, p.poses, p.jacobian)


def noise_for(model: ArmModel) -> tuple[PoseDependentNoise, str]:
    """The description's noise law, or the UR5e's fit (same camera and marker) where it has none."""
    if model.noise_law:
        return PoseDependentNoise.for_robot(model), f'{model.name} noise_model'
    fallback = PoseDependentNoise.for_robot(load_robot(_FALLBACK_LAW))
    return fallback, f'{_FALLBACK_LAW} noise_model (none in {model.name})'


def _sqrt_weights(model: ArmModel, noise: PoseDependentNoise, hand: NDArray[np.float64]) -> NDArray[np.float64]:
    """``R^(-1/2)`` diagonals of the hand observations, (N, 6)."""
    cov = noise.hand_covariance(model.camera_pose(model.camera_names[0]), hand, model.markers)
    return 1.0 / np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))


@dataclass(frozen=True)
class Conditioning:
    """What a stacked, weighted, column-scaled Jacobian can identify.

    Attributes
    ----------
    n : int
        Parameters.
    rank : int
        Base set size (pivoted QR, :data:`RANK_TOL`).
    condition : float
        Of the base set's scaled columns.
    smallest : ndarray, shape (3,)
        Their three smallest singular values, ascending.
    dependent : tuple of str
        Parameters the QR left out.
    """

    n: int
    rank: int
    condition: float
    smallest: NDArray[np.float64]
    dependent: tuple[str, ...]


def conditioning(jac: ArrayLike, names: Sequence[str], rank_tol: float = RANK_TOL) -> Conditioning:
    """Base set and conditioning of a stacked Jacobian.

    Parameters
    ----------
    jac : array_like, shape (N, 6, n) or (M, n)
        Weighted pose Jacobian.
    names : sequence of str, length n
    rank_tol : float

    Raises
    ------
    ValueError
        If the Jacobian is not finite, has fewer rows than columns, or a zero column.
    """
    j = np.asarray(jac, dtype=float)
    j = j.reshape(-1, j.shape[-1])
    scale = np.linalg.norm(j, axis=0)
    if not np.all(np.isfinite(j)) or j.shape[0] < j.shape[1] or j.shape[1] != len(names) or np.any(scale == 0):
        raise ValueError(f'conditioning: need a finite (M >= n, n = {len(names)}) Jacobian without zero columns, '
                         f'got shape {j.shape}, zero columns {[names[i] for i in np.flatnonzero(scale == 0)]}')
    js = j / scale                                                  # unit-norm columns: units drop out
    _q, r, piv = scipy.linalg.qr(js, mode='economic', pivoting=True)
    diag = np.abs(np.diag(r))
    rank = int(np.sum(diag > rank_tol * diag[0]))
    sv = scipy.linalg.svdvals(js[:, piv[:rank]])
    return Conditioning(j.shape[1], rank, float(sv[0] / sv[-1]), sv[::-1][:3],
                        tuple(names[i] for i in sorted(piv[rank:])))


def as_urdf_chain(chain: OriginChain) -> UrdfChain:
    """The origin chain as an in-memory URDF chain (links ``l0 .. lL``, the hand on a fixed joint)."""
    joints = [UrdfJoint(n, 'revolute', f'l{k}', f'l{k + 1}', chain.origins[k], chain.axes[k], np.array([-7.0, 7.0]))
              for k, n in enumerate(chain.names)]
    joints.append(UrdfJoint('hand_joint', 'fixed', f'l{len(joints)}', 'hand', chain.tool, np.zeros(3), np.zeros(2)))
    return UrdfChain(tuple(joints), 'l0', 'hand', '')


def _angle(u: NDArray[np.float64], v: NDArray[np.float64], about: NDArray[np.float64]) -> float:
    return float(np.arctan2(np.cross(u, v) @ about, u @ v))


def derive_hayati(chain: UrdfChain, links: Sequence[int]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                                   NDArray[np.float64], NDArray[np.float64]]:
    """The table :func:`body_schema.urdf_model.derive_dh` derives, with Hayati's rows at ``links``.

    A Hayati row's frame has its origin where the next axis crosses the plane through the previous
    frame's origin normal to its z (``d = 0``), x toward it, and ``Rx(alpha) Ry(beta)`` turning z
    onto the next axis; every other row is the standard construction from the frame before it.

    Returns
    -------
    table : ndarray, shape (L, 4)
        ``(a, d, alpha, offset)``, ``d = 0`` at ``links``.
    beta : ndarray, shape (L,)
        Zero outside ``links``.
    base, tool : ndarray, shape (4, 4)
        ``hand = base @ prod(Rz(q + offset) Tz(d) Tx(a) Rx(alpha) Ry(beta)) @ tool`` is the tip.

    Raises
    ------
    ValueError
        If a Hayati link's next axis is perpendicular to its previous one (no crossing point).
    """
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', NearlyParallelAxesWarning)
        base = derive_dh(chain).base
    moving = chain.moving
    poses = [f for f, j in zip(chain.frames(), chain.joints) if j.kind != 'fixed']
    tip = chain.tip_pose()
    targets = [(poses[k + 1][:3, 3], poses[k + 1][:3, :3] @ moving[k + 1].axis, None) for k in range(len(moving) - 1)]
    targets.append((tip[:3, 3], tip[:3, 2], tip[:3, 0]))
    rows, beta, frame = [], np.zeros(len(moving)), base
    for k, (point, z_new, tip_x) in enumerate(targets):
        o, x, z = frame[:3, 3], frame[:3, 0], frame[:3, 2]
        if k in links:
            if abs(z_new @ z) < 1e-9:
                raise ValueError(f'derive_hayati: link {k} ({moving[k].name}) has perpendicular axes; Hayati needs '
                                 'nearly parallel ones')
            cross = point + ((o - point) @ z) / (z_new @ z) * z_new     # the next axis meets the plane here
            a = float(np.linalg.norm(cross - o))
            x_new = (cross - o) / a if a > 1e-12 else x
            y_new = np.cross(z, x_new)
            row = np.array([a, 0.0, np.arctan2(-(z_new @ y_new), z_new @ z), _angle(x, x_new, z)])
            beta[k] = np.arcsin(np.clip(z_new @ x_new, -1.0, 1.0))
        else:
            # derive_dh's own construction, so the tables differ only in the Hayati links
            anchor = o if tip_x is None else point
            row = next_dh_row(frame, point, z_new, anchor, x if tip_x is None else tip_x)[0]
        rows.append(row)
        frame = frame @ kinematics.dh_link_transforms(row[None], np.zeros((1, 1)))[0, 0] @ _turn([0, 1, 0], beta[k])
    return np.array(rows), beta, base, np.linalg.inv(frame) @ tip


def _wrap_deg(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.degrees((a + np.pi) % (2 * np.pi) - np.pi)


def tilt_study(model: ArmModel, tilts_deg: Sequence[float] = (0.01, 0.1, 1.0)) -> list[dict[str, float | str]] | None:
    """How DH and Hayati tables move when the second axis of the first parallel pair turns.

    Returns
    -------
    list of dict or None
        One row per tilt and direction (``about`` ``'y'``: the turn that keeps the axes coplanar,
        ``'x'``: about the common normal, alpha's): the DH ``d`` that moved by over 1 mm [m],
        the largest change of any DH length [m] and angle [deg] against the untilted table, Hayati's
        ``beta`` [deg] and its largest changes of the other parameters. None without a parallel pair.
    """
    flagged = hayati_links(model.dh)
    if not flagged:
        return None
    k = flagged[0]
    chain = origin_chain(model)
    joint_frame = chain.frames(np.zeros((1, model.n_joints)))[0][0, k + 1]
    dh_frame = kinematics.chain_frames(model.base, model.dh, np.zeros(model.n_joints))[k + 1]

    def derive(c: OriginChain) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        urdf = as_urdf_chain(c)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', NearlyParallelAxesWarning)
            dh = derive_dh(urdf).dh
        table, beta = derive_hayati(urdf, flagged)[:2]
        return dh, table, beta

    dh0, hy0, _ = derive(chain)
    rows = []
    for about, col in (('y', 1), ('x', 0)):
        local = joint_frame[:3, :3].T @ dh_frame[:3, col]          # the DH frame's axis in the joint frame
        for tilt in tilts_deg:
            origins = chain.origins.copy()
            origins[k + 1] = origins[k + 1] @ _turn(local, np.radians(tilt))
            dh, hy, beta = derive(OriginChain(origins, chain.axes, chain.tool, chain.names))
            hy_angles = hy[:, 2:].copy()
            moved = np.flatnonzero(np.abs(dh[:, 1] - dh0[:, 1]) > 1e-3)
            rows.append({'tilt_deg': float(tilt), 'about': about,
                         'pair': f'{model.joint_names[k]}-{model.joint_names[k + 1]}',
                         'dh_d_moved': ', '.join(f'{model.joint_names[i]} {dh[i, 1]:.4g}' for i in moved) or 'none',
                         'dh_length': float(np.abs(dh[:, :2] - dh0[:, :2]).max()),
                         'dh_angle': float(np.abs(_wrap_deg(dh[:, 2:] - dh0[:, 2:])).max()),
                         'beta_deg': float(np.degrees(beta[k])),
                         'hayati_length': float(np.abs(hy[:, :2] - hy0[:, :2]).max()),
                         'hayati_angle': float(np.abs(_wrap_deg(hy_angles - hy0[:, 2:])).max())})
    return rows


def _residual(poses: NDArray[np.float64], observed: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    rot = kinematics.rotation_vector_error(observed[:, :3, :3], poses[:, :3, :3])
    return (np.concatenate([observed[:, :3, 3] - poses[:, :3, 3], rot], axis=1) * w).ravel()


def _prior_sd(names: Sequence[str]) -> NDArray[np.float64]:
    """The estimator's initial spread per parameter: ``w / sqrt(12)`` of the paper's widths (angles by name)."""
    angle = ('alpha', 'offset', 'beta', 'rx', 'ry', 'rz')
    widths = [PAPER_WIDTH_ANGLE if n.rsplit('.', 1)[1] in angle else PAPER_WIDTH_LENGTH for n in names]
    return np.array(widths) / np.sqrt(12)


def accuracy(model: ArmModel, params: dict[str, Parameterisation], noise: PoseDependentNoise, n_configs: int,
             seed: int, n_eval: int = 500) -> dict[str, NDArray[np.float64]]:
    """One synthetic identification: a real arm drawn around the nominal one (module docstring),
    ``n_configs`` noisy hand poses of the box, each parameterisation fitted from the nominal arm by
    least squares, alone and with the estimator's prior (:func:`_prior_sd` around the nominal arm,
    as :func:`body_schema.sampling.initial_covariance`: what a MAP estimate adds).

    Returns
    -------
    dict of str to ndarray, shape (2, 3)
        Per parameterisation, rows least squares and with the prior: mean hand position [mm] and
        orientation [deg] error over ``n_eval`` configurations of the box, and the largest
        parameter step of the fit (lengths [m] and angles [rad] alike).
    """
    rng = np.random.default_rng(seed)
    chain = origin_chain(model)
    widths = np.tile(np.repeat(TRUE_WIDTHS, 3), (model.n_joints + 1, 1))
    true_delta = rng.uniform(-0.5, 0.5, widths.shape) * widths
    qs = uniform_configs(model.calibration_box, n_configs, rng)
    truth = chain.frames(qs, true_delta)[1]
    cov = noise.hand_covariance(model.camera_pose(model.camera_names[0]), truth, model.markers)
    observed = np.array([sample_pose(t, c, rng) for t, c in zip(truth, cov)])
    w = _sqrt_weights(model, noise, truth)
    q_eval = uniform_configs(model.calibration_box, n_eval, seed + 10_000)
    true_eval = chain.frames(q_eval, true_delta)[1]
    out = {}
    for key, p in params.items():
        prior = 1.0 / _prior_sd(p.names)
        res = []
        for weight in (0.0, 1.0):
            fit = least_squares(lambda x: np.concatenate([_residual(p.poses(x, qs), observed, w), weight * prior * x]),
                                np.zeros(len(p.names)), method='trf', x_scale='jac', xtol=1e-10, ftol=1e-10,
                                gtol=1e-10, max_nfev=100)
            est = p.poses(fit.x, q_eval)
            pos = np.linalg.norm(est[:, :3, 3] - true_eval[:, :3, 3], axis=1).mean()
            rot = kinematics.rotation_angle_deg(est[:, :3, :3], true_eval[:, :3, :3]).mean()
            res.append((1000.0 * pos, rot, np.abs(fit.x).max()))
        out[key] = np.array(res)
    return out


def _conditioning_table(models: Sequence[ArmModel], n_configs: int, seed: int) -> str:
    lines = ['| robot | parameterisation | parameters | identifiable | condition number | 3 smallest singular values | '
             'left out by the QR |', '|---|---|---|---|---|---|---|']
    for model in models:
        noise, _ = noise_for(model)
        qs = uniform_configs(model.calibration_box, n_configs, seed)
        w = _sqrt_weights(model, noise, model.forward_kinematics(qs))
        for key, p in parameterisations(model).items():
            c = conditioning(p.jacobian(qs) * w[:, :, None], p.names)
            left = ', '.join(c.dependent) if len(c.dependent) <= 3 else str(len(c.dependent))
            lines.append(f'| {model.name} | {key} | {c.n} | {c.rank} | {c.condition:.3g} | '
                         f'{", ".join(f"{s:.3g}" for s in c.smallest)} | {left or "none"} |')
    return '\n'.join(lines)


def _tilt_table(model: ArmModel) -> str:
    rows = tilt_study(model)
    if rows is None:
        return f'{model.name}: no parallel or nearly parallel consecutive axes: DH has nothing to jump.'
    lines = [f'{model.name}, pair {rows[0]["pair"]}: the second axis turned by the tilt about the DH frame\'s axis',
             '', '| tilt [deg] | about | DH d that moved [m] | DH largest change: length [m] / angle [deg] '
             '| Hayati beta [deg] | Hayati largest change: length [m] / angle [deg] |', '|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f'| {r["tilt_deg"]:g} | {r["about"]} | {r["dh_d_moved"]} | '
                     f'{r["dh_length"]:.3g} / {r["dh_angle"]:.3g} | {r["beta_deg"]:.4g} | '
                     f'{r["hayati_length"]:.3g} / {r["hayati_angle"]:.3g} |')
    return '\n'.join(lines)


def _accuracy_table(models: Sequence[ArmModel], n_configs: int, seeds: int, n_eval: int) -> str:
    lines = ['| robot | parameterisation | least squares: position [mm] / orientation [deg], mean (worst seed) | '
             'largest step | with the prior: position [mm] / orientation [deg] | largest step |',
             '|---|---|---|---|---|---|']
    for model in models:
        noise, _ = noise_for(model)
        params = parameterisations(model)
        runs = [accuracy(model, params, noise, n_configs, s, n_eval) for s in range(seeds)]
        for key in params:
            v = np.array([r[key] for r in runs])                   # (seeds, 2, 3)
            cells = [f'{v[:, i, 0].mean():.3f} ({v[:, i, 0].max():.3f}) / {v[:, i, 1].mean():.4f} '
                     f'({v[:, i, 1].max():.4f}) | {v[:, i, 2].max():.3g}' for i in (0, 1)]
            lines.append(f'| {model.name} | {key} | {cells[0]} | {cells[1]} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.parameterisation_study', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robots', nargs='+', default=['panda', 'kuka_iiwa', 'ur5e'], help='descriptions to compare')
    ap.add_argument('--configs', type=int, default=50, help='box configurations stacked / observed (default 50)')
    ap.add_argument('--seed', type=int, default=0, help='seed of the conditioning configurations')
    ap.add_argument('--seeds', type=int, default=5, help='synthetic identifications per robot (0: none)')
    ap.add_argument('--eval', type=int, default=500, help='configurations the accuracy is scored on')
    args = ap.parse_args(argv)
    if args.configs < 9 or args.seeds < 0 or args.eval < 1:
        ap.error(f'--configs must be >= 9 (6 rows each, up to 48 parameters), --seeds >= 0, --eval >= 1; got '
                 f'{args.configs}, {args.seeds}, {args.eval}')
    models = [load_robot(r) for r in args.robots]
    print(f'# Conditioning: {args.configs} uniform configurations of each box (seed {args.seed}); rows weighted by '
          f'R^(-1/2) ({"; ".join(noise_for(m)[1] for m in models)}), columns scaled to unit norm; rank: pivoted QR, '
          f'|R_ii| > {RANK_TOL:g} |R_00|; condition number and singular values of the base set\n')
    print(_conditioning_table(models, args.configs, args.seed))
    print('\n# The discontinuity of DH at parallel axes\n')
    print('\n\n'.join(_tilt_table(m) for m in models))
    if args.seeds:
        print(f'\n# Accuracy: {args.seeds} real arms per robot (every joint origin and the tool off by up to '
              f'+-{TRUE_WIDTHS[0] * 500:g} mm / +-{np.degrees(TRUE_WIDTHS[1]) / 2:g} deg per component), '
              f'{args.configs} noisy hand poses, least squares from the nominal arm; errors over {args.eval} '
              'configurations of the box\n')
        print(_accuracy_table(models, args.configs, args.seeds, args.eval))
    return 0


if __name__ == '__main__':
    sys.exit(main())
