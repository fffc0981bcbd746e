"""Camera calibration files in camera_info_manager's YAML format (``ost.yaml``; pure, no rclpy).

``camera_calibration`` (the ROS calibration tool) writes them and camera drivers load them
through camera_info_manager's ``camera_info_url``::

    image_width: 640
    image_height: 480
    camera_name: narrow_stereo
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}
    projection_matrix: {rows: 3, cols: 4, data: [...]}

URLs as camera_info_manager takes them: ``file:///abs/path.yaml``, ``package://<pkg>/<path>``
(the package's share directory), ``${ROS_HOME}`` expanded (default ``~/.ros``); a plain path is
accepted too. Only the fields the marker detector uses are required (size, camera matrix); the
distortion defaults to none, R to identity and P to ``[K | 0]``, as for a camera_info_manager
file without them.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

__all__ = ['CameraInfoFileError', 'CameraInfoFile', 'resolve_url', 'read_camera_info', 'write_camera_info',
           'camera_info_differences']


class CameraInfoFileError(ValueError):
    """A camera calibration file is missing, not YAML, or a field is missing or malformed (named)."""


@dataclass(frozen=True)
class CameraInfoFile:
    """A camera calibration as camera_info_manager stores it.

    Attributes
    ----------
    width, height : int
        Image size [px].
    k : ndarray, shape (3, 3)
        Camera matrix.
    d : ndarray, shape (N,)
        Distortion coefficients (N = 0 without distortion).
    distortion_model : str
        ``plumb_bob``, ``rational_polynomial``, ``equidistant``, ...
    r : ndarray, shape (3, 3)
        Rectification matrix.
    p : ndarray, shape (3, 4)
        Projection matrix.
    camera_name : str
    source : str
        The file it was read from ('' if built in memory).
    """

    width: int
    height: int
    k: NDArray[np.float64]
    d: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = 'plumb_bob'
    r: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    p: NDArray[np.float64] | None = None
    camera_name: str = ''
    source: str = ''

    def __post_init__(self) -> None:
        if self.p is None:
            object.__setattr__(self, 'p', np.hstack([np.asarray(self.k, float), np.zeros((3, 1))]))


def resolve_url(url: str) -> Path:
    """The file a ``camera_info_url`` names.

    Raises
    ------
    CameraInfoFileError
        Empty URL, a scheme other than ``file://`` / ``package://``, a ``${...}`` other than
        ``${ROS_HOME}`` (camera_info_manager's ``${NAME}`` needs the driver's camera name), or
        an unknown package.
    """
    text = str(url).strip()
    if not text:
        raise CameraInfoFileError('camera_info_url is empty')
    text = text.replace('${ROS_HOME}', os.environ.get('ROS_HOME', os.path.expanduser('~/.ros')))
    if '${' in text:
        raise CameraInfoFileError(f'camera_info_url {url!r}: only ${{ROS_HOME}} is expanded here; give the file itself')
    if text.startswith('file://'):
        return Path(text[len('file://'):]).expanduser()
    if text.startswith('package://'):
        package, _, rest = text[len('package://'):].partition('/')
        try:
            from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        except ImportError as exc:                              # pragma: no cover (ament_index ships with rclpy)
            raise CameraInfoFileError(f'camera_info_url {url!r}: package:// needs ament_index_python') from exc
        try:
            return Path(get_package_share_directory(package)) / rest
        except (PackageNotFoundError, ValueError, LookupError) as exc:
            raise CameraInfoFileError(f'camera_info_url {url!r}: package {package!r} not found') from exc
    if '://' in text:
        raise CameraInfoFileError(f'camera_info_url {url!r}: expected file://, package:// or a path')
    return Path(text).expanduser()


def _matrix(doc: dict[str, Any], key: str, shape: tuple[int, int] | None, where: str) -> NDArray[np.float64]:
    m = doc[key]
    if not isinstance(m, dict) or 'data' not in m:
        raise CameraInfoFileError(f'{where}: {key} must be a mapping with rows, cols and data, got {m!r}')
    try:
        data = np.asarray(m['data'], dtype=float).reshape(-1)
        rows, cols = int(m.get('rows', shape[0] if shape else 1)), int(m.get('cols', data.size))
    except (TypeError, ValueError) as exc:
        raise CameraInfoFileError(f'{where}: {key} is not numeric: {exc}') from exc
    if rows * cols != data.size:
        raise CameraInfoFileError(f'{where}: {key} says {rows} x {cols} but has {data.size} values')
    if shape is not None and (rows, cols) != shape:
        raise CameraInfoFileError(f'{where}: {key} must be {shape[0]} x {shape[1]}, got {rows} x {cols}')
    if not np.all(np.isfinite(data)):
        raise CameraInfoFileError(f'{where}: {key} contains NaN or inf')
    return data.reshape(rows, cols) if shape is not None else data


def read_camera_info(url: str) -> CameraInfoFile:
    """Read a camera_info_manager YAML file (``ost.yaml``).

    Parameters
    ----------
    url : str
        ``file://``, ``package://`` or a path (:func:`resolve_url`).

    Raises
    ------
    CameraInfoFileError
        The file is missing or not YAML; ``image_width``/``image_height`` are not positive
        integers; ``camera_matrix`` is missing, not 3 x 3, or has a non-positive focal length;
        a matrix's ``rows x cols`` does not match its data.
    """
    path = resolve_url(url)
    where = str(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise CameraInfoFileError(f'{where}: cannot read the camera calibration file: {exc.strerror or exc}') from exc
    except yaml.YAMLError as exc:
        raise CameraInfoFileError(f'{where}: not YAML: {exc}') from exc
    if not isinstance(doc, dict):
        raise CameraInfoFileError(f'{where}: expected a mapping (camera_info_manager format), got {type(doc).__name__}')
    missing = [k for k in ('image_width', 'image_height', 'camera_matrix') if k not in doc]
    if missing:
        raise CameraInfoFileError(f'{where}: missing {missing} (camera_info_manager format: image_width, image_height, '
                                  f'camera_matrix, distortion_model, distortion_coefficients, ...)')
    size = []
    for key in ('image_width', 'image_height'):
        v = doc[key]
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise CameraInfoFileError(f'{where}: {key} must be a positive integer, got {v!r}')
        size.append(v)
    k = _matrix(doc, 'camera_matrix', (3, 3), where)
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise CameraInfoFileError(f'{where}: camera_matrix focal lengths must be positive, got fx {k[0, 0]}, '
                                  f'fy {k[1, 1]}')
    d = _matrix(doc, 'distortion_coefficients', None, where) if doc.get('distortion_coefficients') else np.zeros(0)
    model = doc.get('distortion_model') or 'plumb_bob'
    if not isinstance(model, str):
        raise CameraInfoFileError(f'{where}: distortion_model must be a string, got {model!r}')
    r = _matrix(doc, 'rectification_matrix', (3, 3), where) if doc.get('rectification_matrix') else np.eye(3)
    p = _matrix(doc, 'projection_matrix', (3, 4), where) if doc.get('projection_matrix') else None
    return CameraInfoFile(size[0], size[1], k, d, model, r, p, str(doc.get('camera_name') or ''), where)


def write_camera_info(path: str | Path, info: CameraInfoFile) -> Path:
    """Write ``info`` as camera_info_manager's YAML (what ``camera_calibration`` saves); returns the path."""
    def block(m: Any) -> dict[str, Any]:
        a = np.atleast_2d(np.asarray(m, dtype=float))
        return {'rows': int(a.shape[0]), 'cols': int(a.shape[1]), 'data': [float(v) for v in a.reshape(-1)]}

    doc = {'image_width': int(info.width), 'image_height': int(info.height), 'camera_name': info.camera_name,
           'camera_matrix': block(info.k), 'distortion_model': info.distortion_model,
           'distortion_coefficients': block(np.asarray(info.d, float).reshape(1, -1)),
           'rectification_matrix': block(info.r), 'projection_matrix': block(info.p)}
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    return out


