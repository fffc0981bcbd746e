"""The one encoding of the topic contract's arrays, poses and joints (every node package uses this).

DH tables and covariances <-> std_msgs/Float64MultiArray (``/body_schema/estimate``,
``/body_schema/covariance``, ``/body_schema/true``); geometry_msgs/Pose <-> 4x4 transforms;
builtin_interfaces/Time -> seconds.

Estimate and true tables: 7 x 4, rows joints, columns ``a [m], d [m], alpha [rad], offset [rad]``,
row-major, layout dims labelled ``joints`` and ``params``. Covariance: 28 x 28 in the same
parameter order, dims ``params_row`` and ``params_col``.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from geometry_msgs.msg import Pose
from scipy.spatial.transform import Rotation
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

__all__ = ['table_to_msg', 'msg_to_table', 'covariance_to_msg', 'msg_to_covariance', 'MessageFormatError',
           'pose_msg_to_matrix', 'matrix_to_pose_msg', 'stamp_to_seconds', 'joints_in_order',
           'extrinsics_to_msg', 'msg_to_extrinsics']


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


def extrinsics_to_msg(camera: ArrayLike, marker: ArrayLike) -> Float64MultiArray:
    """Camera and marker offsets (6,) each as a labelled 2 x 6 Float64MultiArray."""
    return _matrix_msg(np.stack([np.asarray(camera, dtype=float), np.asarray(marker, dtype=float)]),
                       ('camera_marker', 'xyz_rotvec'))


def msg_to_extrinsics(msg: Float64MultiArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The camera and marker offsets (6,) each of :func:`extrinsics_to_msg`."""
    m = _msg_matrix(msg, (2, 6), 'true extrinsics')
    return m[0].copy(), m[1].copy()


def pose_msg_to_matrix(pose: Pose) -> NDArray[np.float64]:
    """geometry_msgs/Pose -> (4, 4); raises ValueError on NaN or a zero quaternion."""
    p, q = pose.position, pose.orientation
    xyz = np.array([p.x, p.y, p.z], dtype=float)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
    norm = np.linalg.norm(quat)
    if not (np.all(np.isfinite(xyz)) and np.isfinite(norm) and norm > 1e-6):
        raise ValueError(f'pose: position {xyz.tolist()} / quaternion {quat.tolist()} is not valid')
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(quat / norm).as_matrix()
    t[:3, 3] = xyz
    return t


def matrix_to_pose_msg(t: ArrayLike) -> Pose:
    """(4, 4) -> geometry_msgs/Pose."""
    t = np.asarray(t, dtype=float)
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in t[:3, 3])
    x, y, z, w = Rotation.from_matrix(t[:3, :3]).as_quat()
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (
        float(x), float(y), float(z), float(w))
    return msg


def joints_in_order(names: Sequence[str], positions: Sequence[float],
                    order: Sequence[str]) -> NDArray[np.float64] | None:
    """Positions of the joints ``order`` from a named message (JointState, a trajectory point).

    Returns shape (len(order),), or None when a joint of ``order`` is missing or the message has
    a different number of names and positions.
    """
    names = list(names)
    if len(positions) != len(names) or any(n not in names for n in order):
        return None
    return np.array([positions[names.index(n)] for n in order], dtype=float)


def stamp_to_seconds(stamp: object) -> float:
    """builtin_interfaces/Time -> seconds."""
    return stamp.sec + 1e-9 * stamp.nanosec
