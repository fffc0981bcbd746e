"""The camera's pose and the marker's offset, estimated with the DH table (pure, no rclpy).

A fixed camera's pose in the root frame is known from a tape measure (centimetres, degrees)
and the marker's place on the flange from a drawing (millimetres, degrees). Both are estimated
with the arm as 6-D corrections of the nominal poses the rest of the graph uses:

* the real camera is ``C = perturb_pose(C_nom, c)`` and the real marker (board) placement on the
  flange ``M = perturb_pose(M_nom, m)``, where :func:`perturb_pose` adds ``delta[:3]`` [m] to the
  position and turns the frame by the rotation vector ``delta[3:]`` [rad] about its own origin,
  both in the parent frame (root for the camera, flange for the marker): a user states "2 cm,
  2 deg" in exactly these terms;
* the detector turns a marker seen at ``cam_T_marker = C^-1 FK(dh, q) M`` into a hand pose with the
  nominal poses, ``C_nom cam_T_marker M_nom^-1``, so the observation model is

      h(dh, c, m; q) = E(c) FK(dh, q) F(m),   E = C_nom C^-1,   F = M M_nom^-1.

With several markers on the hand, ``M_nom`` is the first one's placement and the board moves
rigidly (every marker by the same ``F``).

:class:`Extrinsics` holds the nominal poses, which corrections are estimated and their prior
standard deviations; :meth:`Extrinsics.predict` gives the predicted hand poses and the Jacobian
of the augmented parameter vector ``(dh.ravel(), c, m)`` for
:class:`body_schema.map_estimator.MapEstimator`. The DH block is analytic (the DH pose Jacobian
carried through ``E`` and ``F``); the 6 or 12 correction columns are central differences
(checked against the closed form at zero corrections in the tests).

Some DH parameters are then not separable from the corrections: ``E`` absorbs the first link's
``d`` and ``offset`` (a turn about and a shift along the first joint axis commute with the
joint), ``F`` absorbs the whole last row (everything after the last joint's rotation is one fixed
transform). :func:`align_truth` re-expresses a true (table, camera, marker) in the gauge of an
estimate that holds those parameters, which is how an estimate is scored against a simulator's
truth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from . import kinematics
from .kinematics import PARAMS_PER_LINK

__all__ = ['POSE_FIELDS', 'Extrinsics', 'corrections', 'perturb_pose', 'pose_delta', 'random_delta', 'parse_std',
           'align_truth', 'absorbed_parameters', 'static_transform']

#: Names of a 6-D correction's components: position [m] then rotation vector [rad], parent frame.
POSE_FIELDS = ('x', 'y', 'z', 'rx', 'ry', 'rz')

#: Central-difference step of the correction columns [m or rad].
_STEP = 1e-6


def perturb_pose(pose: ArrayLike, delta: ArrayLike) -> NDArray[np.float64]:
    """``pose`` moved by ``delta[:3]`` [m] and turned by the rotation vector ``delta[3:]`` [rad]
    about its own origin, both in the parent frame, shape (4, 4)."""
    pose = np.asarray(pose, dtype=float)
    delta = np.asarray(delta, dtype=float)
    if pose.shape != (4, 4) or delta.shape != (6,):
        raise ValueError(f'perturb_pose needs a (4, 4) pose and a (6,) delta, got {pose.shape}, {delta.shape}')
    out = pose.copy()
    out[:3, :3] = Rotation.from_rotvec(delta[3:]).as_matrix() @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + delta[:3]
    return out


def pose_delta(pose: ArrayLike, nominal: ArrayLike) -> NDArray[np.float64]:
    """The ``delta`` (6,) with ``perturb_pose(nominal, delta) == pose`` (inverse of :func:`perturb_pose`)."""
    pose = np.asarray(pose, dtype=float)
    nominal = np.asarray(nominal, dtype=float)
    rot = kinematics.rotation_vector_error(pose[:3, :3], nominal[:3, :3])
    return np.concatenate([pose[:3, 3] - nominal[:3, 3], np.ravel(rot)])


def random_delta(rng: np.random.Generator, length: float, angle: float) -> NDArray[np.float64]:
    """A correction of exactly ``length`` [m] in a uniformly random direction and ``angle`` [rad]
    about a uniformly random axis, shape (6,) (a tape-measure error "2 cm, 2 deg")."""
    u = rng.normal(size=(2, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.concatenate([length * u[0], angle * u[1]])


def parse_std(text: str, name: str) -> tuple[float, float] | None:
    """``"<length m> <angle deg>"`` as (length [m], angle [rad]); ``''``, ``'0'`` or ``'0 0'``: None.

    Raises
    ------
    ValueError
        Naming ``name`` and the text, for anything else (one value, negative, non-numeric).
    """
    fields = text.replace(',', ' ').split()
    try:
        values = [float(v) for v in fields]
    except ValueError as exc:
        raise ValueError(f'{name} must be "<length m> <angle deg>", got {text!r}') from exc
    if not values or all(v == 0 for v in values):
        return None
    if len(values) != 2 or not all(np.isfinite(v) and v > 0 for v in values):
        raise ValueError(f'{name} must be "<length m> <angle deg>" with both > 0 (or 0: known), got {text!r}')
    return values[0], float(np.radians(values[1]))


def corrections(camera: ArrayLike, marker: ArrayLike, c: ArrayLike, m: ArrayLike
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``E = C_nom C^-1`` and ``F = M M_nom^-1`` (4, 4) for nominal poses ``camera`` (root frame),
    ``marker`` (flange frame) and corrections ``c``, ``m`` (6,) (:func:`perturb_pose`)."""
    camera, marker = np.asarray(camera, dtype=float), np.asarray(marker, dtype=float)
    return (camera @ np.linalg.inv(perturb_pose(camera, c)),
            perturb_pose(marker, m) @ np.linalg.inv(marker))


