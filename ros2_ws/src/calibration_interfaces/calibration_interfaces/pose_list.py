"""The pose list: joint configurations to visit, written by a plan or by hand (no rclpy).

A reviewed plan (``python -m calibration_bringup.plan``) or a list of poses taught on the robot,
which the selector visits first (``poses_file``, ``run_calibration.sh --poses FILE``), each
checked against the collision margins, before its strategy takes over::

    robot: ur5e
    angle_unit: deg                  # of the positions; 'rad' if absent
    joint_names: [shoulder_pan_joint, shoulder_lift_joint, elbow_joint, wrist_1_joint, wrist_2_joint, wrist_3_joint]
    poses:
      - [10.0, -80.0, 95.0, -190.0, -90.0, 30.0]
      - ...

Other top-level keys (how it was planned, the clearance of each pose) are kept but not read.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from body_schema.robot import ArmModel

__all__ = ['PoseListError', 'PoseList', 'parse_pose_list', 'read_pose_list', 'write_pose_list']


class PoseListError(ValueError):
    """A pose list is missing, not YAML, or a field is wrong; the message names the file and field."""


@dataclass(frozen=True)
class PoseList:
    """Poses in the robot description's joint order.

    Attributes
    ----------
    positions : ndarray, shape (K, L)
        Joint positions [rad].
    extra : dict
        The file's other top-level entries.
    """

    positions: NDArray[np.float64]
    extra: dict[str, Any] = field(default_factory=dict)


def parse_pose_list(doc: Any, model: ArmModel, where: str = '<dict>') -> PoseList:
    """The poses of a parsed pose list, reordered to ``model``'s joints.

    Raises
    ------
    PoseListError
        If ``joint_names`` is not a permutation of the model's joints, ``angle_unit`` is unknown,
        ``poses`` is empty or malformed, or a pose lies outside the joint limits.
    """
    if not isinstance(doc, Mapping):
        raise PoseListError(f'{where}: expected a mapping with joint_names and poses')
    unit = doc.get('angle_unit', 'rad')
    if unit not in ('deg', 'rad'):
        raise PoseListError(f"{where}: angle_unit: must be 'deg' or 'rad', got {unit!r}")
    names = doc.get('joint_names', list(model.joint_names))
    if not isinstance(names, list) or sorted(map(str, names)) != sorted(model.joint_names):
        raise PoseListError(f'{where}: joint_names: must name each of {list(model.joint_names)} once, got {names!r}')
    poses = doc.get('poses')
    if not isinstance(poses, list) or not poses:
        raise PoseListError(f'{where}: poses: must be a non-empty list of joint positions')
    try:
        q = np.array(poses, dtype=float)
    except (TypeError, ValueError):
        raise PoseListError(f'{where}: poses: every pose must be {len(names)} numbers') from None
    if q.ndim != 2 or q.shape[1] != len(names):
        raise PoseListError(f'{where}: poses: every pose must be {len(names)} numbers, got shape {q.shape}')
    if not np.all(np.isfinite(q)):
        raise PoseListError(f'{where}: poses[{int(np.nonzero(~np.all(np.isfinite(q), axis=1))[0][0])}]: NaN or inf')
    if unit == 'deg':
        q = np.radians(q)
    order = [list(map(str, names)).index(j) for j in model.joint_names]
    q = q[:, order]
    outside = np.nonzero(~model.within_limits(q))[0]
    if outside.size:
        i = int(outside[0])
        raise PoseListError(f'{where}: poses[{i}]: outside the joint limits of {model.name}: '
                            f'{np.degrees(q[i]).round(2).tolist()} deg')
    extra = {k: v for k, v in doc.items() if k not in ('angle_unit', 'joint_names', 'poses')}
    return PoseList(q, extra)


def read_pose_list(path: str | Path, model: ArmModel) -> PoseList:
    """Read a pose list for ``model`` (see :func:`parse_pose_list`).

    Raises
    ------
    PoseListError
        If the file does not exist, is not YAML or is malformed; the message names the file.
    """
    p = Path(path)
    if not p.is_file():
        raise PoseListError(f'pose list {str(path)!r} does not exist')
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise PoseListError(f'{p}: not valid YAML: {" ".join(str(exc).split())}') from exc
    return parse_pose_list(doc, model, str(p))


def write_pose_list(path: str | Path, model: ArmModel, positions: ArrayLike,
                    extra: Mapping[str, Any] | None = None, comment: str = '') -> Path:
    """Write poses (K, L) [rad] in degrees, in the model's joint order; ``extra`` entries after them.

    ``comment`` (lines) opens the file as YAML comments.
    """
    q = np.atleast_2d(np.asarray(positions, dtype=float))
    if q.shape[1] != model.n_joints:
        raise ValueError(f'positions must have shape (K, {model.n_joints}), got {q.shape}')
    doc = {'robot': model.name, 'angle_unit': 'deg', 'joint_names': list(model.joint_names),
           'poses': [[round(float(v), 6) for v in row] for row in np.degrees(q)], **(extra or {})}
    head = ''.join(f'# {line}\n' if line else '#\n' for line in comment.splitlines())
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    return p



