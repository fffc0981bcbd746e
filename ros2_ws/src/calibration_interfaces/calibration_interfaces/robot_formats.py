"""A calibrated DH table in formats robot stacks read (no rclpy): UR's kinematics YAML, iKin's chain .ini.

The estimator's export writes the formats a description lists under ``exports:`` beside
``calibrated_dh.yaml`` (:meth:`dh_estimator.estimator.OnlineEstimator.export`).

``ur_kinematics`` -- the kinematics calibration YAML that ``ur_calibration`` writes and
``ur_description`` reads (its ``config/<model>/default_kinematics.yaml`` format)::

    kinematics:
      shoulder: {x, y, z, roll, pitch, yaw}
      upper_arm: ...
      forearm: ...
      wrist_1: ...
      wrist_2: ...
      wrist_3: ...
      hash: calib_...

``ur_description``'s xacro uses entry ``k`` as the ``<origin xyz rpy>`` of the ``k``-th arm joint
(``shoulder_pan_joint`` ... ``wrist_3_joint``, each revolute about its z), whose parent of the first
is ``base_link_inertia`` (oriented as the controller's ``base`` frame, the DH base). ``rpy`` is
URDF's fixed-axis convention, ``R = Rz(yaw) Ry(pitch) Rx(roll)``. With DH rows
``(a_i, d_i, alpha_i, offset_i)`` the origins are the DH chain regrouped, as ``ur_calibration`` does:
``base Rz(offset_0) Tz(d_0)``, then ``Tx(a_{k-1}) Rx(alpha_{k-1}) Rz(offset_k) Tz(d_k)``. What follows
the last joint (``Tx(a_5) Rx(alpha_5)``: zero on the nominal UR tables) has no place in the file
(the flange and ``tool0`` are fixed in the xacro); it is returned and written under
``body_schema.flange_residual`` (a key the xacro does not read) so that it is not lost silently.
The ``hash`` identifies the file; ``ur_robot_driver`` compares the one in the description with
the controller's own calibration and, as it will differ from this one, logs that they do not
match: the controller keeps moving by its own kinematics, the calibrated values are for the
description (TF, planning).

``ikin`` -- an iKin chain as ``iKinLimb::fromLinksProperties`` (robotology/icub-main,
``iKinFwd.cpp``) reads it from a YARP property file: ``numLinks``, ``H0`` (16 values, row-major)
and per link ``link_<i> (A a) (D d) (alpha deg) (offset deg) (min deg) (max deg)``, blocked links
with ``(blocked deg)``. The description's blocked torso links come first (blocked at 0, without
limits: iKin's defaults), then the calibrated joints with their limits.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from body_schema.robot import ArmModel
from body_schema.urdf import transform_to_xyz_rpy

__all__ = ['UR_LINKS', 'ur_kinematics', 'write_ur_kinematics', 'ikin_ini', 'write_ikin_ini', 'write_exports']

#: The entries of UR's kinematics YAML, joint by joint.
UR_LINKS = ('shoulder', 'upper_arm', 'forearm', 'wrist_1', 'wrist_2', 'wrist_3')


def _rz(t: float) -> NDArray[np.float64]:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _tz(d: float) -> NDArray[np.float64]:
    m = np.eye(4)
    m[2, 3] = d
    return m


def _tx_rx(a: float, alpha: float) -> NDArray[np.float64]:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[1, 0, 0, a], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _entry(t: NDArray[np.float64]) -> dict[str, float]:
    xyz, rpy = transform_to_xyz_rpy(t)
    return {k: float(v) for k, v in zip(('x', 'y', 'z', 'roll', 'pitch', 'yaw'), np.concatenate([xyz, rpy]))}


def ur_kinematics(model: ArmModel, dh: ArrayLike | None = None) -> tuple[dict[str, Any], NDArray[np.float64]]:
    """The ``kinematics`` document of a six-joint table, and what follows the last joint.

    Parameters
    ----------
    model : ArmModel
        Six joints; its ``base`` (root to the first joint's frame) goes into ``shoulder``.
    dh : array_like, shape (6, 4), optional
        The calibrated table (default: the model's).

    Returns
    -------
    doc : dict
        ``{'kinematics': {shoulder: {...}, ..., hash: str}}``.
    residual : ndarray, shape (4, 4)
        ``Tx(a_5) Rx(alpha_5)``: the flange's offset after the last joint, not in the format.

    Raises
    ------
    ValueError
        If the model does not have six joints.
    """
    table = np.asarray(model.dh if dh is None else dh, dtype=float).reshape(model.dh.shape)
    if table.shape[0] != len(UR_LINKS):
        raise ValueError(f'the UR kinematics format has {len(UR_LINKS)} joints; {model.name} has {table.shape[0]}')
    origins = [model.base @ _rz(table[0, 3]) @ _tz(table[0, 1])]
    for k in range(1, 6):
        origins.append(_tx_rx(table[k - 1, 0], table[k - 1, 2]) @ _rz(table[k, 3]) @ _tz(table[k, 1]))
    kin: dict[str, Any] = {name: _entry(t) for name, t in zip(UR_LINKS, origins)}
    digest = hashlib.sha256(np.round(table, 12).tobytes() + np.round(model.base, 12).tobytes()).hexdigest()
    kin['hash'] = f'calib_body_schema_{int(digest[:15], 16)}'
    return {'kinematics': kin}, _tx_rx(table[5, 0], table[5, 2])


def write_ur_kinematics(path: str | Path, model: ArmModel, dh: ArrayLike | None = None) -> Path:
    """Write :func:`ur_kinematics` as YAML (``ur_description``'s ``kinematics_parameters_file``)."""
    doc, residual = ur_kinematics(model, dh)
    doc['body_schema'] = {
        'robot': model.name, 'joints': list(model.joint_names),
        'flange_residual': _entry(residual),
        'note': 'flange_residual: Tx(a) Rx(alpha) of the last DH row, after wrist_3_joint; ur_description fixes '
                'the flange and tool0 on wrist_3_link, so it is not applied there (zero on a nominal table)'}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text('# Kinematics calibration for ur_description (kinematics_parameters_file), written by '
                 'body_schema\'s estimator\n' + yaml.safe_dump(doc, sort_keys=False))
    return p


def ikin_ini(model: ArmModel, dh: ArrayLike | None = None) -> str:
    """An iKin chain file: the blocked torso links, then the calibrated joints (see the module docstring)."""
    table = np.asarray(model.dh if dh is None else dh, dtype=float).reshape(model.dh.shape)
    lines = [f'# iKin chain of {model.name} (iKinLimb::fromLinksProperties), written by body_schema\'s estimator:',
             '# standard DH, A and D in m, alpha, offset, min, max and blocked in deg',
             f'numLinks {model.torso.shape[0] + table.shape[0]}',
             'H0 (' + ' '.join(repr(float(v)) for v in np.asarray(model.h0, dtype=float).ravel()) + ')']

    def link(i: int, row: NDArray[np.float64], extra: str) -> str:
        return (f'link_{i} (A {float(row[0])!r}) (D {float(row[1])!r}) (alpha {float(np.degrees(row[2]))!r}) '
                f'(offset {float(np.degrees(row[3]))!r}){extra}')

    for i, row in enumerate(model.torso):
        lines.append(link(i, row, ' (blocked 0.0)'))
    n0 = model.torso.shape[0]
    for k, (row, (lo, hi)) in enumerate(zip(table, model.limits)):
        lines.append(link(n0 + k, row, f' (min {float(np.degrees(lo))!r}) (max {float(np.degrees(hi))!r})'))
    return '\n'.join(lines) + '\n'


def write_ikin_ini(path: str | Path, model: ArmModel, dh: ArrayLike | None = None) -> Path:
    """Write :func:`ikin_ini`."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(ikin_ini(model, dh))
    return p


def write_exports(directory: str | Path, model: ArmModel, dh: ArrayLike, stem: str = 'calibrated') -> list[Path]:
    """Write every format of ``model.exports`` for ``dh``: ``<stem>_ur_kinematics.yaml``, ``<stem>_ikin.ini``."""
    directory = Path(directory)
    out = []
    for fmt in model.exports:
        if fmt == 'ur_kinematics':
            out.append(write_ur_kinematics(directory / f'{stem}_ur_kinematics.yaml', model, dh))
        elif fmt == 'ikin':
            out.append(write_ikin_ini(directory / f'{stem}_ikin.ini', model, dh))
        else:
            raise ValueError(f'unknown export format {fmt!r}')
    return out