@dataclass(frozen=True)
class Extrinsics:
    """Which extrinsic corrections are estimated, around which nominal poses.

    Attributes
    ----------
    camera : ndarray, shape (4, 4)
        Nominal optical frame in the root frame (what the detector uses).
    marker : ndarray, shape (4, 4)
        Nominal placement of the (first) hand marker in the flange frame.
    camera_std, marker_std : tuple of float or None
        Prior standard deviation (length [m], angle [rad]) per component of the correction;
        None: known, not estimated.
    """

    camera: NDArray[np.float64]
    marker: NDArray[np.float64]
    camera_std: tuple[float, float] | None = None
    marker_std: tuple[float, float] | None = None

    @property
    def blocks(self) -> tuple[str, ...]:
        """The estimated corrections, in state order: ``'camera'``, ``'marker'``."""
        return tuple(b for b, s in (('camera', self.camera_std), ('marker', self.marker_std)) if s is not None)

    @property
    def n(self) -> int:
        """Number of correction parameters (0, 6 or 12)."""
        return 6 * len(self.blocks)

    @property
    def names(self) -> tuple[str, ...]:
        """``camera.x`` ... ``marker.rz``, in state order."""
        return tuple(f'{b}.{f}' for b in self.blocks for f in POSE_FIELDS)

    def prior_std(self) -> NDArray[np.float64]:
        """Prior standard deviation of each correction, shape (n,)."""
        out = []
        for b in self.blocks:
            length, angle = self.camera_std if b == 'camera' else self.marker_std
            out += [length] * 3 + [angle] * 3
        return np.asarray(out, dtype=float)

    def split(self, e: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Camera and marker corrections (6,) each (zeros for a known one) from ``e`` (n,)."""
        e = np.asarray(e, dtype=float)
        parts = {b: e[6 * i:6 * i + 6] for i, b in enumerate(self.blocks)}
        return parts.get('camera', np.zeros(6)), parts.get('marker', np.zeros(6))

    def poses(self, e: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The camera (root frame) and marker (flange frame) poses the corrections ``e`` describe."""
        c, m = self.split(e)
        return perturb_pose(self.camera, c), perturb_pose(self.marker, m)

    def corrections(self, e: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``E = C_nom C^-1`` and ``F = M M_nom^-1``, (4, 4) each."""
        return corrections(self.camera, self.marker, *self.split(e))

    def predict(self, frames: NDArray[np.float64], e: ArrayLike, jacobian: bool = True
                ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Predicted hand poses and the Jacobian w.r.t. ``(dh.ravel(), e)``.

        Parameters
        ----------
        frames : ndarray, shape (N, L + 1, 4, 4)
            :func:`body_schema.kinematics.chain_frames` of the DH estimate.
        e : array_like, shape (n,)
            The corrections.
        jacobian : bool

        Returns
        -------
        hands : ndarray, shape (N, 4, 4)
            ``E FK F``.
        J : ndarray, shape (N, 6, 4 L + n) or None
            Rows (position, root-frame rotation), as :func:`kinematics.pose_jacobian_from_frames`.
        """
        e = np.asarray(e, dtype=float)
        fk = frames[:, -1]
        big_e, big_f = self.corrections(e)
        hands = big_e @ fk @ big_f
        if not jacobian:
            return hands, None
        j_dh = kinematics.pose_jacobian_from_frames(frames)              # (N, 6, 4L) of FK
        # h = E T F: dp = R_E (dp_T + dw_T x (R_T p_F)), dw = R_E dw_T.
        arm = np.einsum('nij,j->ni', fk[:, :3, :3], big_f[:3, 3])          # R_T p_F, (N, 3)
        skew = np.zeros((len(fk), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -arm[:, 2], arm[:, 1], -arm[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = arm[:, 2], -arm[:, 1], arm[:, 0]
        r_e = big_e[:3, :3]
        jp = r_e @ (j_dh[:, :3] - np.einsum('nij,njk->nik', skew, j_dh[:, 3:]))
        jw = r_e @ j_dh[:, 3:]
        cols = [np.concatenate([jp, jw], axis=1)]
        if self.n:
            cols.append(self._correction_columns(fk, e))
        return hands, np.concatenate(cols, axis=2)

    def _correction_columns(self, fk: NDArray[np.float64], e: NDArray[np.float64]) -> NDArray[np.float64]:
        """Central differences of ``E FK F`` w.r.t. each correction, shape (N, 6, n)."""
        out = np.empty((len(fk), 6, self.n))
        for k in range(self.n):
            step = np.zeros(self.n)
            step[k] = _STEP
            (ep, fp), (em, fm) = self.corrections(e + step), self.corrections(e - step)
            plus, minus = ep @ fk @ fp, em @ fk @ fm
            out[:, :3, k] = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * _STEP)
            out[:, 3:, k] = np.reshape(kinematics.rotation_vector_error(plus[:, :3, :3], minus[:, :3, :3]),
                                       (-1, 3)) / (2 * _STEP)
        return out


def absorbed_parameters(n_links: int, camera: bool, marker: bool) -> tuple[int, ...]:
    """Indices in the flattened table of the DH parameters a free camera / marker absorbs.

    A free camera (``E`` left of the chain) absorbs the first link's ``d`` and ``offset``
    (``Rz(offset) Tz(d)`` commutes with the first joint's rotation); a free marker (``F`` right
    of it) absorbs the last link's ``a, d, alpha, offset`` (all after the last joint's rotation).
    """
    idx: list[int] = []
    if camera:
        idx += [1, 3]
    if marker:
        last = (n_links - 1) * PARAMS_PER_LINK
        idx += list(range(last, last + PARAMS_PER_LINK))
    return tuple(sorted(set(idx)))


def _rz_tz(offset: float, d: float) -> NDArray[np.float64]:
    c, s = np.cos(offset), np.sin(offset)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, d], [0, 0, 0, 1]], dtype=float)


def align_truth(base: ArrayLike, true_dh: ArrayLike, true_camera: ArrayLike, true_marker: ArrayLike,
                held_dh: ArrayLike, camera: bool, marker: bool
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The truth in the gauge of an estimate: same observations, absorbed parameters as held.

    The parameters of :func:`absorbed_parameters` take ``held_dh``'s values and the true camera
    and marker move to keep every hand pose the camera sees unchanged (exactly, not to first
    order). An estimate is then scored against this truth: a camera cannot tell the base's turn
    about its first axis from the camera's own, nor the last link's transform from the marker's.

    Parameters
    ----------
    base : array_like, shape (4, 4)
        Root to the first joint's frame.
    true_dh, held_dh : array_like, shape (L, 4)
        The real table and the estimate's (whose absorbed parameters were held).
    true_camera : array_like, shape (4, 4)
        Real camera pose in the root frame.
    true_marker : array_like, shape (4, 4)
        Real marker placement in the flange frame.
    camera, marker : bool
        Which corrections the estimate has.

    Returns
    -------
    dh, camera, marker : ndarray, shapes (L, 4), (4, 4), (4, 4)
    """
    base = np.asarray(base, dtype=float)
    dh = np.array(true_dh, dtype=float)
    held = np.asarray(held_dh, dtype=float)
    cam = np.array(true_camera, dtype=float)
    mk = np.array(true_marker, dtype=float)
    if camera:
        # C^-1 B Rz(o) Tz(d) = C'^-1 B Rz(o') Tz(d')  =>  C' = B G^-1 B^-1 C, G = Rz(o - o') Tz(d - d').
        g = _rz_tz(dh[0, 3] - held[0, 3], dh[0, 1] - held[0, 1])
        cam = base @ np.linalg.inv(g) @ np.linalg.inv(base) @ cam
        dh[0, 1], dh[0, 3] = held[0, 1], held[0, 3]
    if marker:
        # K(row) M = K(row') M', K = everything of the last link after its joint's rotation.
        def fixed(row: NDArray[np.float64]) -> NDArray[np.float64]:
            return kinematics.dh_link_transforms(row[None], np.zeros((1, 1)))[0, 0]
        mk = np.linalg.inv(fixed(held[-1])) @ fixed(dh[-1]) @ mk
        dh[-1] = held[-1]
    return dh, cam, mk


def static_transform(pose: ArrayLike, frame_id: str, child_frame_id: str) -> dict[str, object]:
    """A pose as the arguments of tf2_ros ``static_transform_publisher`` (x y z qx qy qz qw)."""
    pose = np.asarray(pose, dtype=float)
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()
    values = [float(v) for v in np.concatenate([pose[:3, 3], q])]
    keys = ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')
    return {**dict(zip(keys, values)), 'frame_id': frame_id, 'child_frame_id': child_frame_id,
            'arguments': ' '.join(f'--{k} {v:.6f}' for k, v in zip(keys, values))
            + f' --frame-id {frame_id} --child-frame-id {child_frame_id}'}
