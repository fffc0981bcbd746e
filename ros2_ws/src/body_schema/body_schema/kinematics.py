"""Standard Denavit-Hartenberg chains: batched forward kinematics and analytic pose Jacobians.

Convention (robotology/iKin, standard DH): the transform of link ``i`` is

    H_i(q_i) = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i),

and a DH table is an array of shape (L, 4) with columns ``(a, d, alpha, offset)``. The parameter
vector of a chain is the table flattened row-major, so parameter ``4 * i + k`` is column ``k`` of
link ``i``.

Pose errors on SO(3) use a rotation vector in the *base* frame: a small orientation change
``dw`` maps ``R`` to ``exp([dw]x) R``. Pose Jacobians therefore have rows
``(dp_x, dp_y, dp_z, dw_x, dw_y, dw_z)``.

Everything is vectorised over configurations: a loop runs over the (few) links, never over
configurations. The chain functions take ``base`` (4, 4), root to the frame before link 0, ``dh``
(L, 4) and ``q`` (L,) or (N, L); a single configuration gives unbatched results.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    'rotation_angle_deg',
    'PARAMS_PER_LINK',
    'dh_link_transforms',
    'compose_frames',
    'chain_frames',
    'equivalent_table',
    'twin_tables',
    'wrap_angle',
    'forward_kinematics',
    'pose_jacobian_dh',
    'pose_jacobian_from_frames',
    'pose_jacobian_joints',
    'rotation_vector_error',
    'so3_log',
]

#: Columns of a DH table: a [m], d [m], alpha [rad], offset [rad].
PARAMS_PER_LINK = 4


def _cross(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross product over the last axis (np.cross's generic axis handling costs ~30 us a call)."""
    return np.stack([u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1],
                     u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                     u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]], axis=-1)


def _as_configs(q: ArrayLike, n_links: int) -> tuple[NDArray[np.float64], bool]:
    """Return ``q`` as an (N, L) array and whether the input was a single configuration."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    q2 = q[None, :] if single else q
    if q2.ndim != 2 or q2.shape[1] != n_links:
        raise ValueError(f'joint configuration must have shape ({n_links},) or (N, {n_links}), '
                         f'got {q.shape}')
    return q2, single


def dh_link_transforms(dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous transforms of every link for every configuration.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        DH table ``(a, d, alpha, offset)``.
    q : array_like, shape (N, L)
        Joint angles in radians.

    Returns
    -------
    ndarray, shape (N, L, 4, 4)
        ``H_i(q_i)`` for each configuration and link.
    """
    dh = np.asarray(dh, dtype=float)
    q = np.asarray(q, dtype=float)
    a, d, alpha, offset = dh[:, 0], dh[:, 1], dh[:, 2], dh[:, 3]
    theta = q + offset                                  # (N, L)
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)               # (L,)
    n, n_links = theta.shape
    h = np.zeros((n, n_links, 4, 4))
    h[..., 0, 0] = ct
    h[..., 0, 1] = -st * ca
    h[..., 0, 2] = st * sa
    h[..., 0, 3] = a * ct
    h[..., 1, 0] = st
    h[..., 1, 1] = ct * ca
    h[..., 1, 2] = -ct * sa
    h[..., 1, 3] = a * st
    h[..., 2, 1] = sa
    h[..., 2, 2] = ca
    h[..., 2, 3] = d
    h[..., 3, 3] = 1.0
    return h


def _batched_links(dh: ArrayLike, q: ArrayLike) -> tuple[NDArray[np.float64], bool]:
    """Link transforms (N, L, 4, 4) for ``q`` of shape (L,) or (N, L), and whether it was (L,)."""
    dh = np.asarray(dh, dtype=float)
    q2, single = _as_configs(q, dh.shape[0])
    return dh_link_transforms(dh, q2), single


