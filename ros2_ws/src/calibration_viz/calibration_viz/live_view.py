"""The live 3D view: a viser server that draws a :class:`~calibration_viz.scene.SceneState`.

No rclpy. viser serves its own web client (bundled in the wheel: no internet, no account) at
``http://<host>:<port>`` and pushes scene updates over a WebSocket; any browser that opens the
URL sees the real arm (dark grey), the estimate (orange) converging onto it, both cameras as frustums
with their latest image, the observed hand poses with their 3-sigma position ellipsoids, and the
error curve of the estimates so far. Scene node names (what a client receives):

``/real_arm``, ``/estimated_arm``
    Polylines through the joint origins (line segments) and the joints (points).
``/cameras/<eye>``
    Camera frustums (OpenCV optical frame, as ``/camera/<eye>/pose``) with the image.
``/observations``
    One ellipsoid per observed hand position (batched meshes).
``/obstacles/<name>``
    The description's static bodies (the collision check's obstacles), half transparent.
"""
from __future__ import annotations

import numpy as np
import viser
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .scene import SceneState, covariance_ellipsoid

__all__ = ['REAL_RGB', 'ESTIMATE_RGB', 'LiveView']

REAL_RGB = (70, 70, 80)      # dark on the client's light background
ESTIMATE_RGB = (255, 140, 25)
_OBSERVATION_RGB = (60, 170, 255)


def _wxyz(t: NDArray[np.float64]) -> NDArray[np.float64]:
    x, y, z, w = Rotation.from_matrix(t[:3, :3]).as_quat()
    return np.array([w, x, y, z])


def _unit_sphere(subdivisions: int = 2) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    import trimesh   # a viser dependency

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(s.vertices, dtype=np.float32), np.asarray(s.faces, dtype=np.int32)


class LiveView:
    """A viser server showing a calibration.

    Parameters
    ----------
    host : str
        Interface to listen on (``127.0.0.1``: this machine only).
    port : int
        HTTP and WebSocket port.
    camera_position, look_at : tuple of 3 floats
        Where the browser's camera starts [m, root frame].
    """

    def __init__(self, host: str = '127.0.0.1', port: int = 8080, *,
                 camera_position: tuple[float, float, float] = (-0.6, 0.5, 0.2),
                 look_at: tuple[float, float, float] = (-0.05, 0.15, -0.05)) -> None:
        self.server = viser.ViserServer(host=host, port=port, label='body schema calibration', verbose=False)
        self.server.initial_camera.position = camera_position
        self.server.initial_camera.look_at = look_at
        self.server.initial_camera.up = (0.0, 0.0, 1.0)   # root_link: z up
        self.server.scene.set_up_direction('+z')
        self.server.scene.add_grid('/grid', width=1.0, height=1.0, cell_size=0.1, position=(0.0, 0.0, -0.3))
        self._sphere = _unit_sphere()
        self._uplot = None
        self._drawn_version = -1
        self._image_versions: dict[str, int] = {}
        self.status = self.server.gui.add_markdown('waiting for the graph ...')

    @property
    def url(self) -> str:
        """Where a browser opens the view."""
        return f'http://{self.server.get_host()}:{self.server.get_port()}'

    def draw(self, state: SceneState, *, images: bool = True) -> bool:
        """Push what changed since the last draw; False if nothing had.

        Parameters
        ----------
        state : SceneState
        images : bool
            Also send camera images (the costly part: JPEG over the socket).
        """
        if state.version == self._drawn_version:
            return False
        self._drawn_version = state.version
        scene = self.server.scene
        for name, points, rgb in (('/real_arm', state.real_arm(), REAL_RGB),
                                  ('/estimated_arm', state.estimated_arm(), ESTIMATE_RGB)):
            if points is None:
                continue
            segments = np.stack([points[:-1], points[1:]], axis=1)
            scene.add_line_segments(f'{name}/links', segments, colors=rgb, thickness=6.0, thickness_units='screen')
            scene.add_point_cloud(f'{name}/joints', points, colors=rgb, point_size=0.012, point_shape='circle')
        for eye, cam in sorted(state.cameras.items()):
            if cam.root_T_optical is None or cam.intrinsics is None:
                continue
            k = cam.intrinsics
            image = cam.image if images else None
            scene.add_camera_frustum(f'/cameras/{eye}', fov=2.0 * np.arctan2(k.height / 2.0, k.fy),
                                     aspect=k.width / k.height, scale=0.06, thickness=0.002, image=image, format='jpeg',
                                     jpeg_quality=70, wxyz=_wxyz(cam.root_T_optical),
                                     position=cam.root_T_optical[:3, 3], color=(80, 80, 200))
        if state.observations:
            self._draw_observations(state)
        self._draw_errors(state)
        return True

    def _draw_observations(self, state: SceneState) -> None:
        axes = [covariance_ellipsoid(o.covariance) for o in state.observations]
        # A floor on the radius keeps a near-certain observation visible.
        scales = np.array([np.maximum(r, 0.003) for r, _ in axes])
        wxyz = np.array([_wxyz(np.block([[v, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
                         for _, v in axes])
        positions = np.array([o.root_T_hand[:3, 3] for o in state.observations])
        self.server.scene.add_batched_meshes_simple(
            '/observations', self._sphere[0], self._sphere[1], batched_wxyzs=wxyz, batched_positions=positions,
            batched_scales=scales, batched_colors=_OBSERVATION_RGB, opacity=0.5)

    def _draw_errors(self, state: SceneState) -> None:
        pos, rot = state.errors.position_mm, state.errors.orientation_deg
        if not pos:
            return
        x = np.arange(len(pos), dtype=float)
        data = (x, np.asarray(pos), np.asarray(rot))
        self.status.content = (f'**estimate {len(pos) - 1}**: hand position error {pos[-1]:.2f} mm, '
                               f'orientation {rot[-1]:.2f} deg ({pos[0]:.1f} mm / {rot[0]:.1f} deg at the start)')
        if self._uplot is None:
            self._uplot = self.server.gui.add_uplot(
                data, ({'label': 'estimate'}, {'label': 'position [mm]', 'stroke': 'orange', 'width': 2},
                       {'label': 'orientation [deg]', 'stroke': 'steelblue', 'width': 2}),
                title='error vs estimate', aspect=1.6, scales={'x': {'time': False}})
        else:
            self._uplot.data = data

    def add_obstacles(self, meshes: list) -> None:
        """Draw the static bodies once: ``(name, vertices, faces, rgb)`` (:func:`calibration_viz.plan_view.obstacle_meshes`)."""
        for name, vertices, faces, rgb in meshes:
            self.server.scene.add_mesh_simple(f'/obstacles/{name}', vertices, faces, color=rgb, opacity=0.5)

    def stop(self) -> None:
        """Close the server (idempotent)."""
        self.server.stop()