def camera_info_differences(info: CameraInfoFile, width: int, height: int, k: Sequence[float], d: Sequence[float],
                            distortion_model: str, rtol: float = 1e-6) -> list[str]:
    """What a ``sensor_msgs/CameraInfo`` (its fields) says differently from the file.

    Distortion vectors of different lengths are compared zero-padded (five zeros and none are
    the same camera); an empty distortion model on either side is not a difference.

    Returns
    -------
    list of str
        One phrase per differing field, e.g. ``"K: fx 257.34 vs 260.0"``; empty if they agree.
    """
    out = []
    if (int(width), int(height)) != (info.width, info.height):
        out.append(f'size: {info.width} x {info.height} in the file vs {width} x {height} on the topic')
    kk = np.asarray(k, dtype=float).reshape(-1)
    if kk.size != 9:
        out.append(f'K: {kk.size} values on the topic')
    else:
        names = {0: 'fx', 2: 'cx', 4: 'fy', 5: 'cy'}
        fk = info.k.reshape(-1)
        bad = [i for i in range(9) if not np.isclose(fk[i], kk[i], rtol=rtol, atol=1e-9)]
        if bad:
            out.append('K: ' + ', '.join(f'{names.get(i, f"k[{i}]")} {fk[i]:g} in the file vs {kk[i]:g}' for i in bad))
    fd, td = np.asarray(info.d, float).reshape(-1), np.asarray(d, float).reshape(-1)
    n = max(fd.size, td.size)
    fd, td = np.pad(fd, (0, n - fd.size)), np.pad(td, (0, n - td.size))
    if not np.allclose(fd, td, rtol=rtol, atol=1e-9):
        out.append(f'D: {np.round(fd, 6).tolist()} in the file vs {np.round(td, 6).tolist()}')
    if distortion_model and info.distortion_model and distortion_model != info.distortion_model:
        out.append(f'distortion model: {info.distortion_model!r} in the file vs {distortion_model!r}')
    return out
