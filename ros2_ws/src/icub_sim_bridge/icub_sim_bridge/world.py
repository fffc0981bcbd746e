"""The PyBullet world: an arm built from a DH table, an ArUco-marked hand, its cameras.

Pure module (no rclpy). :class:`SimWorld` owns one ``BulletClient`` in DIRECT mode, so several
worlds coexist in one process. The arm follows the DH table it is given (the nominal
description's, or a "real robot" that differs from it):

* a description read from a URDF (``urdf:``) is that URDF, meshes and all, with its joint origins
  corrected to the table (:func:`body_schema.urdf_model.calibrated_urdf`: the "real" robot is the
  URDF with its joint origins perturbed); the links beyond the tip (a gripper) stay as written,
  their joints at 0;
* any other description is generated as URDF by :mod:`body_schema.urdf` with geometry that looks
  like an iCub arm (:mod:`body_schema.arm_visuals`): upper arm, forearm and a 7 x 5.5 x 2.5 cm hand.

Either way a link ``hand`` (the DH frame after the last joint) carries ArUco markers (textured
quads with a white quiet zone) exactly where the robot description's ``hand_markers`` says they
are, and the description's obstacles, scenery and head are drawn around it.

The arm is kinematic: :meth:`SimWorld.set_joint_positions` places it exactly, :meth:`SimWorld.step`
advances the (gravity-free) physics by one fixed step. :meth:`SimWorld.render` draws an image
with TinyRenderer for any camera pose and intrinsics; the image obeys the pinhole model ``K``
exactly (see :mod:`icub_sim_bridge.camera`).
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pybullet as p
from numpy.typing import ArrayLike, NDArray
from pybullet_utils import bullet_client

from body_schema.arm_visuals import HAND_SIZE, WHITE, arm_visuals, head_box, palm_size, quad_side, static_bodies
from body_schema.markers import aruco_dictionary, marker_corners
from body_schema.robot import ArmModel, CameraIntrinsics, MarkerPlacement
from body_schema.urdf import FixedLink, Visual, dh_chain_urdf

from . import camera as cam
from .urdf_arm import load_arm_urdf, pose_matrix, write_arm_urdf

__all__ = ['HAND_SIZE', 'MarkerSpec', 'SimWorld', 'marker_texture']


def _grid_obj(n: int) -> str:
    """Unit square in z = 0 (normal +z) as an n x n grid; uv (0, 0) at (-0.5, -0.5).

    TinyRenderer's texture mapping is perspective-correct (a 16 x 16 grid measured the same corner
    errors as one quad), so one quad (n = 1) is enough.
    """
    t = np.linspace(0.0, 1.0, n + 1)
    lines = ['# unit square grid, normal +z']
    lines += [f'v {x - 0.5:.6f} {y - 0.5:.6f} 0' for y in t for x in t]
    lines += [f'vt {x:.6f} {y:.6f}' for y in t for x in t]
    lines.append('vn 0 0 1')
    for j in range(n):
        for i in range(n):
            a, b = j * (n + 1) + i + 1, j * (n + 1) + i + 2
            c, d = b + n + 1, a + n + 1
            lines += [f'f {a}/{a}/1 {b}/{b}/1 {c}/{c}/1', f'f {a}/{a}/1 {c}/{c}/1 {d}/{d}/1']
    return '\n'.join(lines) + '\n'


#: Grid resolution of the marker quads (see :func:`_grid_obj`).
MARKER_GRID = 1


def marker_texture(dictionary: str, marker_id: int, cell_px: int = 24,
                   quiet_cells: int = 1) -> NDArray[np.uint8]:
    """Printed marker image: the ArUco square with a white quiet zone around it.

    Parameters
    ----------
    dictionary : str
        cv2.aruco dictionary name.
    marker_id : int
    cell_px : int
        Pixels per marker cell.
    quiet_cells : int
        Width of the white margin [cells].

    Returns
    -------
    ndarray, shape (S, S), uint8
        ``S = (bits + 2 + 2 quiet_cells) cell_px``; row 0 is the top of the printed marker.
    """
    import cv2

    d = aruco_dictionary(dictionary)
    n_markers = d.bytesList.shape[0]
    if not 0 <= marker_id < n_markers:
        raise ValueError(f'marker id {marker_id} not in {dictionary} (0..{n_markers - 1})')
    cells = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, int(marker_id), cells * cell_px, borderBits=1)
    pad = quiet_cells * cell_px
    return np.pad(img, pad, constant_values=255)


@dataclass(frozen=True)
class MarkerSpec:
    """A marker as the world draws it: placement, id, dictionary, black-square side [m]."""

    placement: MarkerPlacement
    dictionary: str
    side_length: float
    quiet_cells: int = 1

    @property
    def quad_side(self) -> float:
        """Side of the printed quad including the quiet zone [m]."""
        return quad_side(self.dictionary, self.side_length, self.quiet_cells)

    def corners_in_marker(self) -> NDArray[np.float64]:
        """The black square's corners in ArUco order (TL, TR, BR, BL), shape (4, 3)."""
        return marker_corners(self.side_length)


