"""Measure how often the hand's markers are detected in a camera over a joint box.

This is how the default head pose and calibration box of the robot descriptions were chosen
(the iCub's eye, the UR5e's fixed camera): for uniform random configurations of the box, render
the camera image, run
``cv2.aruco.ArucoDetector`` and count the configurations where at least one of the hand's markers
is detected. Usage::

    python -m icub_sim_bridge.visibility [--n 400] [--seed 0] [--eye left]
        [--head DEG DEG DEG DEG DEG] [--box-deg lo hi lo hi ...] [--width 320 --height 240]
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from body_schema.markers import aruco_dictionary
from body_schema.robot import ArmModel, CameraIntrinsics, load_robot
from body_schema.sampling import uniform_configs

from .world import SimWorld

__all__ = ['VisibilityResult', 'measure_visibility', 'main']


@dataclass(frozen=True)
class VisibilityResult:
    """Outcome of a visibility measurement.

    Attributes
    ----------
    configs : ndarray, shape (N, L)
        The sampled joint configurations [rad].
    detected : ndarray, shape (N, M), bool
        Whether marker m (in the world's marker order) was detected at configuration n.
    marker_ids : tuple of int, length M
    """

    configs: NDArray[np.float64]
    detected: NDArray[np.bool_]
    marker_ids: tuple[int, ...]

    @property
    def fraction(self) -> float:
        """Fraction of configurations with at least one marker detected."""
        return float(np.mean(np.any(self.detected, axis=1)))

    @property
    def per_marker(self) -> NDArray[np.float64]:
        """Detection fraction of each marker, shape (M,)."""
        return self.detected.mean(axis=0)

    def stderr(self) -> float:
        """Binomial standard error of :attr:`fraction`."""
        f = self.fraction
        return float(np.sqrt(f * (1 - f) / max(len(self.configs), 1)))


def measure_visibility(robot: ArmModel, n: int = 400, seed: int = 0, *, eye: str = 'left',
                       head_pose: ArrayLike | None = None, box: ArrayLike | None = None,
                       intrinsics: CameraIntrinsics | None = None,
                       world: SimWorld | None = None) -> VisibilityResult:
    """Render ``n`` uniform configurations of ``box`` and detect the markers in one eye.

    Parameters
    ----------
    robot : ArmModel
    n : int
        Number of configurations.
    seed : int
        Seed of the configuration draw.
    eye : str
        A camera of the description (an eye, or a fixed camera).
    head_pose : array_like, shape (5,), optional
        Head joints [rad]; the description's ``head_pose`` if omitted.
    box : array_like, shape (L, 2), optional
        Joint box [rad]; the description's ``calibration_box`` if omitted.
    intrinsics : CameraIntrinsics, optional
        The description's camera if omitted.
    world : SimWorld, optional
        Reuse a world (its DH table is used); a nominal one is built (and closed) otherwise.

    Returns
    -------
    VisibilityResult
    """
    import cv2

    box = robot.calibration_box if box is None else np.asarray(box, dtype=float)
    intr = intrinsics or robot.camera
    if intr is None:
        raise ValueError(f'robot {robot.name!r} has no camera section; pass intrinsics')
    pose = robot.camera_pose(eye, head_pose)
    own = world is None
    w = SimWorld(robot, head_pose=head_pose) if own else world
    try:
        if not own and head_pose is not None:
            w.set_head_pose(head_pose)
        ids = tuple(m.placement.marker_id for m in w.markers)
        det = cv2.aruco.ArucoDetector(aruco_dictionary(w.markers[0].dictionary),
                                      cv2.aruco.DetectorParameters())
        qs = uniform_configs(box, n, seed)
        detected = np.zeros((n, len(ids)), dtype=bool)
        for k, q in enumerate(qs):
            w.set_joint_positions(q)
            _corners, found, _rej = det.detectMarkers(w.render(pose, intr))
            if found is not None:
                detected[k] = np.isin(ids, found.ravel())
    finally:
        if own:
            w.close()
    return VisibilityResult(qs, detected, ids)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', default='icub_right_arm', help='robot description name or path')
    ap.add_argument('--n', type=int, default=400, help='number of configurations')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--eye', default='left', help="camera name: an eye or a fixed camera of the description")
    ap.add_argument('--head', type=float, nargs=5, metavar='DEG', help='head joints [deg]')
    ap.add_argument('--box-deg', type=float, nargs='+', metavar='DEG',
                    help='joint box as lo hi pairs [deg], one pair per joint')
    ap.add_argument('--width', type=int, help='image width (scales the description intrinsics)')
    ap.add_argument('--height', type=int)
    args = ap.parse_args(argv)
    robot = load_robot(args.robot)
    head = None if args.head is None else np.radians(args.head)
    box = None if args.box_deg is None else np.radians(np.reshape(args.box_deg, (-1, 2)))
    intr = robot.camera
    if args.width and args.height:
        intr = intr.scaled(args.width, args.height)
    t0 = time.perf_counter()
    res = measure_visibility(robot, args.n, args.seed, eye=args.eye, head_pose=head, box=box,
                             intrinsics=intr)
    dt = time.perf_counter() - t0
    names = ', '.join(f'id {i}: {100 * f:.1f}%' for i, f in zip(res.marker_ids, res.per_marker))
    print(f'camera {args.eye}, {args.n} configurations (seed {args.seed}), {intr.width}x{intr.height}: '
          f'at least one marker detected in {100 * res.fraction:.1f}% (+- {100 * res.stderr():.1f}); '
          f'per marker {names}; {dt:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