def chain_frames(base: ArrayLike, dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Every frame of the chain in the base (root) frame.

    Parameters
    ----------
    base : array_like, shape (4, 4)
        Root to the frame before link 0.
    dh : array_like, shape (L, 4)
    q : array_like, shape (L,) or (N, L)

    Returns
    -------
    ndarray, shape (L + 1, 4, 4) or (N, L + 1, 4, 4)
        Frame 0 is ``base``; frame ``i + 1`` is the frame after link ``i``; the last is the hand.
    """
    links, single = _batched_links(dh, q)
    frames = compose_frames(base, links)
    return frames[0] if single else frames


def compose_frames(base: ArrayLike, links: ArrayLike) -> NDArray[np.float64]:
    """Frames of a chain of given link transforms, in the base (root) frame.

    Parameters
    ----------
    base : array_like, shape (4, 4)
    links : array_like, shape (N, L, 4, 4)
        Link ``i`` maps the frame after link ``i - 1`` to the frame after link ``i`` (e.g.
        :func:`dh_link_transforms`, or those times an extra rotation per link).

    Returns
    -------
    ndarray, shape (N, L + 1, 4, 4)
        Frame 0 is ``base``; the last is the hand.
    """
    links = np.asarray(links, dtype=float)
    n, n_links = links.shape[:2]
    frames = np.empty((n, n_links + 1, 4, 4))
    frames[:, 0] = np.asarray(base, dtype=float)
    for i in range(n_links):
        frames[:, i + 1] = frames[:, i] @ links[:, i]
    return frames


def forward_kinematics(base: ArrayLike, dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Hand pose(s) in the base frame.

    Returns
    -------
    ndarray, shape (4, 4) or (N, 4, 4)
    """
    # Not chain_frames()[..., -1]: a running product of contiguous arrays is ~3x faster batched.
    links, single = _batched_links(dh, q)
    pose = np.broadcast_to(np.asarray(base, dtype=float), (links.shape[0], 4, 4))
    for i in range(links.shape[1]):
        pose = pose @ links[:, i]
    return pose[0] if single else pose


def pose_jacobian_dh(base: ArrayLike, dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Analytic Jacobian of the hand pose with respect to the DH parameters.

    For link ``i`` with parent frame ``(z_p, o_p)`` and child frame ``(x_c, o_c)``:
    ``offset`` rotates about ``z_p`` through ``o_p``; ``d`` translates along ``z_p``;
    ``a`` translates along ``x_c``; ``alpha`` rotates about ``x_c`` through ``o_c``.

    Returns
    -------
    ndarray, shape (6, 4 L) or (N, 6, 4 L)
        Rows: position (3) then base-frame rotation vector (3); columns: parameters in row-major
        DH-table order ``(a_0, d_0, alpha_0, offset_0, a_1, ...)``.
    """
    return pose_jacobian_from_frames(chain_frames(base, dh, q))


def pose_jacobian_from_frames(frames: ArrayLike) -> NDArray[np.float64]:
    """Pose Jacobian w.r.t. the DH parameters from the frames of :func:`chain_frames`.

    Parameters
    ----------
    frames : array_like, shape (L + 1, 4, 4) or (N, L + 1, 4, 4)

    Returns
    -------
    ndarray, shape (6, 4 L) or (N, 6, 4 L)
    """
    frames = np.asarray(frames, dtype=float)
    single = frames.ndim == 3
    f = frames[None] if single else frames
    p = f[:, -1, :3, 3][:, None, :]                     # (N, 1, 3) hand position
    z_p = f[:, :-1, :3, 2]                              # (N, L, 3) parent z axes
    o_p = f[:, :-1, :3, 3]
    x_c = f[:, 1:, :3, 0]                               # (N, L, 3) child x axes
    o_c = f[:, 1:, :3, 3]
    n, n_links = z_p.shape[:2]
    # Both moment arms in one cross product: x_c x (p - o_c) for alpha, z_p x (p - o_p) for offset.
    arms = _cross(np.concatenate([x_c, z_p], axis=1), np.concatenate([p - o_c, p - o_p], axis=1))
    jac = np.zeros((n, n_links, PARAMS_PER_LINK, 6))
    jac[:, :, 0, :3] = x_c                              # a
    jac[:, :, 1, :3] = z_p                              # d
    jac[:, :, 2, :3] = arms[:, :n_links]                # alpha
    jac[:, :, 2, 3:] = x_c
    jac[:, :, 3, :3] = arms[:, n_links:]                # offset
    jac[:, :, 3, 3:] = z_p
    jac = jac.reshape(n, n_links * PARAMS_PER_LINK, 6).transpose(0, 2, 1)
    return jac[0] if single else jac


def pose_jacobian_joints(base: ArrayLike, dh: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Geometric Jacobian of the hand pose with respect to the joint angles.

    Returns
    -------
    ndarray, shape (6, L) or (N, 6, L)
        Identical to the ``offset`` columns of :func:`pose_jacobian_dh`, since a joint angle
        enters the chain exactly as its offset does.
    """
    jac = pose_jacobian_dh(base, dh, q)
    return jac[..., PARAMS_PER_LINK - 1::PARAMS_PER_LINK]


def so3_log(r: ArrayLike) -> NDArray[np.float64]:
    """Rotation vector of one rotation matrix (the SO(3) logarithm), shape (3,).

    Closed form ``w = theta / (2 sin theta) vee(R - R^T)``: it costs a few microseconds where
    scipy's ``Rotation.from_matrix`` costs ~50, and the EKF residual calls it on every update.
    Near ``theta = pi``, where that form loses precision, it defers to scipy.
    """
    from scipy.spatial.transform import Rotation

    r = np.asarray(r, dtype=float)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos_t = min(1.0, max(-1.0, 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)))
    theta = float(np.arccos(cos_t))
    if theta < 1e-8:
        return 0.5 * v                          # first order: R ~ I + [w]x
    if theta > np.pi - 1e-3:
        return Rotation.from_matrix(r).as_rotvec()
    return (0.5 * theta / np.sin(theta)) * v


def rotation_vector_error(r_target: ArrayLike, r_estimate: ArrayLike) -> NDArray[np.float64]:
    """Base-frame rotation vector ``w`` with ``R_target = exp([w]x) R_estimate``.

    Parameters
    ----------
    r_target, r_estimate : array_like, shape (3, 3) or (N, 3, 3)

    Returns
    -------
    ndarray, shape (3,) or (N, 3)
    """
    from scipy.spatial.transform import Rotation

    r_target = np.asarray(r_target, dtype=float)
    r_estimate = np.asarray(r_estimate, dtype=float)
    rel = r_target @ np.swapaxes(r_estimate, -1, -2)
    return so3_log(rel) if rel.ndim == 2 else Rotation.from_matrix(rel).as_rotvec()


def rotation_angle_deg(r_a: ArrayLike, r_b: ArrayLike) -> NDArray[np.float64]:
    """Geodesic angle between rotations, shape (...) [deg]; inputs (..., 3, 3).

    ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)`` of ``R = R_a R_b^T``: accurate at every
    angle (arccos of the trace alone loses precision near 0 and 180 deg) and far cheaper than a
    Rotation round trip, which matters at three calls per marker per frame.
    """
    rel = np.asarray(r_a, dtype=float) @ np.swapaxes(np.asarray(r_b, dtype=float), -1, -2)
    vee = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
                    rel[..., 1, 0] - rel[..., 0, 1]], axis=-1)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arctan2(np.linalg.norm(vee, axis=-1) / 2.0, cos))


