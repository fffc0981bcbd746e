"""Conversions between DH tables / covariances and std_msgs/Float64MultiArray (the contract's
``/body_schema/estimate``, ``/body_schema/covariance`` and ``/body_schema/true`` encoding).

Estimate and true tables: 7 x 4, rows joints, columns ``a [m], d [m], alpha [rad], offset [rad]``,
row-major, layout dims labelled ``joints`` and ``params``. Covariance: 28 x 28 in the same
parameter order, dims ``params_row`` and ``params_col``.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

__all__ = ['table_to_msg', 'msg_to_table', 'covariance_to_msg', 'msg_to_covariance', 'MessageFormatError']


class MessageFormatError(ValueError):
    """A Float64MultiArray does not have the contract's layout."""


def _matrix_msg(m: NDArray[np.float64], labels: tuple[str, str]) -> Float64MultiArray:
    rows, cols = m.shape
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=labels[0], size=rows, stride=rows * cols),
                      MultiArrayDimension(label=labels[1], size=cols, stride=cols)]
    msg.data = np.ascontiguousarray(m, dtype=float).ravel().tolist()
    return msg


def _msg_matrix(msg: Float64MultiArray, shape: tuple[int, int], what: str) -> NDArray[np.float64]:
    data = np.asarray(msg.data, dtype=float)
    dims = tuple(d.size for d in msg.layout.dim)
    if data.size != shape[0] * shape[1] or (dims and dims != shape):
        raise MessageFormatError(f'{what}: expected {shape[0]}x{shape[1]} values, got {data.size} '
                                 f'with layout {dims}')
    if not np.all(np.isfinite(data)):
        raise MessageFormatError(f'{what}: contains NaN or inf')
    return data.reshape(shape)


def table_to_msg(dh: ArrayLike) -> Float64MultiArray:
    """A (L, 4) DH table as a labelled Float64MultiArray."""
    return _matrix_msg(np.asarray(dh, dtype=float).reshape(-1, 4), ('joints', 'params'))


def msg_to_table(msg: Float64MultiArray, n_joints: int = 7) -> NDArray[np.float64]:
    """The (L, 4) DH table in a Float64MultiArray; raises MessageFormatError on a bad layout."""
    return _msg_matrix(msg, (n_joints, 4), 'DH table')


def covariance_to_msg(P: ArrayLike) -> Float64MultiArray:  # noqa: N803
    """An (n, n) covariance as a labelled Float64MultiArray (row-major)."""
    return _matrix_msg(np.asarray(P, dtype=float), ('params_row', 'params_col'))


def msg_to_covariance(msg: Float64MultiArray, n_params: int = 28) -> NDArray[np.float64]:
    """The (n, n) covariance in a Float64MultiArray."""
    return _msg_matrix(msg, (n_params, n_params), 'covariance')