#: Views whose latest image :meth:`SimWorld.render` keeps (the node renders one per eye).
_CACHED_VIEWS = 4


class SimWorld:
    """A PyBullet world with the arm, its marked hand and the static torso and head.

    Parameters
    ----------
    robot : ArmModel
        Robot description (base, limits, joint names, marker placements, eyes).
    dh : array_like, shape (L, 4), optional
        The simulated robot's real DH table; the description's nominal table if omitted.
    marker_dictionary : str, optional
        Overrides the description's dictionary.
    marker_ids : sequence of int, optional
        Overrides the ids of the description's markers (same count and order).
    marker_side_length : float, optional
        Overrides the black square's side [m].
    head_pose : array_like, shape (5,), optional
        Head joints [rad] used to place the (static) head geometry.
    physics_step : float
        Fixed physics time step [s].

    Attributes
    ----------
    renders : int
        Images rendered so far (a supersampled one counts once; one served from the cache does
        not count).
    render_seconds : float
        Wall seconds spent rendering them: a timing hook for benchmarks and experiments.

    Notes
    -----
    The arm is kinematic and the scene holds no other moving body, so an image depends only on
    the joint positions, the table, the head and the camera: :meth:`render` keeps the latest
    image of each camera and returns it again while none of these has changed (a camera
    watching an arm at rest renders once, not at every frame).
    """

    def __init__(self, robot: ArmModel, dh: ArrayLike | None = None, *,
                 marker_dictionary: str | None = None, marker_ids: Sequence[int] | None = None,
                 marker_side_length: float | None = None, head_pose: ArrayLike | None = None,
                 physics_step: float = 0.005) -> None:
        self.robot = robot
        self.dh = np.array(robot.dh if dh is None else dh, dtype=float)
        if self.dh.shape != robot.dh.shape or not np.all(np.isfinite(self.dh)):
            raise ValueError(f'dh must be a finite table of shape {robot.dh.shape}, got {self.dh.tolist()}')
        if not robot.markers:
            raise ValueError(f'robot {robot.name!r} has no hand_markers; the world needs at least one')
        if not (np.isfinite(physics_step) and physics_step > 0):
            raise ValueError(f'physics_step must be > 0 s, got {physics_step}')
        dictionary = marker_dictionary or robot.marker_dictionary
        side = robot.marker_side_length if marker_side_length is None else float(marker_side_length)
        if not 0 < side <= 0.5:
            raise ValueError(f'marker side length must be in (0, 0.5] m, got {side}')
        ids = [m.marker_id for m in robot.markers] if marker_ids is None else [int(i) for i in marker_ids]
        if len(ids) != len(robot.markers) or len(set(ids)) != len(ids):
            raise ValueError(f'marker_ids must be {len(robot.markers)} distinct ids, got {ids}')
        self.markers = tuple(
            MarkerSpec(MarkerPlacement(m.name, i, m.hand_T_marker), dictionary, side)
            for m, i in zip(robot.markers, ids))
        # The palm is the plate the markers are printed on: it grows to hold them (the iCub's
        # fit its 7 x 5.5 cm palm; a 10 cm target on a flange makes it 10 cm wide).
        self.palm = palm_size([s.placement for s in self.markers], self.markers[0].quad_side)
        self.physics_step = float(physics_step)
        self.head_pose: NDArray[np.float64] | None = None
        self.renders = 0
        self.render_seconds = 0.0
        self._q_set: NDArray[np.float64] | None = None     # joint positions last placed
        self._images: dict[tuple, NDArray[np.uint8]] = {}  # latest image per camera and view
        self._urdf = None
        if robot.urdf is not None:
            from body_schema.urdf_model import model_chain

            self._urdf = model_chain(robot)     # read once: set_dh rewrites it
        self._tmp = tempfile.mkdtemp(prefix='icub_sim_')
        self._client = bullet_client.BulletClient(connection_mode=p.DIRECT)
        try:
            self._build(head_pose)
        except Exception:
            self.close()
            raise

    # ----------------------------------------------------------------------------------------
    # Construction

    def _build(self, head_pose: ArrayLike | None) -> None:
        c = self._client
        c.setGravity(0, 0, 0)
        c.setPhysicsEngineParameter(fixedTimeStep=self.physics_step)
        quad = os.path.join(self._tmp, 'marker_quad.obj')
        with open(quad, 'w') as f:
            f.write(_grid_obj(MARKER_GRID))
        names = self.robot.joint_names
        extra = []
        for spec in self.markers:
            s = spec.quad_side
            extra.append(FixedLink(f'marker_{spec.placement.name}', 'hand', spec.placement.hand_T_marker,
                                   (Visual('mesh', (s, s, 1.0), filename=quad, rgba=(1, 1, 1, 1)),)))
        # A new file name per build: PyBullet caches what it loaded under a file name, so a rebuilt
        # arm (set_dh) under the old name would come back with the old geometry.
        self._builds = getattr(self, '_builds', 0) + 1
        path = os.path.join(self._tmp, f'arm_{self._builds}.urdf')
        if self._urdf is None:
            visuals = arm_visuals(self.dh, names, palm=self.palm)
            urdf = dh_chain_urdf(self.dh, names, self.robot.limits, base=self.robot.base,
                                 name=self.robot.name, root_link=self.robot.root_frame,
                                 visuals=visuals, extra_links=extra, link_mass=0.01)
            with open(path, 'w') as f:
                f.write(urdf)
            self.body = c.loadURDF(path, useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE)
        else:
            write_arm_urdf(self.robot, *self._urdf, self.dh, path, extra)
            self.body = load_arm_urdf(c, path, self.robot, self._urdf[1])
        self._joint_index: dict[str, int] = {}
        self._link_index: dict[str, int] = {self.robot.root_frame: -1}
        for i in range(c.getNumJoints(self.body)):
            info = c.getJointInfo(self.body, i)
            self._joint_index[info[1].decode()] = i
            self._link_index[info[12].decode()] = i
        self._arm_joints = [self._joint_index[j] for j in names]
        for spec in self.markers:
            img = marker_texture(spec.dictionary, spec.placement.marker_id, quiet_cells=spec.quiet_cells)
            png = os.path.join(self._tmp, f'marker_{spec.placement.marker_id}.png')
            import cv2

            # With the quad's uv (0, 0) at marker (-x, -y), TinyRenderer shows image row 0 at
            # marker +y: the printed marker is upright (x right, y up), as ArUco's corner order needs.
            cv2.imwrite(png, img)
            tex = c.loadTexture(png)
            c.changeVisualShape(self.body, self._link_index[f'marker_{spec.placement.name}'], -1,
                                textureUniqueId=tex, rgbaColor=[1, 1, 1, 1])
        self._images.clear()
        self._q_set = None
        self._build_context(head_pose)
        self.set_joint_positions(np.clip(np.zeros(len(names)), self.robot.limits[:, 0], self.robot.limits[:, 1]))

    def _build_context(self, head_pose: ArrayLike | None) -> None:
        """The description's obstacles and scenery (e.g. a torso, a table) and, for eyes, a head behind them."""
        from .contacts import create_static_body

        # No floor: TinyRenderer's cost grows with covered pixels and a floor filling the view
        # halved the frame rate; the light background suits the markers anyway.
        for body in static_bodies(self.robot):
            if body.name != 'head':
                create_static_body(self._client, body, visual=True, collision=False)
        self._head = None
        if self.robot.eyes is not None and 'left' in self.robot.eyes.links:
            self.set_head_pose(self.robot.eyes.head_pose if head_pose is None else head_pose)

    def set_dh(self, dh: ArrayLike) -> None:
        """Rebuild the arm with another DH table (a body that changed), keeping its joint positions.

        Parameters
        ----------
        dh : array_like, shape (L, 4)
            The new real table.
        """
        dh = np.array(dh, dtype=float)
        if dh.shape != self.robot.dh.shape or not np.all(np.isfinite(dh)):
            raise ValueError(f'dh must be a finite table of shape {self.robot.dh.shape}, got {dh.tolist()}')
        q = self.joint_positions()
        self._client.resetSimulation()
        self.dh = dh
        self._build(self.head_pose)
        self.set_joint_positions(q)

    def set_head_pose(self, head_pose: ArrayLike) -> None:
        """Place the static head geometry for head joints ``head_pose`` (5,) [rad]."""
        self.head_pose = np.array(head_pose, dtype=float)
        self._images.clear()
        c = self._client
        # A 12 x 10 x 10 cm skull just behind the eyes (never in front: the cameras sit there).
        head = head_box(self.robot, head_pose)
        centre, quat = head.pose[:3, 3], _quat_xyzw(head.pose[:3, :3])
        if self._head is None:
            vs = c.createVisualShape(p.GEOM_BOX, halfExtents=[s / 2 for s in head.size], rgbaColor=WHITE)
            self._head = c.createMultiBody(0, -1, vs, basePosition=centre, baseOrientation=quat)
        else:
            c.resetBasePositionAndOrientation(self._head, centre, quat)

    # ----------------------------------------------------------------------------------------
    # State

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.robot.joint_names

    def set_joint_positions(self, q: ArrayLike) -> None:
        """Place the arm at ``q`` (L,) [rad] exactly (kinematic arm)."""
        q = np.asarray(q, dtype=float)
        if q.shape != (len(self._arm_joints),) or not np.all(np.isfinite(q)):
            raise ValueError(f'joint positions must be {len(self._arm_joints)} finite values, got {q!r}')
        if self._q_set is not None and np.array_equal(q, self._q_set):
            return
        self._q_set = q.copy()
        self._images.clear()
        for idx, v in zip(self._arm_joints, q):
            self._client.resetJointState(self.body, idx, float(v), 0.0)

    def joint_positions(self) -> NDArray[np.float64]:
        """Present joint positions, shape (L,) [rad]."""
        return np.array([s[0] for s in self._client.getJointStates(self.body, self._arm_joints)])

    def step(self) -> None:
        """Advance the physics by one fixed step (gravity-free; the arm stays where it was put)."""
        self._client.stepSimulation()

    def link_pose(self, link: str) -> NDArray[np.float64]:
        """Pose of a URDF link frame in root_link, shape (4, 4)."""
        if link not in self._link_index:
            raise KeyError(f'unknown link {link!r}')
        idx = self._link_index[link]
        if idx < 0:
            return np.eye(4)
        st = self._client.getLinkState(self.body, idx, computeForwardKinematics=True)
        return pose_matrix(self._client, st[4], st[5])

    def hand_pose(self) -> NDArray[np.float64]:
        """Hand frame in root_link, shape (4, 4)."""
        return self.link_pose('hand')

    def marker_corners(self) -> dict[int, NDArray[np.float64]]:
        """Black-square corners of each marker in root_link, ArUco order; id -> (4, 3)."""
        hand = self.hand_pose()
        out = {}
        for spec in self.markers:
            t = hand @ spec.placement.hand_T_marker
            out[spec.placement.marker_id] = spec.corners_in_marker() @ t[:3, :3].T + t[:3, 3]
        return out

    # ----------------------------------------------------------------------------------------
    # Cameras

    def render(self, root_T_cam: ArrayLike, intrinsics: CameraIntrinsics, near: float = 0.01,
               far: float = 20.0, supersample: int = 1) -> NDArray[np.uint8]:
        """Render an RGB image with TinyRenderer.

        Parameters
        ----------
        root_T_cam : array_like, shape (4, 4)
            Optical frame (z forward, x right, y down) in root_link.
        intrinsics : CameraIntrinsics
        near, far : float
            Clipping distances [m].
        supersample : int
            Anti-aliasing: render ``supersample`` times larger (same field of view, pixel centres
            kept) and average down. TinyRenderer does not anti-alias, so edges in a plain render
            are only located to half a pixel; 2 brings corner errors under 0.5 px at 4x the cost.

        Returns
        -------
        ndarray, shape (H, W, 3), uint8, C-contiguous, read-only
            The same array as the previous call's if nothing in the scene or the view changed.
        """
        view = np.asarray(root_T_cam, dtype=float)
        key = (view.tobytes(), intrinsics.K.tobytes(), intrinsics.width, intrinsics.height, near, far, supersample)
        image = self._images.get(key)
        if image is not None:
            return image
        t0 = time.perf_counter()
        try:
            image = self._render(view, intrinsics, near, far, supersample)
        finally:
            self.renders += 1
            self.render_seconds += time.perf_counter() - t0
        image.setflags(write=False)
        if len(self._images) >= _CACHED_VIEWS:    # many views of one scene (a study): keep it small
            self._images.clear()
        self._images[key] = image
        return image

    def _render(self, root_T_cam: ArrayLike, intrinsics: CameraIntrinsics, near: float, far: float,
                supersample: int) -> NDArray[np.uint8]:
        if supersample != 1:
            if int(supersample) != supersample or supersample < 1:
                raise ValueError(f'supersample must be a positive integer, got {supersample}')
            import cv2

            s = int(supersample)
            big = self._render(root_T_cam, intrinsics.scaled(intrinsics.width * s, intrinsics.height * s),
                               near, far, 1)
            return cv2.resize(big, (intrinsics.width, intrinsics.height), interpolation=cv2.INTER_AREA)
        w, h = intrinsics.width, intrinsics.height
        view = cam.to_gl_list(cam.gl_view(root_T_cam))
        proj = cam.to_gl_list(cam.gl_projection(intrinsics.K, w, h, near, far))
        rgba = self._client.getCameraImage(
            w, h, view, proj, renderer=p.ER_TINY_RENDERER, flags=p.ER_NO_SEGMENTATION_MASK,
            shadow=0, lightDirection=[-1.0, 0.3, 1.5], lightAmbientCoeff=0.65,
            lightDiffuseCoeff=0.35, lightSpecularCoeff=0.0)[2]
        import cv2

        # cv2 drops the alpha channel into a contiguous array faster than a numpy strided copy.
        return cv2.cvtColor(np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4), cv2.COLOR_RGBA2RGB)

    # ----------------------------------------------------------------------------------------

    def close(self) -> None:
        """Disconnect from PyBullet and remove the generated files."""
        if getattr(self, '_client', None) is not None:
            try:
                self._client.disconnect()
            except p.error:
                pass
            self._client = None
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> 'SimWorld':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 (interpreter shutdown)
            pass


def _quat_xyzw(r: NDArray[np.float64]) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_quat().tolist()