def wrap_angle(angle: ArrayLike) -> NDArray[np.float64]:
    """``angle`` [rad] written in ``[-pi, pi)``."""
    return (np.asarray(angle, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi



def equivalent_table(dh: ArrayLike, near: ArrayLike) -> NDArray[np.float64]:
    """The table that moves the hand exactly as ``dh`` does, written as close to ``near`` as it can be.

    A standard DH table is not unique: ``Rz(pi) Tx(a) Rx(alpha) = Tx(-a) Rx(-alpha) Rz(pi)``, so
    ``(offset_i + pi, -a_i, -alpha_i)`` with ``offset_(i+1) + pi`` gives the same forward
    kinematics for every configuration; and every angle is defined modulo 2 pi. An estimate from
    a far initial guess can settle on such a twin of the truth (the UR5e's elbow with ``a > 0``
    and both neighbouring offsets turned by pi). Scoring it against the truth as written would
    count a perfect estimate as pi radians off; scoring it against this equivalent table does not.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        The table to rewrite (e.g. the truth).
    near : array_like, shape (L, 4)
        The table to be close to (e.g. the estimate).

    Returns
    -------
    ndarray, shape (L, 4)
        Same forward kinematics as ``dh``; a link is turned (links 0 .. L-2: the last one's
        trailing turn would move the flange) where that brings its ``a``, ``alpha`` and
        ``offset`` closer to ``near``'s; every angle within pi of ``near``'s.
    """
    out = np.array(dh, dtype=float)
    ref = np.asarray(near, dtype=float)
    if out.shape != ref.shape or out.ndim != 2 or out.shape[1] != PARAMS_PER_LINK:
        raise ValueError(f'equivalent_table: tables of shape (L, 4) needed, got {out.shape} and {ref.shape}')

    def gap(row: NDArray[np.float64], r: NDArray[np.float64]) -> float:
        return float(abs(row[0] - r[0]) + abs(wrap_angle(row[2] - r[2])) + abs(wrap_angle(row[3] - r[3])))

    for i in range(len(out) - 1):
        turned = out[i] + np.array([0.0, 0.0, 0.0, np.pi])
        turned[0], turned[2] = -turned[0], -turned[2]
        if gap(turned, ref[i]) < gap(out[i], ref[i]):
            out[i] = turned
            out[i + 1, 3] += np.pi
    for col in (2, 3):
        out[:, col] = ref[:, col] + wrap_angle(out[:, col] - ref[:, col])
    return out


def twin_tables(dh: ArrayLike, max_turned: int = 12) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Every table with the same forward kinematics as ``dh`` got by turning inner frames by pi.

    Turning the frame after link ``i`` half a revolution about its own ``z`` axis changes link
    ``i`` to ``(offset_i + pi, -a_i, -alpha_i)`` and adds pi to ``offset_(i+1)``
    (``Rz(pi) Tx(a) Rx(alpha) = Tx(-a) Rx(-alpha) Rz(pi)``); the turns of frames ``0 .. L-2``
    compose freely, so a chain of ``L`` links has ``2^(L-1)`` such twins, angles taken modulo
    2 pi (:func:`equivalent_table` picks one of them greedily).

    Parameters
    ----------
    dh : array_like, shape (L, 4)
    max_turned : int
        Inner frames beyond which only single turns are listed (``2^(L-1)`` grows fast; arms have
        at most about ten links).

    Returns
    -------
    tables : ndarray, shape (K, L, 4)
        The twins, ``tables[0]`` is ``dh`` itself; angles are not wrapped.
    turns : ndarray, shape (K, L - 1)
        Which inner frames each twin turns (0 or 1).
    """
    dh = np.asarray(dh, dtype=float)
    if dh.ndim != 2 or dh.shape[1] != PARAMS_PER_LINK or len(dh) < 1:
        raise ValueError(f'twin_tables: a table of shape (L, 4) needed, got {dh.shape}')
    m = len(dh) - 1
    if m <= max_turned:
        turns = (np.arange(2 ** m)[:, None] >> np.arange(m)[None, :]) & 1
    else:
        turns = np.vstack([np.zeros((1, m), dtype=np.int64), np.eye(m, dtype=np.int64)])
    padded = np.concatenate([np.zeros((len(turns), 1), dtype=np.int64), turns,
                             np.zeros((len(turns), 1), dtype=np.int64)], axis=1)    # frames -1 .. L-1
    out = np.repeat(dh[None], len(turns), axis=0)
    sign = 1.0 - 2.0 * padded[:, 1:]                     # link i's a and alpha flip with its own frame
    out[:, :, 0] *= sign
    out[:, :, 2] *= sign
    out[:, :, 3] += np.pi * (padded[:, :-1] + padded[:, 1:])
    return out, turns.astype(np.int64)
