"""The DH table file: one YAML format, written by the estimator's export, read by the estimator
(``initial_guess: file``), the simulator (``true_dh_file``) and the offline evaluation (no rclpy).

The format is the ``joints`` section of a robot description, so a robot description is a valid
DH file too::

    robot: icub_right_arm
    angle_unit: deg                 # of alpha and offset; 'rad' if absent (as in descriptions)
    joints:
      - {name: r_shoulder_pitch, dh: [a, d, alpha, offset], sigma: [a, d, alpha, offset]}
      ...

``a`` and ``d`` are in metres; ``sigma`` (one standard deviation, optional) uses the same units.
Other top-level keys (``updates``, a description's ``H0`` ...) are ignored, and so is
``convention`` unless it is ``modified``: a description's Craig table (with its ``flange`` row) is
read as the standard table the loader regroups it into (:mod:`body_schema.modified_dh`), and a
description with a ``urdf:`` key and no ``joints`` as the table derived from its URDF. The
export of a modified description adds a ``modified_dh`` section (the estimate in that convention,
:func:`modified_section`); readers keep reading ``joints``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

__all__ = ['DhFileError', 'DhTable', 'read_dh_file', 'write_dh_file', 'modified_section', 'CONVENTION',
           'MODIFIED_CONVENTION']

CONVENTION = 'standard DH: H = Rz(q + offset) Tz(d) Tx(a) Rx(alpha); a, d in m'
#: What a ``modified_dh`` section says of its rows.
MODIFIED_CONVENTION = ('modified DH (Craig): T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(q_i + offset_i) Tz(d_i); rows '
                       '[a_{i-1}, d_i, alpha_{i-1}, offset_i]; flange [a, d, alpha, theta] after the last joint')


class DhFileError(ValueError):
    """A DH file is missing, not YAML, or its table has the wrong shape or unit."""


@dataclass(frozen=True)
class DhTable:
    """A DH table read from a file, in SI units.

    Attributes
    ----------
    dh : ndarray, shape (L, 4)
        ``a [m], d [m], alpha [rad], offset [rad]`` per joint.
    names : tuple of str
        Joint names (empty strings where the file has none).
    sigma : ndarray, shape (L, 4), or None
        One standard deviation per parameter in the same units, when the file has it.
    robot : str
        The ``robot`` (or a description's ``name``) entry; empty if absent.
    """

    dh: NDArray[np.float64]
    names: tuple[str, ...]
    sigma: NDArray[np.float64] | None = None
    robot: str = ''


def _rows(joints: Sequence[Mapping[str, Any]], key: str, where: str, scale: float) -> NDArray[np.float64]:
    try:
        table = np.array([j[key] for j in joints], dtype=float)
    except KeyError:
        raise DhFileError(f'{where}: every joint needs {key!r}') from None
    except (TypeError, ValueError) as exc:
        raise DhFileError(f'{where}: {key} is not a numeric table: {exc}') from exc
    if table.ndim != 2 or table.shape[1] != 4:
        raise DhFileError(f'{where}: {key} rows must be [a, d, alpha, offset], got shape {table.shape}')
    if not np.all(np.isfinite(table)):
        raise DhFileError(f'{where}: {key} contains NaN or inf')
    table[:, 2:] *= scale
    return table


def parse_dh(doc: Any, where: str = '<dict>', n_joints: int | None = None) -> DhTable:
    """The DH table of a parsed DH file (see the module docstring).

    ``where`` is the file's path for a description read from a URDF (its ``urdf.file`` may be
    relative to it).

    Raises
    ------
    DhFileError
        If ``joints`` is missing, a row is malformed, ``angle_unit`` is unknown, or the table
        does not have ``n_joints`` rows.
    """
    if isinstance(doc, Mapping) and 'urdf' in doc and 'joints' not in doc:
        from body_schema.robot import RobotDescriptionError, robot_from_dict

        try:
            model = robot_from_dict(dict(doc), source=where)
        except RobotDescriptionError as exc:
            raise DhFileError(f'{where}: {exc}') from exc
        if n_joints is not None and model.n_joints != n_joints:
            raise DhFileError(f'{where}: expected {n_joints} joints, got {model.n_joints}')
        return DhTable(model.dh, model.joint_names, None, model.name)
    if not isinstance(doc, Mapping) or not isinstance(doc.get('joints'), list) or not doc['joints']:
        raise DhFileError(f'{where}: expected a mapping with a non-empty "joints" list')
    unit = doc.get('angle_unit', 'rad')
    if unit not in ('deg', 'rad'):
        raise DhFileError(f"{where}: angle_unit must be 'deg' or 'rad', got {unit!r}")
    scale = np.pi / 180.0 if unit == 'deg' else 1.0
    joints = doc['joints']
    if not all(isinstance(j, Mapping) for j in joints):
        raise DhFileError(f'{where}: every entry of "joints" must be a mapping with "dh"')
    dh = _rows(joints, 'dh', where, scale)
    if n_joints is not None and dh.shape[0] != n_joints:
        raise DhFileError(f'{where}: expected {n_joints} joints, got {dh.shape[0]}')
    sigma = _rows(joints, 'sigma', where, scale) if all('sigma' in j for j in joints) else None
    if doc.get('convention') == 'modified':
        from body_schema.modified_dh import modified_to_standard

        flange = np.zeros(4)
        if 'flange' in doc:
            flange = _rows([{'flange': doc['flange']}], 'flange', where, scale)[0]
        dh = modified_to_standard(dh, flange)[0]
        sigma = None if sigma is None else _modified_to_standard_sigma(sigma)
    return DhTable(dh, tuple(str(j.get('name', '')) for j in joints), sigma,
                   str(doc.get('robot', doc.get('name', ''))))


def read_dh_file(path: str | Path, n_joints: int | None = None) -> DhTable:
    """Read a DH file (an export or a robot description).

    Parameters
    ----------
    path : str or Path
    n_joints : int, optional
        Required number of rows.

    Raises
    ------
    DhFileError
        If the file does not exist, is not YAML, or its table is malformed; the message names
        the file and the problem.
    """
    p = Path(path)
    if not p.is_file():
        raise DhFileError(f'DH file {str(path)!r} does not exist')
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise DhFileError(f'{p}: not valid YAML: {exc}') from exc
    return parse_dh(doc, str(p), n_joints)


def _modified_to_standard_sigma(sigma: NDArray[np.float64]) -> NDArray[np.float64]:
    """A modified table's one-sigma rows as the standard rows' (a, alpha from the next row; the
    flange's, not estimated, as 0)."""
    out = sigma.copy()
    out[:-1, [0, 2]] = sigma[1:, [0, 2]]
    out[-1, [0, 2]] = 0.0
    return out


def modified_section(mdh: ArrayLike, flange: ArrayLike, names: Sequence[str],
                     sigma: ArrayLike | None = None) -> dict[str, Any]:
    """The ``modified_dh`` entry of an export: a table in Craig's convention (angles in degrees).

    Parameters
    ----------
    mdh : array_like, shape (L, 4)
        ``[a_{i-1}, d_i, alpha_{i-1}, offset_i]`` [m, m, rad, rad].
    flange : array_like, shape (4,)
        ``[a, d, alpha, theta]``.
    names : sequence of str, length L
    sigma : array_like, shape (L, 4), optional
        The *standard* table's one-sigma rows; they are moved to the modified rows (a, alpha of
        standard row ``i`` are modified row ``i + 1``'s, the last the flange's; the first row's
        and the flange's d, theta are not estimated: 0).
    """
    mdh = np.asarray(mdh, dtype=float)
    fl = np.asarray(flange, dtype=float)

    def deg(row: NDArray[np.float64]) -> list[float]:
        return [float(row[0]), float(row[1]), float(np.degrees(row[2])), float(np.degrees(row[3]))]

    joints: list[dict[str, Any]] = [{'name': str(n), 'dh': deg(r)} for n, r in zip(names, mdh)]
    out: dict[str, Any] = {'convention': 'modified', 'note': MODIFIED_CONVENTION, 'angle_unit': 'deg',
                           'joints': joints, 'flange': deg(fl)}
    if sigma is not None:
        s = np.asarray(sigma, dtype=float).reshape(mdh.shape)
        ms = s.copy()
        ms[0, [0, 2]] = 0.0
        ms[1:, [0, 2]] = s[:-1, [0, 2]]
        for j, row in zip(joints, ms):
            j['sigma'] = deg(row)
        out['flange_sigma'] = deg(np.array([s[-1, 0], 0.0, s[-1, 2], 0.0]))
    return out


def write_dh_file(path: str | Path, dh: ArrayLike, names: Sequence[str], robot: str,
                  sigma: ArrayLike | None = None, extra: Mapping[str, Any] | None = None) -> Path:
    """Write a DH table (angles in degrees) that :func:`read_dh_file` reads back.

    Parameters
    ----------
    path : str or Path
    dh : array_like, shape (L, 4)
        ``a [m], d [m], alpha [rad], offset [rad]``.
    names : sequence of str, length L
    robot : str
    sigma : array_like, shape (L, 4), optional
        One standard deviation per parameter, same units as ``dh``.
    extra : mapping, optional
        Further top-level entries (e.g. the estimator's counters), written after ``joints``.
    """
    dh = np.asarray(dh, dtype=float).reshape(-1, 4)
    if len(names) != dh.shape[0]:
        raise ValueError(f'{len(names)} joint names for a table of {dh.shape[0]} rows')
    sig = None if sigma is None else np.asarray(sigma, dtype=float).reshape(dh.shape)

    def deg(row: NDArray[np.float64]) -> list[float]:
        return [float(row[0]), float(row[1]), float(np.degrees(row[2])), float(np.degrees(row[3]))]

    joints = []
    for i, name in enumerate(names):
        entry: dict[str, Any] = {'name': str(name), 'dh': deg(dh[i])}
        if sig is not None:
            entry['sigma'] = deg(sig[i])
        joints.append(entry)
    doc = {'robot': robot, 'convention': CONVENTION, 'angle_unit': 'deg', 'joints': joints, **(extra or {})}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p
