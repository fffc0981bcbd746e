"""ArUco detection and hand-pose estimation (pure: numpy, OpenCV, scipy, body_schema; no rclpy).

Pipeline for one image of one eye (:meth:`HandPoseEstimator.process`):

1. :class:`MarkerDetector` finds the markers of the robot's dictionary with sub-pixel corner
   refinement; ids that are not on the hand are ignored.
2. :func:`solve_marker_pose` computes both IPPE_SQUARE solutions per marker and :func:`gate_marker`
   keeps a marker only if its best solution reprojects within ``max_reprojection_error_px`` and is
   not ambiguous: the planar flip ambiguity is declared when the alternative solution explains the
   corners almost as well (``alt_err < ambiguity_ratio * best_err + ambiguity_margin_px``) while
   being a genuinely different rotation (more than ``ambiguity_min_angle_deg`` away).
3. Each kept marker gives a hand pose ``root_T_cam @ cam_T_marker @ inv(hand_T_marker)`` and a
   covariance from the noise model at the marker's distance ``r`` and viewing angle ``phi``.
4. With several markers (or both eyes) the hand poses are fused (:data:`FUSION_MODES`).

Conventions: a marker frame has its origin at the black square's centre and z out of the printed
face; its object corners are OpenCV's ArUco order (top-left, top-right, bottom-right, bottom-left
of the printed image) ``(-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0)``.
Covariances are 6x6 over ``(x, y, z, rot_x, rot_y, rot_z)`` with the rotation part a rotation
vector in the output (root) frame, as in :mod:`body_schema.kinematics`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from body_schema.kinematics import rotation_angle_deg
from body_schema.markers import aruco_dictionary, marker_corners, refine_corners_edges
from body_schema.noise import NoiseModel, PoseDependentNoise, line_of_sight_covariance, stereo_covariance, view_geometry
from body_schema.robot import ArmModel, MarkerPlacement
from calibration_interfaces.outcome import FrameStatus
from calibration_interfaces.parameters import setting

__all__ = [
    'FUSION_MODES', 'BadInput', 'DetectorConfig', 'DetectedMarker', 'MarkerPose', 'HandEstimate',
    'FrameResult', 'MarkerDetector', 'solve_marker_pose', 'gate_marker',
    'hand_from_marker', 'fuse_estimates', 'refine_joint', 'StereoView', 'refine_stereo', 'HandPoseEstimator',
]

#: How several accepted markers (or eyes) are combined into one hand pose:
#: ``best``: the single marker with the smallest predicted variance (pose-dependent model);
#: ``weighted``: information-weighted mean of the per-marker hand poses;
#: ``joint``: one Levenberg-Marquardt PnP over the corners of all markers, hand frame as object.
FUSION_MODES = ('best', 'weighted', 'joint')


class BadInput(ValueError):
    """An input the detector cannot judge (an image or camera calibration it cannot use): not a
    scene without markers, so not evidence that the hand is hidden.

    Parameters
    ----------
    kind : str
        What was bad, ``<input>.<field>`` (e.g. ``image.encoding``, ``camera_info.D``): warnings
        are throttled per kind and the per-frame diagnostic carries it.
    reason : str
        Names the bad value.
    """

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(f'{kind}: {reason}')
        self.kind = kind
        self.reason = reason


@dataclass(frozen=True)
class DetectorConfig:
    """Detection and gating settings (defaults chosen by the accuracy study, see README).

    Attributes
    ----------
    max_reprojection_error_px : float
        Reject a marker whose best IPPE solution has a larger RMS corner reprojection error.
    ambiguity_ratio, ambiguity_margin_px : float
        The flip is ambiguous when ``alt_err < ambiguity_ratio * best_err + ambiguity_margin_px``.
    ambiguity_min_angle_deg : float
        ...and the two solutions differ by more than this rotation (near head-on they coincide and
        either is fine).
    refine_lm : bool
        Polish the chosen IPPE solution with Levenberg-Marquardt on the reprojection error.
    fusion : str
        One of :data:`FUSION_MODES`.
    min_side_px : float
        Ignore markers whose shortest side is below this (too few pixels for a pose).
    corner_refinement : bool
        Sub-pixel corner refinement (CORNER_REFINE_SUBPIX).
    edge_refinement : bool
        Then re-locate corners from fitted edge lines (:func:`body_schema.markers.refine_corners_edges`).
    """

    max_reprojection_error_px: float = setting(1.0, 'Reject a marker whose RMS corner reprojection error is '
                                               'larger [px]', (0.0, 100.0))
    ambiguity_ratio: float = setting(2.0, 'IPPE flip is ambiguous when alt_err < ratio * best_err + margin',
                                     (1.0, 100.0))
    ambiguity_margin_px: float = setting(0.1, 'Additive margin of the ambiguity test [px]', (0.0, 100.0))
    ambiguity_min_angle_deg: float = setting(8.0, 'Solutions closer than this are not ambiguous [deg]', (0.0, 180.0))
    refine_lm: bool = setting(True, 'Levenberg-Marquardt polish of the IPPE pose')
    fusion: str = setting('best', 'Combining several accepted markers', choices=FUSION_MODES)
    min_side_px: float = setting(8.0, 'Ignore markers with a shorter side [px]', (0.0, 1000.0))
    corner_refinement: bool = setting(True, "ArUco's sub-pixel corner refinement (CORNER_REFINE_SUBPIX)")
    edge_refinement: bool = setting(True, 'Corners from fitted edge lines (removes ArUco corner bias)')

    def __post_init__(self) -> None:
        if self.fusion not in FUSION_MODES:
            raise ValueError(f'fusion: unknown mode {self.fusion!r}; expected one of {FUSION_MODES}')
        for name in ('max_reprojection_error_px', 'ambiguity_ratio', 'ambiguity_margin_px',
                     'ambiguity_min_angle_deg', 'min_side_px'):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f'{name}: must be finite and >= 0, got {v}')
        if self.ambiguity_ratio < 1.0:
            raise ValueError(f'ambiguity_ratio: must be >= 1 (1 with ambiguity_margin_px 0 disables the test), '
                             f'got {self.ambiguity_ratio}')


@dataclass(frozen=True)
class DetectedMarker:
    """A marker found in an image: id and refined corners, shape (4, 2), OpenCV order."""

    marker_id: int
    corners: NDArray[np.float64]


@dataclass(frozen=True)
class MarkerPose:
    """Pose of one detected marker in the camera frame and the evidence behind it.

    Attributes
    ----------
    marker_id : int
    corners : ndarray, shape (4, 2)
    cam_T_marker : ndarray, shape (4, 4)
        The chosen solution.
    alt_cam_T_marker : ndarray, shape (4, 4) or None
        The other IPPE solution (None when IPPE returned one).
    error_px, alt_error_px : float
        RMS reprojection errors of the chosen and alternative solutions [px].
    alt_angle_deg : float
        Rotation between the two solutions [deg].
    r, phi_deg : float
        Distance [m] and viewing angle [deg] of the chosen solution (for the noise model).
    status : str
        ``ok``, ``ambiguous``, ``reprojection``, ``invalid`` (NaN, behind the camera, degenerate).
    """

    marker_id: int
    corners: NDArray[np.float64]
    cam_T_marker: NDArray[np.float64]
    alt_cam_T_marker: NDArray[np.float64] | None
    error_px: float
    alt_error_px: float
    alt_angle_deg: float
    r: float
    phi_deg: float
    status: str = 'ok'

    @property
    def ok(self) -> bool:
        return self.status == 'ok'


@dataclass(frozen=True)
class HandEstimate:
    """A hand pose with its covariance.

    Attributes
    ----------
    pose : ndarray, shape (4, 4)
        Hand frame in the output frame (root_link, or the camera for camera-frame estimates).
    covariance : ndarray, shape (6, 6)
    marker_ids : tuple of int
        Markers that contributed.
    pos_var, rot_var : float
        Per-axis position [m^2] and orientation [rad^2] variances of the estimate.
    """

    pose: NDArray[np.float64]
    covariance: NDArray[np.float64]
    marker_ids: tuple[int, ...]
    pos_var: float
    rot_var: float


@dataclass
class FrameResult:
    """Everything one image produced.

    ``markers`` are the accepted marker poses (what ``/markers`` carries); ``rejected`` the
    detected-but-refused ones; ``hand`` is None for a failed detection; ``bad_input`` is set
    when the frame could not be judged at all (then there are no markers and no hand). ``k``
    and ``dist`` are the camera matrix and distortion the image was judged with (None before
    that), which a stereo refinement projects through (:meth:`HandPoseEstimator.stereo`).
    """

    markers: list[MarkerPose] = field(default_factory=list)
    rejected: list[MarkerPose] = field(default_factory=list)
    hand: HandEstimate | None = None
    seconds: float = 0.0
    bad_input: BadInput | None = None
    k: NDArray[np.float64] | None = None
    dist: NDArray[np.float64] | None = None

    @property
    def success(self) -> bool:
        return self.hand is not None

    @property
    def status(self) -> FrameStatus:
        """Detected, no marker (a valid frame without the hand), or bad input."""
        if self.bad_input is not None:
            return FrameStatus.BAD_INPUT
        return FrameStatus.DETECTED if self.success else FrameStatus.NO_MARKER


# --------------------------------------------------------------------------------------------
# Detection (the only place that knows about OpenCV ArUco API versions)


def _aruco_backend(dictionary: object, params: object) -> Callable[[NDArray[np.uint8]], tuple]:
    """``image -> (corners, ids, rejected)`` for this OpenCV.

    OpenCV >= 4.7 has the ArucoDetector class; older versions only the free function.
    """
    if hasattr(cv2.aruco, 'ArucoDetector'):
        return cv2.aruco.ArucoDetector(dictionary, params).detectMarkers
    return lambda img: cv2.aruco.detectMarkers(img, dictionary, parameters=params)  # pragma: no cover


def _detector_parameters() -> object:
    if hasattr(cv2.aruco, 'DetectorParameters'):
        return cv2.aruco.DetectorParameters()
    return cv2.aruco.DetectorParameters_create()  # pragma: no cover (OpenCV < 4.7)


class MarkerDetector:
    """Find the hand's ArUco markers in a grey image.

    Parameters
    ----------
    dictionary : str
        Name of a predefined dictionary, e.g. ``"DICT_4X4_50"``.
    known_ids : iterable of int
        Ids of the hand's markers; any other id is ignored.
    corner_refinement : bool
        Sub-pixel corner refinement.
    min_side_px : float
        Drop detections whose shortest side is below this many pixels.
    edge_refinement : bool
        Re-locate corners from fitted edge lines after ArUco's own refinement.
    """

    def __init__(self, dictionary: str, known_ids: Sequence[int], corner_refinement: bool = True,
                 min_side_px: float = 8.0, edge_refinement: bool = True) -> None:
        aruco_dict = aruco_dictionary(dictionary)
        self.dictionary_name = dictionary
        self.known_ids = frozenset(int(i) for i in known_ids)
        self.min_side_px = float(min_side_px)
        params = _detector_parameters()
        if corner_refinement:
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            # Small markers (a 3 cm marker is ~25 px at 320x240): keep the window inside a cell.
            params.cornerRefinementWinSize = 3
            params.cornerRefinementMinAccuracy = 0.01
            params.cornerRefinementMaxIterations = 50
        self.cells = int(aruco_dict.markerSize) + 2 * int(params.markerBorderBits)
        self.edge_refinement = bool(edge_refinement)
        self._detect = _aruco_backend(aruco_dict, params)

    def detect(self, gray: NDArray[np.uint8]) -> list[DetectedMarker]:
        """Detect markers.

        Parameters
        ----------
        gray : ndarray, uint8, shape (H, W)

        Returns
        -------
        list of DetectedMarker
            Known ids only, sorted by id; a duplicated id (two markers claiming the same id) is
            dropped entirely since at most one can be the hand's. Empty for an image too small to
            hold a marker.

        Raises
        ------
        ValueError
            ``gray`` is not a 2-D uint8 array.
        """
        gray = np.asarray(gray)
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f'gray: expected a uint8 image of shape (H, W), got {gray.dtype} {gray.shape}')
        if min(gray.shape) < 8:
            return []                                   # too small to hold a marker
        corners, ids, _ = self._detect(np.ascontiguousarray(gray))
        if ids is None or len(ids) == 0:
            return []
        ids = np.asarray(ids).reshape(-1)
        found: dict[int, list[NDArray[np.float64]]] = {}
        for mid, c in zip(ids.tolist(), corners):
            if mid in self.known_ids:
                found.setdefault(int(mid), []).append(np.asarray(c, dtype=float).reshape(4, 2))
        out = []
        for mid in sorted(found):
            if len(found[mid]) != 1:
                continue
            c = found[mid][0]
            side = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1).min()
            if not (np.all(np.isfinite(c)) and side >= self.min_side_px):
                continue
            if self.edge_refinement:
                refined = refine_corners_edges(gray, c, self.cells)
                c = c if refined is None else refined
            out.append(DetectedMarker(mid, c))
        return out


# --------------------------------------------------------------------------------------------
# Single-marker pose


def _to_matrix(rvec: ArrayLike, tvec: ArrayLike) -> NDArray[np.float64]:
    t = np.eye(4)
    t[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]
    t[:3, 3] = np.asarray(tvec, dtype=float).reshape(3)
    return t


def _rms_error(obj: NDArray[np.float64], img: NDArray[np.float64], t: NDArray[np.float64],
               k: NDArray[np.float64], dist: NDArray[np.float64]) -> float:
    rvec = cv2.Rodrigues(t[:3, :3])[0]
    proj, _ = cv2.projectPoints(obj, rvec, t[:3, 3], k, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def solve_marker_pose(marker: DetectedMarker, side: float, k: ArrayLike,
                      dist: ArrayLike | None = None, refine_lm: bool = True) -> MarkerPose:
    """Best pose of one marker and its planar-flip alternative (no gating; see :func:`gate_marker`).

    Candidates are the two IPPE_SQUARE solutions plus SQPnP's (a guard against an OpenCV IPPE
    failure on mirror-symmetric images); the one with the smallest reprojection error wins and
    the IPPE solution farthest from it in rotation is the alternative (the flip).

    Parameters
    ----------
    marker : DetectedMarker
    side : float
        Marker side length [m].
    k : array_like, shape (3, 3)
        Camera matrix.
    dist : array_like, shape (N,), optional
        Distortion coefficients (plumb_bob); None for none.
    refine_lm : bool
        Polish the best solution by Levenberg-Marquardt on the reprojection error.

    Returns
    -------
    MarkerPose
        ``status`` is ``invalid`` when OpenCV fails, returns NaN, or puts the marker behind the
        camera; otherwise ``ok`` (gating comes later).
    """
    k = np.asarray(k, dtype=float).reshape(3, 3)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).reshape(-1)
    obj = marker_corners(side)
    img = np.asarray(marker.corners, dtype=float).reshape(4, 2)
    invalid = MarkerPose(marker.marker_id, img, np.full((4, 4), np.nan), None, np.inf, np.inf,
                         0.0, np.nan, np.nan, 'invalid')
    if not (np.all(np.isfinite(img)) and np.all(np.isfinite(k)) and np.all(np.isfinite(dist))):
        return invalid
    sols, n_ippe = [], 0
    # IPPE_SQUARE gives both planar solutions. OpenCV 5.0's IPPE returns two wrong poses
    # (tens of px) when the square's image is (nearly) mirror-symmetric about a row; SQPnP's
    # global minimum is a cheap (~0.1 ms) safety net that never loses the true pose.
    for flag in (cv2.SOLVEPNP_IPPE_SQUARE, cv2.SOLVEPNP_SQPNP):
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, k, dist, flags=flag)
        except cv2.error:
            continue
        for i in range(int(n)):
            t = _to_matrix(rvecs[i], tvecs[i])
            if np.all(np.isfinite(t)) and t[2, 3] > 0:
                sols.append(t)
        if flag == cv2.SOLVEPNP_IPPE_SQUARE:
            n_ippe = len(sols)
    if not sols:
        return invalid
    errors = [_rms_error(obj, img, t, k, dist) for t in sols]
    order = [int(i) for i in np.argsort(errors)]
    best = sols[order[0]]
    # The alternative is the IPPE solution farthest in rotation from the winner: the flip.
    # (SQPnP and the matching IPPE solution differ by a degree or so; that is not the flip.)
    angles = [float(rotation_angle_deg(best[:3, :3], sols[i][:3, :3])) for i in range(n_ippe)]
    others = [int(np.argmax(angles))] if angles and max(angles) > 0.5 else []
    if refine_lm:
        rvec, tvec = cv2.Rodrigues(best[:3, :3])[0], best[:3, 3].reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
            cand = _to_matrix(rvec, tvec)
            if np.all(np.isfinite(cand)) and cand[2, 3] > 0 and \
                    _rms_error(obj, img, cand, k, dist) <= errors[order[0]] + 1e-9:
                best = cand
        except cv2.error:
            pass
    err = _rms_error(obj, img, best, k, dist)
    if others:
        alt = sols[others[0]]
        alt_err = errors[others[0]]
        angle = float(rotation_angle_deg(best[:3, :3], alt[:3, :3]))
    else:
        alt, alt_err, angle = None, np.inf, 0.0
    r, phi = view_geometry(np.eye(4), best)
    return MarkerPose(marker.marker_id, img, best, alt, err, float(alt_err), angle,
                      float(r), float(phi))


def gate_marker(pose: MarkerPose, config: DetectorConfig) -> MarkerPose:
    """Apply the reprojection and ambiguity tests; returns the pose with its ``status`` set."""
    if pose.status != 'ok':
        return pose
    if not pose.error_px <= config.max_reprojection_error_px:
        return replace(pose, status='reprojection')
    if (pose.alt_cam_T_marker is not None
            and pose.alt_error_px < config.ambiguity_ratio * pose.error_px + config.ambiguity_margin_px
            and pose.alt_angle_deg > config.ambiguity_min_angle_deg):
        return replace(pose, status='ambiguous')
    return pose


# --------------------------------------------------------------------------------------------
# Hand pose, covariance and fusion


def hand_from_marker(cam_T_marker: ArrayLike, placement: MarkerPlacement,
                     root_T_cam: ArrayLike | None = None) -> NDArray[np.float64]:
    """Hand frame from a marker pose: ``root_T_cam @ cam_T_marker @ inv(hand_T_marker)``, (4, 4)."""
    hand_T_marker = np.asarray(placement.hand_T_marker, dtype=float)
    cam_T_hand = np.asarray(cam_T_marker, dtype=float) @ np.linalg.inv(hand_T_marker)
    return cam_T_hand if root_T_cam is None else np.asarray(root_T_cam, dtype=float) @ cam_T_hand


def _cov(pos_var: float, rot_var: float) -> NDArray[np.float64]:
    return np.diag([pos_var] * 3 + [rot_var] * 3)


def fuse_estimates(estimates: Sequence[HandEstimate]) -> HandEstimate:
    """Information-weighted fusion of independent hand estimates (markers or eyes).

    Positions are averaged with weights ``1 / pos_var``; rotations with the weighted chordal
    mean (``Rotation.mean``) with weights ``1 / rot_var``; the fused variances are the inverse of
    the summed informations (the estimates are treated as independent).
    """
    if not estimates:
        raise ValueError('fuse_estimates: nothing to fuse')
    if len(estimates) == 1:
        return estimates[0]
    wp = np.array([1.0 / e.pos_var for e in estimates])
    wr = np.array([1.0 / e.rot_var for e in estimates])
    poses = np.stack([e.pose for e in estimates])
    out = np.eye(4)
    out[:3, 3] = (wp[:, None] * poses[:, :3, 3]).sum(0) / wp.sum()
    out[:3, :3] = Rotation.from_matrix(poses[:, :3, :3]).mean(weights=wr).as_matrix()
    pv, rv = 1.0 / wp.sum(), 1.0 / wr.sum()
    ids = tuple(sorted({i for e in estimates for i in e.marker_ids}))
    return HandEstimate(out, _cov(pv, rv), ids, pv, rv)


def refine_joint(cam_T_hand0: ArrayLike, markers: Sequence[MarkerPose],
                 placements: dict[int, MarkerPlacement], side: float, k: ArrayLike,
                 dist: ArrayLike | None = None) -> NDArray[np.float64]:
    """One LM PnP over the corners of all markers with the hand frame as the object frame.

    Parameters
    ----------
    cam_T_hand0 : array_like, shape (4, 4)
        Initial hand pose in the camera frame (e.g. from the best marker).
    markers : sequence of MarkerPose
        Accepted markers (their corners are used).

    Returns
    -------
    ndarray, shape (4, 4)
        Refined hand pose in the camera frame; the initial pose if refinement fails.
    """
    k = np.asarray(k, dtype=float).reshape(3, 3)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).reshape(-1)
    obj_m = np.c_[marker_corners(side), np.ones(4)]
    obj = np.concatenate([(placements[m.marker_id].hand_T_marker @ obj_m.T).T[:, :3] for m in markers])
    img = np.concatenate([m.corners for m in markers])
    t0 = np.asarray(cam_T_hand0, dtype=float)
    rvec, tvec = cv2.Rodrigues(t0[:3, :3])[0], t0[:3, 3].reshape(3, 1).copy()
    try:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
    except cv2.error:
        return t0
    t = _to_matrix(rvec, tvec)
    return t if np.all(np.isfinite(t)) and t[2, 3] > 0 else t0


@dataclass(frozen=True)
class StereoView:
    """One eye's share of a stereo refinement.

    Attributes
    ----------
    root_T_cam : ndarray, shape (4, 4)
        The eye's optical frame in the output frame.
    k : ndarray, shape (3, 3)
    dist : ndarray, shape (N,), or None
    markers : sequence of MarkerPose
        The eye's accepted markers (their detected corners are used).
    """

    root_T_cam: NDArray[np.float64]
    k: NDArray[np.float64]
    dist: NDArray[np.float64] | None
    markers: Sequence[MarkerPose]


def refine_stereo(root_T_hand0: ArrayLike, views: Sequence[StereoView], placements: dict[int, MarkerPlacement],
                  side: float) -> tuple[NDArray[np.float64], float]:
    """One hand pose from the marker corners of several calibrated cameras (Levenberg-Marquardt).

    Minimises the reprojection error of every accepted marker corner in every view over the hand
    pose in the root frame: one camera measures a marker's depth from its apparent size, two
    cameras by triangulation over their baseline (on the iCub's eyes, 0.33 mm median position
    error against 0.82 mm for the eyes' poses fused: the package README's bench).

    Parameters
    ----------
    root_T_hand0 : array_like, shape (4, 4)
        Initial hand pose in the root frame (e.g. the eyes' poses fused).
    views : sequence of StereoView
    placements : dict of int to MarkerPlacement
    side : float
        Marker side length [m].

    Returns
    -------
    pose : ndarray, shape (4, 4)
        Refined hand pose in the root frame.
    rms : float
        Root-mean-square reprojection error at the solution [px]; infinite if the solver failed
        or a corner ended behind its camera.
    """
    from scipy.optimize import least_squares

    t0 = np.asarray(root_T_hand0, dtype=float)
    obj_m = np.c_[marker_corners(side), np.ones(4)]
    items = []
    for v in views:
        cam_T_root = np.linalg.inv(np.asarray(v.root_T_cam, dtype=float))
        dist = np.zeros(5) if v.dist is None else np.asarray(v.dist, dtype=float).reshape(-1)
        for m in v.markers:
            obj = (placements[m.marker_id].hand_T_marker @ obj_m.T).T[:, :3]
            corners = np.asarray(m.corners, dtype=float).reshape(-1, 2)
            items.append((cam_T_root, np.asarray(v.k, dtype=float), dist, obj, corners))
    if not items:
        raise ValueError('refine_stereo: no marker corners to refine on')

    def pose(x: NDArray[np.float64]) -> NDArray[np.float64]:
        # Left perturbation in the root frame: the same tangent space as the published covariance.
        t = np.eye(4)
        t[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix() @ t0[:3, :3]
        t[:3, 3] = t0[:3, 3] + x[3:]
        return t

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        t = pose(x)
        out = []
        for cam_T_root, k, dist, obj, uv in items:
            c = cam_T_root @ t
            rvec = cv2.Rodrigues(c[:3, :3])[0]
            proj = cv2.projectPoints(obj, rvec, c[:3, 3], k, dist)[0].reshape(-1, 2)
            out.append((proj - uv).ravel())
        return np.concatenate(out)

    try:
        sol = least_squares(residuals, np.zeros(6), method='lm', x_scale=np.r_[1e-2, 1e-2, 1e-2, 1e-3, 1e-3, 1e-3])
    except (ValueError, cv2.error):
        return t0, float('inf')
    t = pose(sol.x)
    depths = [(cam_T_root @ t @ np.c_[obj, np.ones(len(obj))].T)[2] for cam_T_root, _, _, obj, _ in items]
    if not sol.success or not np.all(np.isfinite(sol.fun)) or min(float(d.min()) for d in depths) <= 0:
        return t0, float('inf')
    return t, float(np.sqrt(np.mean(sol.fun ** 2)))


class HandPoseEstimator:
    """Image of one eye -> accepted marker poses -> one hand pose in the root frame.

    Parameters
    ----------
    model : ArmModel
        Supplies the dictionary, marker side and placements (``model.markers``).
    noise : NoiseModel
        Gives the published covariance (pose-dependent or constant).
    config : DetectorConfig
    quality : PoseDependentNoise, optional
        Ranks markers for ``fusion='best'`` and weights them for the other modes; the
        pose-dependent model by default, whatever ``noise`` is, because a constant model cannot
        tell a good view from a bad one.
    """

    def __init__(self, model: ArmModel, noise: NoiseModel, config: DetectorConfig | None = None,
                 quality: PoseDependentNoise | None = None) -> None:
        if not model.markers:
            raise ValueError(f'robot {model.name!r} has no hand markers')
        self.model = model
        self.noise = noise
        self.config = config or DetectorConfig()
        self.quality = quality or PoseDependentNoise()
        self.placements = {m.marker_id: m for m in model.markers}
        self.side = float(model.marker_side_length)
        self.detector = MarkerDetector(model.marker_dictionary, list(self.placements),
                                       self.config.corner_refinement, self.config.min_side_px,
                                       self.config.edge_refinement)

    def marker_poses(self, gray: NDArray[np.uint8], k: ArrayLike,
                     dist: ArrayLike | None = None) -> list[MarkerPose]:
        """Detect and solve every known marker (ungated; for studies), sorted by id."""
        return [solve_marker_pose(d, self.side, k, dist, self.config.refine_lm)
                for d in self.detector.detect(gray)]

    def combine(self, poses: Sequence[MarkerPose], k: ArrayLike, dist: ArrayLike | None,
                root_T_cam: ArrayLike | None, fusion: str | None = None) -> HandEstimate | None:
        """Hand estimate from accepted marker poses (None if there are none).

        ``root_T_cam`` None gives the estimate in the camera frame.
        """
        ok = [p for p in poses if p.ok]
        if not ok:
            return None
        fusion = fusion or self.config.fusion
        root = np.eye(4) if root_T_cam is None else np.asarray(root_T_cam, dtype=float)
        r = np.array([p.r for p in ok])
        phi = np.array([p.phi_deg for p in ok])
        q_pos, q_rot = self.quality.variances(r, phi)
        n_pos, n_rot = self.noise.variances(r, phi)
        # Each marker's line of sight in the output frame: the law's depth_ratio stretches along it.
        los = [root[:3, :3] @ p.cam_T_marker[:3, 3] for p in ok]
        ratio = self.noise.depth_ratio
        singles = [HandEstimate(root @ hand_from_marker(p.cam_T_marker, self.placements[p.marker_id]),
                                line_of_sight_covariance(float(n_pos[i]), float(n_rot[i]), los[i], ratio),
                                (p.marker_id,), float(n_pos[i]), float(n_rot[i])) for i, p in enumerate(ok)]
        best = int(np.argmin(q_pos))
        if fusion == 'best' or len(ok) == 1:
            return singles[best]
        # Weights from the quality model, published covariance from the noise model.
        weighted = fuse_estimates([replace(s, pos_var=float(q_pos[i]), rot_var=float(q_rot[i]))
                                   for i, s in enumerate(singles)])
        pv = 1.0 / np.sum(1.0 / n_pos)
        rv = 1.0 / np.sum(1.0 / n_rot)
        cov = line_of_sight_covariance(pv, rv, los[best], ratio)
        if fusion == 'weighted':
            return HandEstimate(weighted.pose, cov, weighted.marker_ids, pv, rv)
        cam_T_hand0 = np.linalg.inv(root) @ singles[best].pose
        cam_T_hand = refine_joint(cam_T_hand0, ok, self.placements, self.side, k, dist)
        return HandEstimate(root @ cam_T_hand, cov, weighted.marker_ids, pv, rv)

    def process(self, gray: NDArray[np.uint8], k: ArrayLike, dist: ArrayLike | None = None,
                root_T_cam: ArrayLike | None = None) -> FrameResult:
        """Detect, solve, gate and fuse for one grey image.

        Parameters
        ----------
        gray : ndarray, uint8, shape (H, W)
        k : array_like, shape (3, 3)
        dist : array_like, shape (N,), optional
        root_T_cam : array_like, shape (4, 4), optional
            Camera optical frame in the root frame; None gives the hand in the camera frame.

        Returns
        -------
        FrameResult
            Never raises for image content (random pixels give an empty result: no marker).

        Raises
        ------
        BadInput
            For a camera matrix or distortion that cannot be used (NaN, zero focal length): every
            marker would fail to solve, and an empty result would claim the hand was not seen.
        ValueError
            For a malformed ``gray`` array.
        """
        k = np.asarray(k, dtype=float)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise BadInput('camera_info.K', f'expected a finite camera matrix with positive focal lengths, '
                           f'got {k.tolist()}')
        if dist is not None and not np.all(np.isfinite(np.asarray(dist, dtype=float))):
            raise BadInput('camera_info.D', f'distortion coefficients must be finite, got '
                           f'{np.asarray(dist, dtype=float).tolist()}')
        t0 = time.perf_counter()
        poses = [gate_marker(p, self.config) for p in self.marker_poses(gray, k, dist)]
        hand = self.combine(poses, k, dist, root_T_cam)
        return FrameResult(markers=[p for p in poses if p.ok], rejected=[p for p in poses if not p.ok],
                           hand=hand, seconds=time.perf_counter() - t0, k=k,
                           dist=None if dist is None else np.asarray(dist, dtype=float))

    def stereo(self, views: Sequence[tuple[FrameResult, ArrayLike]]) -> HandEstimate:
        """One hand estimate from the same stamp's results of several eyes, each with its hand.

        The eyes' poses fused (:func:`fuse_estimates`) start :func:`refine_stereo` over all their
        accepted markers' corners; its covariance is :func:`body_schema.noise.stereo_covariance`
        of the eyes' ones. If the refinement fails or its RMS reprojection error exceeds the
        gate's ``max_reprojection_error_px`` (the eyes disagree, e.g. one saw a planar flip), the
        fused poses are returned instead.

        Parameters
        ----------
        views : sequence of (FrameResult, root_T_cam)
            Results with a hand, judged with a camera matrix (``k``); ``root_T_cam`` shape (4, 4).

        Raises
        ------
        ValueError
            For fewer than two views, a view without a hand or without its camera matrix.
        """
        if len(views) < 2:
            raise ValueError(f'stereo needs at least two eyes\' results, got {len(views)}')
        if any(r.hand is None or r.k is None for r, _ in views):
            raise ValueError('stereo needs every eye\'s result with a hand and its camera matrix (k)')
        hands = [r.hand for r, _ in views]
        fused = fuse_estimates(hands)
        pose, rms = refine_stereo(fused.pose, [StereoView(np.asarray(t, dtype=float), r.k, r.dist, r.markers)
                                               for r, t in views], self.placements, self.side)
        if not rms <= self.config.max_reprojection_error_px:
            return fused
        cov = stereo_covariance(np.stack([h.covariance for h in hands]), self.noise)
        return HandEstimate(pose, cov, fused.marker_ids, fused.pos_var * self.noise.stereo_pos,
                            fused.rot_var * self.noise.stereo_rot)
