"""Robot descriptions: load, validate, and evaluate the arm (and the eyes that watch it).

A description is a YAML file (see ``robots/icub_right_arm.yaml``, ``robots/ur5e.yaml``).
:func:`load_robot` accepts a packaged name (``"icub_right_arm"``) or a path, validates every
field, and returns an :class:`ArmModel`.

The cameras that watch the arm are data too: an eye chain carried by a (still) head
(``eyes``: the iCub looking at its own hand) and/or cameras fixed in the root frame
(``fixed_cameras``: a camera on a tripod watching an industrial arm, eye-to-hand).
:meth:`ArmModel.camera_pose` returns the optical frame of either kind by name, so nodes never
ask which kind a robot has. Angles in the file are in the unit named by ``angle_unit`` (``deg`` or
``rad``); everything in memory is SI (metres, radians).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from . import kinematics

__all__ = [
    'RobotDescriptionError',
    'parse_noise_law',
    'CameraIntrinsics',
    'MarkerPlacement',
    'EyeChain',
    'SceneryBox',
    'Obstacle',
    'OBSTACLE_SHAPES',
    'CollisionSettings',
    'UrdfSource',
    'CONVENTIONS',
    'ArmModel',
    'load_robot',
    'robot_path',
]


class RobotDescriptionError(ValueError):
    """A robot description is malformed; the message names the offending field."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics without distortion (the iCub simulator's eye cameras)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> NDArray[np.float64]:  # noqa: N802 (the usual name)
        """Camera matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> 'CameraIntrinsics':
        """The same field of view at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(width, height, self.fx * sx, self.fy * sy,
                                (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)


@dataclass(frozen=True)
class MarkerPlacement:
    """One ArUco marker fixed to the hand.

    ``hand_T_marker`` is the marker frame (origin at the square's centre, z out of the printed
    face) in the hand frame, shape (4, 4).
    """

    name: str
    marker_id: int
    hand_T_marker: NDArray[np.float64]


@dataclass(frozen=True)
class EyeChain:
    """The iCubEye kinematic chain for both eyes; the head joints are held still."""

    base: NDArray[np.float64]                  # root -> frame before the neck, (4, 4)
    links: dict[str, NDArray[np.float64]]      # 'left' / 'right' -> (5, 4) DH table
    head_joints: tuple[str, ...]
    head_pose: NDArray[np.float64]             # (5,) radians

    def camera_pose(self, eye: str = 'left', head: ArrayLike | None = None) -> NDArray[np.float64]:
        """Optical frame of ``eye`` (z forward, x right, y down) in the root frame, (4, 4)."""
        if eye not in self.links:
            raise ValueError(f"unknown eye {eye!r}; expected one of {sorted(self.links)}")
        h = self.head_pose if head is None else np.asarray(head, dtype=float)
        if h.shape != (len(self.head_joints),) or not np.all(np.isfinite(h)):
            raise ValueError(f'head pose must be {len(self.head_joints)} finite angles, got {h!r}')
        return kinematics.forward_kinematics(self.base, self.links[eye], h)


@dataclass(frozen=True)
class SceneryBox:
    """A static box drawn around the arm for context (a torso, a pedestal), in the root frame.

    Attributes
    ----------
    size : tuple of 3 floats
        Full extents [m].
    xyz : tuple of 3 floats
        Centre in the root frame [m] (axis-aligned).
    rgba : tuple of 4 floats
    """

    size: tuple[float, float, float]
    xyz: tuple[float, float, float]
    rgba: tuple[float, float, float, float]


#: Shapes an obstacle may have, and the size each needs [m].
OBSTACLE_SHAPES = {'box': 'size [x, y, z] (full extents)', 'cylinder': 'radius and length (along its z)',
                   'sphere': 'radius'}


@dataclass(frozen=True)
class Obstacle:
    """A static body the arm must keep clear of (a table, a camera's stand, a keep-out zone).

    Attributes
    ----------
    name : str
        Unique among the obstacles and the arm's links (``allowed_pairs`` and reports name it).
    shape : {'box', 'cylinder', 'sphere'}
    size : tuple of float
        box: full extents ``(x, y, z)``; cylinder: ``(radius, length)`` along its z; sphere:
        ``(radius,)`` [m].
    pose : ndarray, shape (4, 4)
        The shape's centre and axes in the root frame.
    rgba : tuple of 4 floats
        How the simulator and the viewers draw it (alpha 0: checked, not drawn).
    """

    name: str
    shape: str
    size: tuple[float, ...]
    pose: NDArray[np.float64] = field(compare=False)
    rgba: tuple[float, float, float, float] = (0.75, 0.75, 0.72, 1.0)


@dataclass(frozen=True)
class CollisionSettings:
    """How close the arm may come to the obstacles and to itself (``collision:`` in the YAML).

    Attributes
    ----------
    margin : float
        Least distance [m] between the arm and a static body (obstacle, scenery, head) that a
        commanded configuration or straight joint-space path may come to: it covers how well the
        obstacles' poses are known and the arm's calibration error.
    self_margin : float or None
        The same between two of the arm's links (their relative placement depends only on the
        kinematics, known to millimetres); None: ``margin``.
    allowed_pairs : tuple of (str, str)
        Pairs never checked (link or obstacle names), beyond neighbouring links and the pairs the
        collision model finds touching in every configuration (a link mounted on a table).
    """

    margin: float = 0.05
    self_margin: float | None = None
    allowed_pairs: tuple[tuple[str, str], ...] = ()

    @property
    def link_margin(self) -> float:
        """The margin between two of the arm's links [m]."""
        return self.margin if self.self_margin is None else self.self_margin


@dataclass(frozen=True)
class UrdfSource:
    """Where a description's arm comes from when it is read from a URDF (``urdf:`` in the YAML).

    Attributes
    ----------
    path : Path
        The ``.urdf`` or ``.xacro`` file (absolute).
    base_link, tip_link : str
        The chain's first and last links; markers are placed on ``tip_link``.
    """

    path: Path
    base_link: str
    tip_link: str


#: DH conventions a description's ``joints:`` table may be written in (``convention:``).
CONVENTIONS = ('standard', 'modified')


@dataclass(frozen=True)
class ArmModel:
    """A serial arm described by a standard DH table.

    Attributes
    ----------
    name : str
    joint_names : tuple of str, length L
    dh : ndarray, shape (L, 4)
        ``(a, d, alpha, offset)`` per joint, metres and radians.
    base : ndarray, shape (4, 4)
        Root frame to the frame before the first calibrated joint (H0 times blocked links).
    limits : ndarray, shape (L, 2)
        Joint limits [rad].
    calibration_box : ndarray, shape (L, 2)
        The joint box searched during calibration [rad], inside ``limits``.
    eyes : EyeChain or None
        Cameras carried by a head (their pose depends on the head joints).
    fixed_cameras : dict of str to ndarray (4, 4)
        Cameras fixed in the root frame: name -> optical frame (z forward, x right, y down).
    camera : CameraIntrinsics or None
        Intrinsics shared by every camera.
    scenery : tuple of SceneryBox
        Static context the simulator draws (no effect on the kinematics); checked as obstacles
        too (named ``scenery_<i>``).
    obstacles : tuple of Obstacle
        Static bodies the arm must keep clear of (``obstacles:`` in the YAML): drawn by the
        simulator and the viewers, checked by :class:`body_schema.collision.CollisionModel`.
    collision : CollisionSettings
        Margin and allowed pairs of the collision check (``collision:`` in the YAML).
    h0 : ndarray, shape (4, 4)
        Root frame to the first (blocked) link's frame, as written in the file.
    torso : ndarray, shape (T, 4)
        The blocked links between ``h0`` and the first calibrated joint (held at 0), DH rows in SI;
        ``base = h0 @ torso at q = 0``. The iKin export writes them as blocked links.
    exports : tuple of str
        Robot-stack formats the estimator's export writes besides the DH file and the URDF
        (:data:`EXPORT_FORMATS`).
    noise_law : dict of str to float
        Coefficients of the pose-dependent observation-noise law fitted for this description's
        camera and marker (``noise_model:`` in the YAML; keys of
        :class:`body_schema.noise.PoseDependentNoise`); empty: the built-in defaults.
    noise_covariance : str
        How the estimator should turn this camera's errors into its posterior covariance
        (``noise_model: {covariance: ...}``, one of
        :data:`body_schema.map_estimator.COVARIANCES`), where the errors need another than the
        estimator's default (heavy tails and an active selector: ``sandwich_hc3``); empty: the
        estimator's default.
    noise_loss_scale : float
        Where the MAP estimator's robust loss should depart from the square, in this law's standard
        deviations (``noise_model: {loss_scale: ...}``), for errors whose typical size is smaller
        than the law, fitted to their variance, says (heavy tails: ``tools.fit_noise`` prints it);
        0: the estimator's default.
    tool : ndarray, shape (4, 4)
        The hand (the frame after the last DH link, which every estimate and Jacobian ends at) to
        the flange: the URDF's ``tip_link`` or a modified table's flange row; identity for a
        standard table. Not estimated; the markers, given on the flange in the YAML, are stored
        composed with it (``hand_T_marker = tool @ flange_T_marker``).
    convention : {'standard', 'modified'}
        How the description's table was written; ``dh`` is standard either way (a modified table
        regrouped exactly, :mod:`body_schema.modified_dh`), :meth:`modified_table` writes it back.
    mdh_first : tuple of 2 floats
        A modified table's first row ``(a_0, alpha_0)`` [m, rad], which went into ``base``.
    urdf : UrdfSource or None
        The URDF the joints and the nominal kinematics come from (``urdf:`` in the YAML).
    body_penalty : bool
        Whether the selection cost's ``a * arctan(b * p_x)`` term applies (``selection:
        {body_penalty: ...}`` in the YAML). It is the paper's penalty on hands behind the iCub's
        body, whose root x points backward; for a robot without such a body the sign of ``p_x``
        means nothing (a camera in front at +x makes it a reward for hands turned away from the
        camera). Default: on for a description with ``eyes`` (a body carrying its cameras), off
        for fixed cameras.
    visibility : tuple of 2 floats
        The geometric visibility prior's margin [fraction of the image width] and marker widths
        (:class:`body_schema.occlusion.VisibilityPrior` ``margin``, ``margin_marker_widths``;
        ``selection: {visibility_margin: ..., visibility_marker_widths: ...}`` in the YAML), the
        selector's values unless its parameters say otherwise. Default ``(0.06, 0.0)``: a fixed
        margin, as fitted to uniform configurations.
    """

    name: str
    joint_names: tuple[str, ...]
    dh: NDArray[np.float64]
    base: NDArray[np.float64]
    limits: NDArray[np.float64]
    calibration_box: NDArray[np.float64]
    root_frame: str = 'root_link'
    eyes: EyeChain | None = None
    camera: CameraIntrinsics | None = None
    marker_dictionary: str = 'DICT_4X4_50'
    marker_side_length: float = 0.03
    markers: tuple[MarkerPlacement, ...] = ()
    fixed_cameras: dict[str, NDArray[np.float64]] = field(default_factory=dict, compare=False)
    scenery: tuple[SceneryBox, ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    collision: CollisionSettings = CollisionSettings()
    h0: NDArray[np.float64] = field(default_factory=lambda: np.eye(4), compare=False, repr=False)
    torso: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)), compare=False, repr=False)
    exports: tuple[str, ...] = ()
    noise_law: dict[str, float] = field(default_factory=dict, compare=False)
    noise_covariance: str = ''
    noise_loss_scale: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)
    tool: NDArray[np.float64] = field(default_factory=lambda: np.eye(4), compare=False, repr=False)
    convention: str = 'standard'
    mdh_first: tuple[float, float] = (0.0, 0.0)
    urdf: UrdfSource | None = None
    body_penalty: bool = False
    visibility: tuple[float, float] = (0.06, 0.0)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_params(self) -> int:
        return self.dh.size

    def with_dh(self, dh: ArrayLike) -> 'ArmModel':
        """The same robot with another DH table, shape (L, 4) or (4 L,)."""
        table = np.array(dh, dtype=float).reshape(self.dh.shape)
        _check_finite('dh', table)
        return dataclasses.replace(self, dh=table)

    def forward_kinematics(self, q: ArrayLike) -> NDArray[np.float64]:
        """Hand pose(s) in the root frame: (4, 4) for q of shape (L,), (N, 4, 4) for (N, L)."""
        return kinematics.forward_kinematics(self.base, self.dh, q)

    def flange_pose(self, q: ArrayLike) -> NDArray[np.float64]:
        """Flange (URDF ``tip_link``) pose(s) in the root frame: ``forward_kinematics(q) @ tool``."""
        return self.forward_kinematics(q) @ self.tool

    def modified_table(self, dh: ArrayLike | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A standard table (default: this model's) written back as the description's modified one.

        Returns
        -------
        mdh : ndarray, shape (L, 4)
            ``[a_{i-1}, d_i, alpha_{i-1}, offset_i]`` per joint [m, m, rad, rad].
        flange : ndarray, shape (4,)
            ``[a, d, alpha, theta]`` of the fixed flange row.

        Raises
        ------
        RobotDescriptionError
            If the description is not written in the modified convention.
        """
        from .modified_dh import standard_to_modified

        if self.convention != 'modified':
            raise RobotDescriptionError(f'robot {self.name!r}: convention is {self.convention!r}, not modified')
        table = self.dh if dh is None else np.asarray(dh, dtype=float).reshape(self.dh.shape)
        theta = float(np.arctan2(self.tool[1, 0], self.tool[0, 0]))
        return standard_to_modified(table, self.mdh_first, (float(self.tool[2, 3]), theta))

    def jacobian_dh(self, q: ArrayLike) -> NDArray[np.float64]:
        """Pose Jacobian w.r.t. the DH parameters: (6, 4 L) or (N, 6, 4 L)."""
        return kinematics.pose_jacobian_dh(self.base, self.dh, q)

    def jacobian_joints(self, q: ArrayLike) -> NDArray[np.float64]:
        """Pose Jacobian w.r.t. the joints: (6, L) or (N, 6, L)."""
        return kinematics.pose_jacobian_joints(self.base, self.dh, q)

    @property
    def camera_names(self) -> tuple[str, ...]:
        """Every camera of the description: the fixed ones, then the eyes."""
        eyes = tuple(self.eyes.links) if self.eyes is not None else ()
        return tuple(self.fixed_cameras) + eyes

    def camera_pose(self, eye: str = 'left', head: ArrayLike | None = None) -> NDArray[np.float64]:
        """Optical frame of camera ``eye`` in the root frame, (4, 4).

        A fixed camera's pose is the description's (``head`` does not move it); an eye's follows
        the head joints ``head`` (default: the description's ``head_pose``).
        """
        if eye in self.fixed_cameras:
            return self.fixed_cameras[eye].copy()
        if self.eyes is None or eye not in self.eyes.links:
            raise RobotDescriptionError(f'robot {self.name!r} has no camera {eye!r}; '
                                        f'cameras: {list(self.camera_names)}')
        return self.eyes.camera_pose(eye, head)

    @property
    def link_names(self) -> tuple[str, ...]:
        """The arm's links that carry geometry, base to hand: ``<joint>_link`` per joint, then ``hand``
        (the URDF links of :func:`body_schema.urdf.dh_chain_urdf`)."""
        return link_names(self.joint_names)

    @property
    def obstacle_names(self) -> tuple[str, ...]:
        """Every static body the collision check knows: the obstacles, the scenery boxes
        (``scenery_<i>``) and, for a robot with a left eye, the ``head`` behind it."""
        return obstacle_names(self.obstacles, len(self.scenery), self.eyes is not None and 'left' in self.eyes.links)

    def within_limits(self, q: ArrayLike, tol: float = 1e-9) -> NDArray[np.bool_]:
        """Whether each configuration lies inside the joint limits."""
        q = np.asarray(q, dtype=float)
        return np.all((q >= self.limits[:, 0] - tol) & (q <= self.limits[:, 1] + tol), axis=-1)


#: Link name of the hand in every URDF this project builds (the frame after the last joint).
HAND_LINK = 'hand'

#: Robot-stack formats the estimator's export can write (``exports:`` in the YAML): the UR
#: driver's kinematics calibration YAML and an iKin chain ``.ini`` (calibration_interfaces.robot_formats).
EXPORT_FORMATS = ('ur_kinematics', 'ikin')


def link_names(joint_names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``<joint>_link`` per joint, then :data:`HAND_LINK`."""
    return tuple(f'{j}_link' for j in joint_names) + (HAND_LINK,)


def obstacle_names(obstacles: tuple[Obstacle, ...], n_scenery: int, head: bool) -> tuple[str, ...]:
    """Names of the static bodies: obstacles, ``scenery_<i>``, then ``head`` if the robot has eyes."""
    return tuple(o.name for o in obstacles) + tuple(f'scenery_{i}' for i in range(n_scenery)) \
        + (('head',) if head else ())


# --------------------------------------------------------------------------------------------
# Loading and validation


def robot_path(name: str) -> Path:
    """Path of a packaged robot description, e.g. ``robot_path("icub_right_arm")``."""
    path = Path(str(resources.files('body_schema') / 'robots' / f'{name}.yaml'))
    if not path.is_file():
        available = sorted(p.stem for p in path.parent.glob('*.yaml'))
        raise FileNotFoundError(f'no packaged robot {name!r}; available: {available}')
    return path


def load_robot(name_or_path: str | Path = 'icub_right_arm', *, propose_box: bool = True) -> ArmModel:
    """Load and validate a robot description.

    Parameters
    ----------
    name_or_path : str or Path
        A packaged robot name (``"icub_right_arm"``) or the path of a YAML description.
    propose_box : bool
        Without a ``calibration_box``, propose one (:func:`robot_from_dict`); False: the limits.

    Raises
    ------
    RobotDescriptionError
        If a field is missing or has the wrong shape, unit or range; the message names it.
    """
    p = Path(name_or_path)
    path = p if (p.suffix in ('.yaml', '.yml') or p.exists()) else robot_path(str(name_or_path))
    try:
        # libyaml's parser when PyYAML has it: the same data, ~9x faster (every node loads the
        # description at start, five times per experiment run).
        data = yaml.load(path.read_text(), Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))  # noqa: S506
    except yaml.YAMLError as exc:
        raise RobotDescriptionError(f'{path}: not valid YAML: {exc}') from exc
    if not isinstance(data, dict):
        raise RobotDescriptionError(f'{path}: top level must be a mapping')
    return robot_from_dict(data, source=str(path), propose_box=propose_box)


def _check_finite(name: str, arr: NDArray[np.float64]) -> None:
    if not np.all(np.isfinite(arr)):
        raise RobotDescriptionError(f'{name}: contains NaN or infinite values: {arr.tolist()}')


def _array(data: dict[str, Any], key: str, shape: tuple[int, ...], where: str) -> NDArray[np.float64]:
    if key not in data:
        raise RobotDescriptionError(f'{where}{key}: missing')
    try:
        arr = np.array(data[key], dtype=float)
    except (TypeError, ValueError) as exc:
        raise RobotDescriptionError(f'{where}{key}: not numeric: {data[key]!r}') from exc
    if arr.shape != shape:
        raise RobotDescriptionError(f'{where}{key}: expected shape {shape}, got {arr.shape}')
    _check_finite(where + key, arr)
    return arr


def _angles_to_rad(table: NDArray[np.float64], cols: list[int], scale: float) -> NDArray[np.float64]:
    out = table.copy()
    out[..., cols] *= scale
    return out


def _table(rows: Any, n_rows: int | None, where: str, scale: float) -> NDArray[np.float64]:
    """A DH table in the file's angle unit -> (n, 4) in radians."""
    try:
        arr = np.array(rows, dtype=float)
    except (TypeError, ValueError) as exc:
        raise RobotDescriptionError(f'{where}: not numeric: {rows!r}') from exc
    if arr.ndim != 2 or arr.shape[1] != 4 or (n_rows is not None and arr.shape[0] != n_rows):
        want = f'({n_rows if n_rows is not None else "n"}, 4)'
        raise RobotDescriptionError(f'{where}: expected a DH table of shape {want} '
                                    f'(a, d, alpha, offset), got {arr.shape}')
    _check_finite(where, arr)
    if np.any(np.abs(arr[:, :2]) > 2.0):
        raise RobotDescriptionError(f'{where}: link lengths a, d above 2 m are not plausible '
                                    f'(are they in mm?): {arr[:, :2].tolist()}')
    return _angles_to_rad(arr, [2, 3], scale)


def _homogeneous(m: NDArray[np.float64], where: str) -> None:
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or not np.isclose(np.linalg.det(r), 1.0, atol=1e-6):
        raise RobotDescriptionError(f'{where}: rotation part is not a proper rotation matrix')
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise RobotDescriptionError(f'{where}: last row must be [0, 0, 0, 1]')


def _fixed_chain(h0: NDArray[np.float64], blocked: NDArray[np.float64]) -> NDArray[np.float64]:
    return kinematics.forward_kinematics(h0, blocked, np.zeros(blocked.shape[0]))


def robot_from_dict(data: dict[str, Any], source: str = '<dict>', *, propose_box: bool = True) -> ArmModel:
    """Validate a parsed description (see :func:`load_robot`) and build the model.

    Without a ``calibration_box`` the box is proposed from the cameras, markers, limits and
    obstacles (:func:`body_schema.box_proposal.proposed_box`: cached, a warning says what to paste);
    where it cannot be (no camera or markers, ``propose_box=False``, or nothing faces a camera:
    warned) the box is the joint limits.
    """
    where = f'{source}: '
    unit = data.get('angle_unit', 'rad')
    if unit not in ('deg', 'rad'):
        raise RobotDescriptionError(f"{where}angle_unit: must be 'deg' or 'rad', got {unit!r}")
    scale = np.pi / 180.0 if unit == 'deg' else 1.0

    convention = data.get('convention', 'standard')
    if convention not in CONVENTIONS:
        raise RobotDescriptionError(f'{where}convention: must be one of {list(CONVENTIONS)}, got {convention!r}')
    arm = _urdf_arm(data, where, source) if 'urdf' in data else _table_arm(data, where, scale, convention)
    names, dh, limits, h0, torso, tool = arm['names'], arm['dh'], arm['limits'], arm['h0'], arm['torso'], arm['tool']
    n = len(names)
    if len(set(names)) != len(names):
        raise RobotDescriptionError(f'{where}joints: duplicate joint names {names}')
    bad = np.nonzero(limits[:, 0] >= limits[:, 1])[0]
    if bad.size:
        raise RobotDescriptionError(f'{where}joints[{bad[0]}] ({names[bad[0]]}).limits: '
                                    f'min must be below max, got {np.degrees(limits[bad[0]]).tolist()} deg')
    if np.any(np.abs(limits) > 2 * np.pi + 1e-9):
        raise RobotDescriptionError(f'{where}joints[*].limits: beyond +-360 deg; check angle_unit')

    box = _array(data, 'calibration_box', (n, 2), where) * scale if 'calibration_box' in data \
        else limits.copy()
    outside = np.nonzero((box[:, 0] < limits[:, 0] - 1e-9) | (box[:, 1] > limits[:, 1] + 1e-9)
                         | (box[:, 0] >= box[:, 1]))[0]
    if outside.size:
        i = outside[0]
        raise RobotDescriptionError(f'{where}calibration_box[{i}] ({names[i]}): must be a non-empty '
                                    f'interval inside the joint limits')

    eyes = _eyes(data['eyes'], h0, where + 'eyes.', scale) if 'eyes' in data else None
    fixed = _fixed_cameras(data['fixed_cameras'], where + 'fixed_cameras', scale) \
        if 'fixed_cameras' in data else {}
    if eyes is not None and set(fixed) & set(eyes.links):
        raise RobotDescriptionError(f'{where}fixed_cameras: names {sorted(set(fixed) & set(eyes.links))} '
                                    f'are eyes already')
    scenery = _scenery(data['scenery'], where + 'scenery') if 'scenery' in data else ()
    camera = None
    if 'camera' in data:
        c = data['camera']
        try:
            camera = CameraIntrinsics(int(c['width']), int(c['height']), float(c['fx']),
                                      float(c['fy']), float(c['cx']), float(c['cy']))
        except (KeyError, TypeError, ValueError) as exc:
            raise RobotDescriptionError(f'{where}camera: needs width, height, fx, fy, cx, cy ({exc})') from exc
        if camera.width <= 0 or camera.height <= 0 or camera.fx <= 0 or camera.fy <= 0:
            raise RobotDescriptionError(f'{where}camera: sizes and focal lengths must be positive')

    dictionary, side, markers = 'DICT_4X4_50', 0.03, ()
    if 'hand_markers' in data:
        dictionary, side, markers = _markers(data['hand_markers'], where + 'hand_markers.', scale)
        # Given on the flange (the URDF's tip link, a modified table's flange row); kept on the hand.
        markers = tuple(dataclasses.replace(m, hand_T_marker=tool @ m.hand_T_marker) for m in markers)

    noise_law, noise_covariance, noise_loss_scale = (parse_noise_law(data['noise_model'], where + 'noise_model')
                                                     if 'noise_model' in data else ({}, '', 0.0))

    obstacles = _obstacles(data['obstacles'], where + 'obstacles', scale) if 'obstacles' in data else ()
    links = link_names(names)
    bodies = obstacle_names(obstacles, len(scenery), eyes is not None and 'left' in eyes.links)
    clash = sorted(set(links) & set(bodies))
    if clash:
        raise RobotDescriptionError(f'{where}obstacles: names {clash} are taken by the arm\'s links or the head')
    if len(set(bodies)) != len(bodies):
        raise RobotDescriptionError(f'{where}obstacles: duplicate names in {list(bodies)} '
                                    '(scenery boxes are named scenery_<i>, the eyes\' head "head")')
    collision = _collision(data['collision'], where + 'collision', links + bodies) \
        if 'collision' in data else CollisionSettings()
    exports = data.get('exports', []) or []
    if not isinstance(exports, list) or any(e not in EXPORT_FORMATS for e in exports):
        raise RobotDescriptionError(f'{where}exports: must be a list of {list(EXPORT_FORMATS)}, got {exports!r}')

    known = {'name', 'root_frame', 'angle_unit', 'H0', 'torso', 'joints', 'calibration_box',
             'eyes', 'camera', 'hand_markers', 'fixed_cameras', 'scenery', 'noise_model',
             'obstacles', 'collision', 'exports', 'urdf', 'convention', 'flange', 'selection'}
    body_penalty, visibility = _selection(data.get('selection', {}), where + 'selection', eyes is not None)
    model = ArmModel(
        name=str(data.get('name', Path(source).stem)),
        joint_names=tuple(names),
        dh=dh,
        base=_fixed_chain(h0, torso),
        limits=limits,
        calibration_box=box,
        root_frame=str(data.get('root_frame', arm['root'])),
        eyes=eyes,
        camera=camera,
        marker_dictionary=dictionary,
        marker_side_length=side,
        markers=markers,
        fixed_cameras=fixed,
        scenery=scenery,
        obstacles=obstacles,
        collision=collision,
        h0=h0,
        torso=torso,
        exports=tuple(str(e) for e in exports),
        noise_law=noise_law,
        noise_covariance=noise_covariance,
        noise_loss_scale=noise_loss_scale,
        extra={k: v for k, v in data.items() if k not in known},
        tool=tool,
        convention=convention,
        mdh_first=arm['first'],
        urdf=arm['urdf'],
        body_penalty=body_penalty,
        visibility=visibility,
    )
    if propose_box and 'calibration_box' not in data and camera is not None and markers:
        from .box_proposal import proposed_box     # here: scipy and the collision check only when proposing

        model = dataclasses.replace(model, calibration_box=proposed_box(model, source, unit))
    return model


def resolve_file(name: str, relative_to: Path, where: str = 'file') -> Path:
    """A file a description names: absolute, relative to the description, or ``package://PKG/REL``.

    ``package://`` looks in ``<prefix>/share/PKG`` for each prefix of ``AMENT_PREFIX_PATH`` (a ROS
    package, as ROS resolves it), then in the directory of an importable Python package ``PKG``
    (``package://pybullet_data/franka_panda/panda.urdf``).

    Raises
    ------
    RobotDescriptionError
        If a ``package://`` name's package is not found.
    """
    import os

    if name.startswith('package://'):
        pkg, _, rest = name[len('package://'):].partition('/')
        for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
            share = Path(prefix) / 'share' / pkg
            if share.is_dir():
                return (share / rest).resolve()
        import importlib.util

        spec = importlib.util.find_spec(pkg) if pkg.isidentifier() else None
        if spec is None or not spec.submodule_search_locations:
            raise RobotDescriptionError(f'{where}: no ROS package (AMENT_PREFIX_PATH) or Python package {pkg!r} '
                                        f'for {name!r}')
        return (Path(list(spec.submodule_search_locations)[0]) / rest).resolve()
    path = Path(name).expanduser()
    return (path if path.is_absolute() else relative_to / path).resolve()


def _table_arm(data: dict[str, Any], where: str, scale: float, convention: str) -> dict[str, Any]:
    """The arm of a description written as a table: ``H0``, ``torso``, ``joints`` (and ``flange``)."""
    h0 = _array(data, 'H0', (4, 4), where)
    _homogeneous(h0, where + 'H0')
    torso = _table(data.get('torso', []) or np.zeros((0, 4)), None, where + 'torso', scale)
    joints = data.get('joints')
    if not isinstance(joints, list) or not joints:
        raise RobotDescriptionError(f'{where}joints: must be a non-empty list')
    names, rows, lims = [], [], []
    for i, j in enumerate(joints):
        if not isinstance(j, dict) or 'name' not in j:
            raise RobotDescriptionError(f'{where}joints[{i}]: needs name, dh and limits')
        jw = f"{where}joints[{i}] ({j['name']}): "
        rows.append(_array(j, 'dh', (4,), jw))
        lims.append(_array(j, 'limits', (2,), jw))
        names.append(str(j['name']))
    dh = _table(rows, len(names), where + 'joints[*].dh', scale)
    tool, first = np.eye(4), (0.0, 0.0)
    if convention == 'modified':
        from .modified_dh import modified_to_standard

        if torso.shape[0]:
            raise RobotDescriptionError(f'{where}torso: not with convention: modified (put the fixed part in H0)')
        flange = np.zeros(4)
        if 'flange' in data:
            flange = _table([data['flange']], 1, where + 'flange', scale)[0]
        first = (float(dh[0, 0]), float(dh[0, 2]))
        dh, pre, tool = modified_to_standard(dh, flange)
        h0 = h0 @ pre                     # Rx(alpha_0) Tx(a_0) before the first joint
    elif 'flange' in data:
        raise RobotDescriptionError(f'{where}flange: only with convention: modified (a standard table ends at '
                                    'the flange)')
    return {'names': names, 'dh': dh, 'limits': np.array(lims) * scale, 'h0': h0, 'torso': torso, 'tool': tool,
            'first': first, 'urdf': None, 'root': 'root_link'}


def _urdf_arm(data: dict[str, Any], where: str, source: str) -> dict[str, Any]:
    """The arm of a description read from a URDF (``urdf: {file, base_link, tip_link}``)."""
    from .urdf_model import derive_dh, urdf_chain    # here: yourdfpy is loaded for URDF descriptions only

    u = data['urdf']
    if not isinstance(u, dict) or not all(isinstance(u.get(k), str) and u.get(k) for k in ('file', 'base_link', 'tip_link')):
        raise RobotDescriptionError(f'{where}urdf: must be a mapping with file, base_link and tip_link, got {u!r}')
    unknown = sorted(set(u) - {'file', 'base_link', 'tip_link'})
    if unknown:
        raise RobotDescriptionError(f'{where}urdf: unknown keys {unknown}; expected file, base_link, tip_link')
    clash = sorted(k for k in ('joints', 'torso', 'flange') if k in data)
    if clash or data.get('convention', 'standard') != 'standard':
        raise RobotDescriptionError(f'{where}urdf: the URDF gives the joints; remove {clash or ["convention"]}')
    path = resolve_file(u['file'], Path(source).parent if source != '<dict>' else Path.cwd(), where + 'urdf.file')
    chain = urdf_chain(path.resolve(), u['base_link'], u['tip_link'])
    derived = derive_dh(chain)
    h0 = np.eye(4)
    if 'H0' in data:                      # root frame -> base_link
        h0 = _array(data, 'H0', (4, 4), where)
        _homogeneous(h0, where + 'H0')
    return {'names': list(chain.joint_names), 'dh': derived.dh, 'limits': chain.limits, 'h0': h0 @ derived.base,
            'torso': np.zeros((0, 4)), 'tool': derived.tool, 'first': (0.0, 0.0),
            'urdf': UrdfSource(path.resolve(), u['base_link'], u['tip_link']), 'root': u['base_link']}


#: The keys a description's ``noise_model:`` block may set (units as in PoseDependentNoise).
NOISE_LAW_KEYS: tuple[str, ...] = ('a_pos', 'b_pos', 'floor_pos', 'a_rot', 'b_rot', 'floor_rot', 'depth_ratio',
                                   'stereo_pos', 'stereo_rot')


def parse_noise_law(n: Any, where: str) -> tuple[dict[str, float], str, float]:
    """A ``noise_model:`` block: the law's coefficients and what the estimator should do with its
    errors, the optional ``covariance`` and ``loss_scale`` (0 when absent).

    Raises
    ------
    RobotDescriptionError
        Naming ``where`` and the key, for a block that is not a mapping, an unknown key, a value
        that is not a number or out of its range (coefficients >= 0, ``depth_ratio``, ``stereo_pos``, ``stereo_rot`` > 0,
        ``loss_scale`` in [0.1, 100]), or an unknown ``covariance``.
    """
    from .map_estimator import COVARIANCES, LOSS_SCALE_RANGE     # here: map_estimator is a higher layer than robot

    settings = ['covariance', 'loss_scale']
    if not isinstance(n, dict):
        raise RobotDescriptionError(f'{where}: must be a mapping of {list(NOISE_LAW_KEYS)} (and {settings})')
    n = dict(n)
    covariance = n.pop('covariance', '')
    if covariance and covariance not in COVARIANCES:
        raise RobotDescriptionError(f'{where}.covariance: must be one of {list(COVARIANCES)}, got {covariance!r}')
    loss_scale = 0.0
    if 'loss_scale' in n:
        v = n.pop('loss_scale')
        try:
            loss_scale = float(v)
        except (TypeError, ValueError) as exc:
            raise RobotDescriptionError(f'{where}.loss_scale: must be a number, got {v!r}') from exc
        lo, hi = LOSS_SCALE_RANGE
        if not lo <= loss_scale <= hi:
            raise RobotDescriptionError(f'{where}.loss_scale: must be in [{lo:g}, {hi:g}] (standard deviations), '
                                        f'got {v!r}')
    unknown = sorted(set(n) - set(NOISE_LAW_KEYS))
    if unknown:
        raise RobotDescriptionError(f'{where}: unknown keys {unknown}; expected some of '
                                    f'{list(NOISE_LAW_KEYS) + settings}')
    law = {}
    for k, v in n.items():
        try:
            law[k] = float(v)
        except (TypeError, ValueError) as exc:
            raise RobotDescriptionError(f'{where}.{k}: must be a number, got {v!r}') from exc
        positive = k in ('depth_ratio', 'stereo_pos', 'stereo_rot')      # ratios; the rest may be 0
        if not np.isfinite(law[k]) or law[k] < 0 or (positive and law[k] == 0):
            raise RobotDescriptionError(f'{where}.{k}: must be finite and {"> 0" if positive else ">= 0"}, got {v!r}')
    return law, covariance, loss_scale


def _eyes(e: Any, h0: NDArray[np.float64], where: str, scale: float) -> EyeChain:
    if not isinstance(e, dict):
        raise RobotDescriptionError(f'{where[:-1]}: must be a mapping')
    heads = tuple(e.get('head_joints', ()))
    if not heads:
        raise RobotDescriptionError(f'{where}head_joints: missing')
    torso = _table(e.get('torso', []) or np.zeros((0, 4)), None, where + 'torso', scale)
    links = {eye: _table(e[eye], len(heads), where + eye, scale) for eye in ('left', 'right') if eye in e}
    if not links:
        raise RobotDescriptionError(f'{where}: needs a left and/or right eye chain')
    head = _array(e, 'head_pose', (len(heads),), where) * scale
    return EyeChain(base=_fixed_chain(h0, torso), links=links, head_joints=heads, head_pose=head)


def rpy_matrix(rpy: ArrayLike) -> NDArray[np.float64]:
    """Rotation of extrinsic x-y-z angles [rad] (URDF's rpy): ``Rz(yaw) Ry(pitch) Rx(roll)``, (3, 3).

    Written out rather than through scipy, whose import alone costs the launcher's validation of a
    description most of its time.
    """
    r, p_, y = np.asarray(rpy, dtype=float)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p_), np.sin(p_), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _pose(entry: Any, where: str, scale: float) -> NDArray[np.float64]:
    """``{xyz, rpy}`` (rpy: extrinsic x-y-z, the file's angle unit) -> (4, 4)."""
    if not isinstance(entry, dict):
        raise RobotDescriptionError(f'{where}: must be a mapping with xyz and rpy')
    t = np.eye(4)
    t[:3, :3] = rpy_matrix(_array(entry, 'rpy', (3,), where + '.') * scale)
    t[:3, 3] = _array(entry, 'xyz', (3,), where + '.')
    return t


def _fixed_cameras(c: Any, where: str, scale: float) -> dict[str, NDArray[np.float64]]:
    if not isinstance(c, list) or not c:
        raise RobotDescriptionError(f'{where}: must be a non-empty list of {{name, xyz, rpy}}')
    out: dict[str, NDArray[np.float64]] = {}
    for i, entry in enumerate(c):
        name = str(entry.get('name', '')) if isinstance(entry, dict) else ''
        if not name or name in out:
            raise RobotDescriptionError(f'{where}[{i}].name: must be a unique non-empty name, got {name!r}')
        out[name] = _pose(entry, f'{where}[{i}]', scale)
    return out


def _scenery(boxes: Any, where: str) -> tuple[SceneryBox, ...]:
    if not isinstance(boxes, list):
        raise RobotDescriptionError(f'{where}: must be a list of {{size, xyz, rgba}}')
    out = []
    for i, b in enumerate(boxes):
        w = f'{where}[{i}].'
        if not isinstance(b, dict):
            raise RobotDescriptionError(f'{w[:-1]}: must be a mapping with size, xyz, rgba')
        size, xyz, rgba = _array(b, 'size', (3,), w), _array(b, 'xyz', (3,), w), _array(b, 'rgba', (4,), w)
        if np.any(size <= 0) or np.any((rgba < 0) | (rgba > 1)):
            raise RobotDescriptionError(f'{w}: sizes must be > 0 and colours in [0, 1], got {b!r}')
        out.append(SceneryBox(tuple(size.tolist()), tuple(xyz.tolist()), tuple(rgba.tolist())))
    return tuple(out)


def _positive(entry: dict[str, Any], key: str, where: str) -> float:
    if key not in entry:
        raise RobotDescriptionError(f'{where}.{key}: missing')
    try:
        v = float(entry[key])
    except (TypeError, ValueError):
        raise RobotDescriptionError(f'{where}.{key}: must be a number, got {entry[key]!r}') from None
    if not (np.isfinite(v) and v > 0):
        raise RobotDescriptionError(f'{where}.{key}: must be a positive length [m], got {entry[key]!r}')
    return v


def _obstacles(items: Any, where: str, scale: float) -> tuple[Obstacle, ...]:
    """``obstacles:``: a list of {name, shape, size | radius (+ length), xyz, rpy, rgba}."""
    if not isinstance(items, list):
        raise RobotDescriptionError(f'{where}: must be a list of {{name, shape, size or radius/length, xyz, rpy}}')
    out: list[Obstacle] = []
    for i, o in enumerate(items):
        w = f'{where}[{i}]'
        if not isinstance(o, dict):
            raise RobotDescriptionError(f'{w}: must be a mapping with name, shape, xyz, rpy and a size')
        name = str(o.get('name', ''))
        if not name or any(c.isspace() for c in name):
            raise RobotDescriptionError(f'{w}.name: must be a non-empty name without spaces, got {name!r}')
        w = f'{where}[{i}] ({name})'
        shape = o.get('shape')
        if shape not in OBSTACLE_SHAPES:
            raise RobotDescriptionError(f'{w}.shape: must be one of {list(OBSTACLE_SHAPES)}, got {shape!r}')
        if shape == 'box':
            size = _array(o, 'size', (3,), w + '.')
            if np.any(size <= 0):
                raise RobotDescriptionError(f'{w}.size: extents must be > 0 m, got {size.tolist()}')
            dims = tuple(size.tolist())
        elif shape == 'cylinder':
            dims = (_positive(o, 'radius', w), _positive(o, 'length', w))
        else:
            dims = (_positive(o, 'radius', w),)
        pose = _pose({**{k: o[k] for k in ('xyz',) if k in o}, 'rpy': o.get('rpy', [0.0, 0.0, 0.0])}, w, scale)
        rgba = _array(o, 'rgba', (4,), w + '.') if 'rgba' in o else np.array(Obstacle.rgba)
        if np.any((rgba < 0) | (rgba > 1)):
            raise RobotDescriptionError(f'{w}.rgba: colours must be in [0, 1], got {rgba.tolist()}')
        out.append(Obstacle(name, str(shape), dims, pose, tuple(float(c) for c in rgba)))
    return tuple(out)


_SELECTION_KEYS = ('body_penalty', 'visibility_margin', 'visibility_marker_widths')


def _selection(sel: Any, where: str, has_eyes: bool) -> tuple[bool, tuple[float, float]]:
    """The ``selection:`` block -> (whether the body penalty applies, the visibility prior's
    (margin, marker widths)); each key optional."""
    if not isinstance(sel, dict) or not set(sel) <= set(_SELECTION_KEYS):
        raise RobotDescriptionError(f'{where}: must be a mapping with any of {list(_SELECTION_KEYS)}, got {sel!r}')
    penalty = sel.get('body_penalty', has_eyes)
    if not isinstance(penalty, bool):
        raise RobotDescriptionError(f'{where}.body_penalty: must be true or false, got {penalty!r}')
    visibility = []
    for key, default, low in (('visibility_margin', 0.06, -1.0), ('visibility_marker_widths', 0.0, 0.0)):
        value = sel.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= 10.0:
            raise RobotDescriptionError(f'{where}.{key}: must be a number in [{low:g}, 10], got {value!r}')
        visibility.append(float(value))
    return penalty, (visibility[0], visibility[1])


def _collision(c: Any, where: str, names: tuple[str, ...]) -> CollisionSettings:
    """``collision:``: margin [m] and allowed_pairs (pairs of link or obstacle names)."""
    if not isinstance(c, dict):
        raise RobotDescriptionError(f'{where}: must be a mapping with margin and/or allowed_pairs')
    unknown = sorted(set(c) - {'margin', 'self_margin', 'allowed_pairs'})
    if unknown:
        raise RobotDescriptionError(f'{where}: unknown keys {unknown}; expected margin, self_margin, allowed_pairs')
    margins: dict[str, float | None] = {'margin': CollisionSettings.margin, 'self_margin': None}
    for key in margins:
        if key not in c:
            continue
        try:
            v = float(c[key])
        except (TypeError, ValueError):
            raise RobotDescriptionError(f'{where}.{key}: must be a number [m], got {c[key]!r}') from None
        if not (np.isfinite(v) and 0 <= v <= 1.0):
            raise RobotDescriptionError(f'{where}.{key}: must be in [0, 1] m, got {c[key]!r}')
        margins[key] = v
    pairs = c.get('allowed_pairs', []) or []
    if not isinstance(pairs, list):
        raise RobotDescriptionError(f'{where}.allowed_pairs: must be a list of [name, name] pairs')
    out = []
    for i, pair in enumerate(pairs):
        if not (isinstance(pair, (list, tuple)) and len(pair) == 2):
            raise RobotDescriptionError(f'{where}.allowed_pairs[{i}]: must be a pair [name, name], got {pair!r}')
        bad = [str(n) for n in pair if str(n) not in names]
        if bad:
            raise RobotDescriptionError(f'{where}.allowed_pairs[{i}]: unknown names {bad}; links and obstacles '
                                        f'are {list(names)}')
        out.append((str(pair[0]), str(pair[1])))
    return CollisionSettings(float(margins['margin']), margins['self_margin'], tuple(out))


def _markers(m: Any, where: str, scale: float) -> tuple[str, float, tuple[MarkerPlacement, ...]]:
    if not isinstance(m, dict):
        raise RobotDescriptionError(f'{where[:-1]}: must be a mapping')
    side = float(m.get('side_length', 0.0))
    if not 0.0 < side < 0.5:
        raise RobotDescriptionError(f'{where}side_length: must be in (0, 0.5) m, got {side}')
    out, ids = [], set()
    for i, mk in enumerate(m.get('markers', [])):
        w = f'{where}markers[{i}].'
        xyz = _array(mk, 'xyz', (3,), w)
        rpy = _array(mk, 'rpy', (3,), w) * scale
        mid = int(mk.get('id', -1))
        if mid < 0 or mid in ids:
            raise RobotDescriptionError(f'{w}id: must be a unique non-negative integer, got {mid}')
        ids.add(mid)
        t = np.eye(4)
        t[:3, :3] = rpy_matrix(rpy)
        t[:3, 3] = xyz
        out.append(MarkerPlacement(str(mk.get('name', f'marker{mid}')), mid, t))
    if not out:
        raise RobotDescriptionError(f'{where}markers: at least one marker is needed')
    return str(m.get('dictionary', 'DICT_4X4_50')), side, tuple(out)

