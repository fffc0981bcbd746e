"""Modified DH (Craig's convention) as an exact regrouping of standard DH links (pure).

Craig's link transform is

    ^{i-1}T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i),   theta_i = q_i + offset_i,

and a published modified table (Franka's Panda, Kinova) lists per joint ``i`` the ``a_{i-1}``,
``alpha_{i-1}`` *before* it and its own ``d_i`` and ``offset_i``, plus often a fixed ``flange``
row (``a, d, alpha, theta`` with no joint). This module writes a row as ``[a, d, alpha, offset]``
in that order, the same column order as a standard table, with ``a`` and ``alpha`` those of the
line the row is printed on.

Since ``Tx(a) Rx(alpha) = Rx(alpha) Tx(a)`` (both act along x), the product of modified links
regroups exactly into standard links ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``:

    T = [Rx(alpha_0) Tx(a_0)] prod_i [Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)] [Rz(theta_F) Tz(d_F)]

where ``a_i, alpha_i`` of standard link ``i`` are the next modified row's (the flange row's for the
last link), the first row's ``a, alpha`` become a fixed transform before the chain (the base) and
the flange's ``theta, d`` a fixed transform after it (the tool). The estimator keeps estimating
its standard table; :func:`standard_to_modified` writes an estimate back as a modified table
(the base and tool parts are not estimated: they are the description's).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['modified_to_standard', 'standard_to_modified', 'modified_forward_kinematics']


def _rows(mdh: ArrayLike, flange: ArrayLike | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    table = np.asarray(mdh, dtype=float)
    fl = np.zeros(4) if flange is None else np.asarray(flange, dtype=float)
    if table.ndim != 2 or table.shape[1] != 4 or table.shape[0] < 1:
        raise ValueError(f'a modified DH table has shape (L, 4) (a, d, alpha, offset), got {table.shape}')
    if fl.shape != (4,):
        raise ValueError(f'the flange row is [a, d, alpha, theta], got shape {fl.shape}')
    if not (np.all(np.isfinite(table)) and np.all(np.isfinite(fl))):
        raise ValueError(f'modified DH rows must be finite: {table.tolist()}, flange {fl.tolist()}')
    return table, fl


def _rx_tx(a: float, alpha: float) -> NDArray[np.float64]:
    """``Rx(alpha) Tx(a)``, shape (4, 4)."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[1.0, 0.0, 0.0, a], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _rz_tz(theta: float, d: float) -> NDArray[np.float64]:
    """``Rz(theta) Tz(d)``, shape (4, 4)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, d], [0.0, 0.0, 0.0, 1.0]])


def modified_to_standard(mdh: ArrayLike, flange: ArrayLike | None = None
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The standard table, base and tool transforms that move the hand exactly as ``mdh`` does.

    Parameters
    ----------
    mdh : array_like, shape (L, 4)
        Modified rows ``[a_{i-1}, d_i, alpha_{i-1}, offset_i]`` [m, m, rad, rad].
    flange : array_like, shape (4,), optional
        The fixed flange row ``[a, d, alpha, theta]`` after the last joint (zeros if omitted).

    Returns
    -------
    dh : ndarray, shape (L, 4)
        Standard rows ``[a_i, d_i, alpha_i, offset_i]``.
    pre : ndarray, shape (4, 4)
        ``Rx(alpha_0) Tx(a_0)``: goes before the chain (into the base).
    tool : ndarray, shape (4, 4)
        ``Rz(theta_F) Tz(d_F)``: the last standard frame to the flange.
    """
    table, fl = _rows(mdh, flange)
    dh = np.empty_like(table)
    dh[:, 1] = table[:, 1]
    dh[:, 3] = table[:, 3]
    nxt = np.vstack([table[1:], fl[None]])          # the next row's a, alpha; the flange's for the last
    dh[:, 0] = nxt[:, 0]
    dh[:, 2] = nxt[:, 2]
    return dh, _rx_tx(table[0, 0], table[0, 2]), _rz_tz(fl[3], fl[1])


def standard_to_modified(dh: ArrayLike, first: tuple[float, float], flange_d_theta: tuple[float, float] = (0.0, 0.0)
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The exact inverse of :func:`modified_to_standard`.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        Standard rows (e.g. an estimate).
    first : (float, float)
        The first modified row's ``(a_0, alpha_0)`` [m, rad] (in the base: not estimated).
    flange_d_theta : (float, float)
        The flange row's ``(d_F, theta_F)`` [m, rad] (in the tool: not estimated).

    Returns
    -------
    mdh : ndarray, shape (L, 4)
    flange : ndarray, shape (4,)
        ``[a_F, d_F, alpha_F, theta_F]``; ``a_F, alpha_F`` are the last standard row's.
    """
    table = np.asarray(dh, dtype=float)
    if table.ndim != 2 or table.shape[1] != 4:
        raise ValueError(f'a standard DH table has shape (L, 4), got {table.shape}')
    mdh = table.copy()
    mdh[0, 0], mdh[0, 2] = first
    mdh[1:, 0] = table[:-1, 0]
    mdh[1:, 2] = table[:-1, 2]
    flange = np.array([table[-1, 0], flange_d_theta[0], table[-1, 2], flange_d_theta[1]])
    return mdh, flange


def modified_forward_kinematics(mdh: ArrayLike, q: ArrayLike, flange: ArrayLike | None = None) -> NDArray[np.float64]:
    """The flange pose by Craig's product, link by link (a reference for tests), shape (4, 4).

    Parameters
    ----------
    mdh : array_like, shape (L, 4)
    q : array_like, shape (L,)
    flange : array_like, shape (4,), optional
    """
    table, fl = _rows(mdh, flange)
    q = np.asarray(q, dtype=float)
    if q.shape != (table.shape[0],):
        raise ValueError(f'q must have shape ({table.shape[0]},), got {q.shape}')
    pose = np.eye(4)
    for (a, d, alpha, offset), qi in zip(table, q):
        pose = pose @ _rx_tx(a, alpha) @ _rz_tz(qi + offset, d)
    return pose @ _rx_tx(fl[0], fl[2]) @ _rz_tz(fl[3], fl[1])
