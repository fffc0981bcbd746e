"""A planned pose list in the browser, with the obstacles, before anything moves (viser; no rclpy).

``python -m calibration_viz.plan_view PLAN.yaml --robot R`` (or ``run_calibration.sh --plan-only
--viz``, ``python -m calibration_bringup.plan --viz``) serves ``http://127.0.0.1:<port>``: the
description's static bodies (:func:`obstacle_meshes`, also drawn by the live view), every planned
pose as a faint polyline through the joint origins, the flange's path along the straight
joint-space motions from the start through the poses in order, and a slider that shows one pose
(with the motion to it) in full colour. What is drawn is computed by :func:`plan_geometry`
(pure), so it is tested without a browser.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema.arm_visuals import static_bodies
from body_schema.kinematics import chain_frames
from body_schema.robot import ArmModel, load_robot

__all__ = ['obstacle_meshes', 'PlanGeometry', 'plan_geometry', 'serve', 'main']


def obstacle_meshes(model: ArmModel) -> list[tuple[str, NDArray[np.float32], NDArray[np.int32], tuple[int, int, int]]]:
    """Every static body as a triangle mesh in the root frame: ``(name, vertices (V, 3), faces (F, 3), rgb)``."""
    import trimesh   # a viser dependency

    out = []
    for o in static_bodies(model):
        if o.shape == 'box':
            mesh = trimesh.creation.box(extents=o.size)
        elif o.shape == 'cylinder':
            mesh = trimesh.creation.cylinder(radius=o.size[0], height=o.size[1], sections=24)
        else:
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=o.size[0])
        mesh.apply_transform(o.pose)
        rgb = tuple(int(round(255 * c)) for c in o.rgba[:3])
        out.append((o.name, np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int32), rgb))
    return out


@dataclass(frozen=True)
class PlanGeometry:
    """What the plan view draws.

    Attributes
    ----------
    arms : ndarray, shape (N, L + 2, 3)
        Per pose, the polyline root, base, joint origins, hand [m].
    flange_path : ndarray, shape (N, S, 3)
        Per pose, the flange's positions along the straight joint-space motion to it from the
        previous pose (the first from the start), ``S`` samples.
    """

    arms: NDArray[np.float64]
    flange_path: NDArray[np.float64]


def plan_geometry(model: ArmModel, poses: ArrayLike, start: ArrayLike, samples: int = 20) -> PlanGeometry:
    """Polylines of the arm (the description's table) at each pose and of the flange between them.

    Parameters
    ----------
    model : ArmModel
    poses : array_like, shape (N, L)
    start : array_like, shape (L,)
    samples : int
    """
    q = np.atleast_2d(np.asarray(poses, dtype=float))
    frames = chain_frames(model.base, model.dh, q)                                   # (N, L+1, 4, 4)
    arms = np.concatenate([np.zeros((len(q), 1, 3)), frames[:, :, :3, 3]], axis=1)
    prev = np.vstack([np.asarray(start, dtype=float)[None], q[:-1]])
    t = np.linspace(0.0, 1.0, samples)
    path = prev[:, None, :] + t[None, :, None] * (q - prev)[:, None, :]             # (N, S, L)
    flange = model.forward_kinematics(path.reshape(-1, q.shape[1]))[:, :3, 3].reshape(len(q), samples, 3)
    return PlanGeometry(arms, flange)


def serve(model: ArmModel, poses: ArrayLike, start: ArrayLike, *, host: str = '127.0.0.1', port: int = 8080,
          block: bool = True) -> 'object':
    """Serve the plan view; with ``block`` until Ctrl-C (returns the viser server otherwise)."""
    import viser

    geo = plan_geometry(model, poses, start)
    server = viser.ViserServer(host=host, port=port, label=f'plan: {model.name}', verbose=False)
    server.scene.set_up_direction('+z')
    for name, vertices, faces, rgb in obstacle_meshes(model):
        server.scene.add_mesh_simple(f'/obstacles/{name}', vertices, faces, color=rgb, opacity=0.6)
    ghosts = np.concatenate([np.stack([a[:-1], a[1:]], axis=1) for a in geo.arms])
    server.scene.add_line_segments('/poses', ghosts, colors=(170, 170, 180), thickness=2.0, thickness_units='screen')
    path = geo.flange_path.reshape(-1, 3)
    server.scene.add_line_segments('/flange_path', np.stack([path[:-1], path[1:]], axis=1), colors=(60, 170, 255),
                                   thickness=2.0, thickness_units='screen')
    slider = server.gui.add_slider('pose', min=1, max=len(geo.arms), step=1, initial_value=1)
    text = server.gui.add_markdown('')

    def show(_event: object = None) -> None:
        k = int(slider.value) - 1
        arm = geo.arms[k]
        server.scene.add_line_segments('/selected/arm', np.stack([arm[:-1], arm[1:]], axis=1), colors=(255, 140, 25),
                                       thickness=6.0, thickness_units='screen')
        seg = geo.flange_path[k]
        server.scene.add_line_segments('/selected/path', np.stack([seg[:-1], seg[1:]], axis=1), colors=(255, 60, 60),
                                       thickness=5.0, thickness_units='screen')
        text.content = f'**pose {k + 1} of {len(geo.arms)}**: ' + ' '.join(
            f'{v:.1f}' for v in np.degrees(np.atleast_2d(poses)[k])) + ' deg'

    slider.on_update(show)
    show()
    if not block:
        return server
    print(f'plan view at http://{server.get_host()}:{server.get_port()} (Ctrl-C to stop)', flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return server


def main(argv: list[str] | None = None) -> int:
    from calibration_interfaces.pose_list import read_pose_list

    ap = argparse.ArgumentParser(prog='python -m calibration_viz.plan_view', description=__doc__.split('\n\n')[0])
    ap.add_argument('poses', help='a pose list (calibration_interfaces.pose_list)')
    ap.add_argument('--robot', default='icub_right_arm')
    ap.add_argument('--start-deg', type=float, nargs='+', help='where the arm starts [deg] (default: the box centre)')
    ap.add_argument('--port', type=int, default=8080)
    args = ap.parse_args(argv)
    model = load_robot(args.robot)
    poses = read_pose_list(args.poses, model).positions
    start = np.radians(args.start_deg) if args.start_deg else model.calibration_box.mean(axis=1)
    serve(model, poses, start, port=args.port)
    return 0


if __name__ == '__main__':
    sys.exit(main())
