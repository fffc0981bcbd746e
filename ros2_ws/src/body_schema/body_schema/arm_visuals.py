"""How the arm looks: URDF geometry of a DH chain (the simulator's arm and the published models).

Pure module. The simulator renders this geometry and ``/robot_description`` and
``/body_schema/robot_description`` carry it, so a 3D view (Foxglove, RViz) draws the same arm the
cameras see: a cylinder along each DH link, a ball at each joint where the chain has moved on, and
a 7 x 5.5 x 2.5 cm hand (palm, fingers, thumb, wrist) whose palm carries the ArUco markers (a
palm that grows to hold markers larger than it, e.g. a calibration plate on an industrial flange).
"""
from __future__ import annotations

import dataclasses

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from .markers import aruco_dictionary, marker_corners
from .robot import MarkerPlacement, Obstacle
from .urdf import FixedLink, Visual, dh_chain_urdf, xyz_rpy_to_transform

__all__ = ['HAND_SIZE', 'WHITE', 'GREY', 'SKIN', 'LINK_RADIUS', 'HEAD_SIZE', 'segment_visuals', 'hand_visuals',
           'quad_side', 'palm_size', 'arm_visuals', 'model_visuals', 'head_box', 'static_bodies', 'marker_links',
           'marker_plates', 'PLATE_THICKNESS', 'drawn_arm_urdf', 'description_urdf']

#: Palm box extents in the hand frame [m]: x toward the fingers, y across, z palm thickness.
HAND_SIZE = (0.07, 0.055, 0.025)

# Colours: iCub-like white shells over dark grey joints.
WHITE = (0.92, 0.92, 0.9, 1.0)
GREY = (0.35, 0.35, 0.38, 1.0)
SKIN = (0.75, 0.72, 0.68, 1.0)

#: Link radii [m] of the segment each joint's link carries (the segment is drawn in <joint>_link).
LINK_RADIUS = {
    'r_shoulder_pitch': 0.03,   # shoulder girdle, across the chest
    'r_shoulder_roll': 0.03,
    'r_shoulder_yaw': 0.032,    # upper arm
    'r_elbow': 0.028,
    'r_wrist_prosup': 0.026,    # forearm
    'r_wrist_pitch': 0.02,
    'r_wrist_yaw': 0.015,       # drawn by the hand itself
}


#: Shortest DH length [m] drawn as a cylinder. A length that is zero on the nominal arm and a
#: millimetre on the real one is not a link: drawn, it is a coin as wide as the link standing
#: across the joint (on the UR5e's flange, a = 1 mm put a 4 cm disc in front of the marker).
MIN_SEGMENT = 0.005


def segment_visuals(a: float, d: float, radius: float, rgba: tuple, joint_ball: bool = True) -> list[Visual]:
    """Cylinders along the DH link: origin -> (0, 0, d) -> (a, 0, d), in the joint's moving frame.

    ``joint_ball`` adds a sphere at the joint; spheres are the costliest shapes to rasterize, so
    the caller leaves out those hidden in the torso or coinciding with another joint's.
    """
    out = [Visual('sphere', (radius * 1.05,), rgba=GREY)] if joint_ball else []
    if abs(d) > MIN_SEGMENT:
        out.append(Visual('cylinder', (radius, abs(d)), xyz_rpy_to_transform([0, 0, d / 2], [0, 0, 0]), rgba))
    if abs(a) > MIN_SEGMENT:
        out.append(Visual('cylinder', (radius, abs(a)),
                          xyz_rpy_to_transform([a / 2, 0, d], [0, np.pi / 2, 0]), rgba))
    return out


def quad_side(dictionary: str, side: float, quiet_cells: int = 1) -> float:
    """Side of a printed marker with its white quiet zone ``quiet_cells`` cells wide [m]."""
    bits = int(aruco_dictionary(dictionary).markerSize)
    return float(side) * (bits + 2 + 2 * quiet_cells) / (bits + 2)


def palm_size(placements: Sequence[MarkerPlacement], quad: float) -> tuple[float, float, float]:
    """Palm extents that hold every marker's printed quad: :data:`HAND_SIZE`, grown where needed.

    Parameters
    ----------
    placements : sequence of MarkerPlacement
        The markers on the hand.
    quad : float
        Printed side of each marker, quiet zone included [m] (:func:`quad_side`).

    Returns
    -------
    tuple of 3 floats
        ``(x, y, z)`` extents [m], centred on the hand frame's origin; the iCub's palm markers fit
        the 7 x 5.5 cm palm, a 10 cm plate on a flange makes it 10 cm wide (the plate it is printed on).
    """
    half = np.array(HAND_SIZE[:2]) / 2
    corners = np.c_[marker_corners(quad), np.ones(4)]
    for m in placements:
        xy = (np.asarray(m.hand_T_marker, dtype=float) @ corners.T)[:2].T
        half = np.maximum(half, np.abs(xy).max(axis=0))
    return float(2 * half[0]), float(2 * half[1]), HAND_SIZE[2]


def hand_visuals(wrist_a: float, palm_rgba: tuple = WHITE,
                 palm: tuple[float, float, float] = HAND_SIZE) -> list[Visual]:
    """Palm, fingers, thumb and wrist in the hand frame (palm face at z = 0, facing +z).

    ``palm`` is the palm box's extents [m] (:func:`palm_size`); the fingers and thumb keep
    their size and stay at its edges.
    """
    lx, ly, lz = palm
    box = lambda size, xyz, rgba=SKIN: Visual('box', size, xyz_rpy_to_transform(xyz, [0, 0, 0]), rgba)  # noqa: E731
    wrist_len = max(wrist_a - lx / 2, 1e-3)
    return [
        box((lx, ly, lz), (0.0, 0.0, -lz / 2), palm_rgba),                            # palm
        box((0.055, ly * 0.95, 0.014), (lx / 2 + 0.0275, 0.0, -0.011)),               # fingers
        box((0.035, 0.016, 0.014), (-0.005, -ly / 2 - 0.008, -0.012)),                # thumb
        box((wrist_len, 0.04, 0.02), (-lx / 2 - wrist_len / 2, 0.0, -0.014), GREY),   # wrist
    ]


def arm_visuals(dh: ArrayLike, joint_names: Sequence[str], rgba: tuple = WHITE,
                palm: tuple[float, float, float] = HAND_SIZE) -> dict[str, list[Visual]]:
    """Geometry of a DH arm for :func:`body_schema.urdf.dh_chain_urdf`, keyed by link name.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        ``(a, d, alpha, offset)`` per joint [m, m, rad, rad].
    joint_names : sequence of str, length L
    rgba : tuple of 4 floats
        Shell colour (a translucent one draws a ghost, e.g. an estimate over the real arm).
    palm : tuple of 3 floats
        Palm extents [m] (:func:`palm_size`).

    Returns
    -------
    dict of str to list of Visual
        ``<joint>_link`` and ``hand`` (``dh_chain_urdf`` adds its ``prefix``).
    """
    dh = np.asarray(dh, dtype=float)
    # A ball at joint i only where the chain has moved on since the previous ball (not inside
    # the torso at the first joint, not twice at the shoulder's or the wrist's common point).
    lengths = np.hypot(dh[:, 0], dh[:, 1])
    ball = [False] + [bool(lengths[i - 1] > 0.02) for i in range(1, len(joint_names))]
    visuals = {f'{j}_link': segment_visuals(a, d, LINK_RADIUS.get(j, 0.02), rgba, b)
               for j, (a, d, _alpha, _off), b in zip(joint_names, dh, ball)}
    visuals['hand'] = hand_visuals(float(dh[-1, 0]), rgba, palm)
    return visuals


def model_visuals(model: 'ArmModel', dh: ArrayLike | None = None, rgba: tuple = WHITE  # noqa: F821
                  ) -> dict[str, list[Visual]]:
    """:func:`arm_visuals` of a description: its joints, and a palm grown to hold its markers.

    The palm is drawn on the flange, ``model.tool`` from the hand frame (a modified table's flange
    row, a URDF's tip link off the last DH frame), where the markers are.
    """
    dh = model.dh if dh is None else np.asarray(dh, dtype=float)
    tool = np.asarray(model.tool, dtype=float)
    on_flange = [dataclasses.replace(m, hand_T_marker=np.linalg.inv(tool) @ m.hand_T_marker) for m in model.markers]
    palm = palm_size(on_flange, quad_side(model.marker_dictionary, model.marker_side_length)) \
        if model.markers else HAND_SIZE
    visuals = arm_visuals(dh, model.joint_names, rgba, palm)
    if not np.allclose(tool, np.eye(4), atol=1e-12):
        visuals['hand'] = [dataclasses.replace(v, origin=tool @ v.origin) for v in visuals['hand']]
    return visuals


#: Extents [m] of the box drawn as a head behind the eyes (x, y, z in the left eye's optical frame).
HEAD_SIZE = (0.12, 0.10, 0.10)


def head_box(model: 'ArmModel', head_pose: ArrayLike | None = None) -> Obstacle:  # noqa: F821
    """The head behind a robot's eyes: a 12 x 10 x 10 cm box just behind the left eye (never in
    front of it: the cameras sit there), along the eye's optical axes.

    Parameters
    ----------
    model : ArmModel
        A robot with ``eyes`` (and a left eye).
    head_pose : array_like, optional
        Head joints [rad]; the description's ``head_pose`` if omitted.

    Raises
    ------
    ValueError
        If the robot has no left eye.
    """
    if model.eyes is None or 'left' not in model.eyes.links:
        raise ValueError(f'robot {model.name!r} has no left eye to place a head behind')
    left = model.camera_pose('left', head_pose)
    pose = left.copy()
    pose[:3, 3] = (left @ np.array([0.034, 0.0, -0.065, 1.0]))[:3]
    return Obstacle('head', 'box', HEAD_SIZE, pose, WHITE)


def static_bodies(model: 'ArmModel', head_pose: ArrayLike | None = None) -> tuple[Obstacle, ...]:  # noqa: F821
    """Every static body around the arm, as the simulator draws it and the collision check sees it:
    the description's ``obstacles``, its ``scenery`` boxes (named ``scenery_<i>``) and, for a robot
    with eyes, the head behind them (:func:`head_box`), in :attr:`ArmModel.obstacle_names` order."""
    out = list(model.obstacles)
    for i, box in enumerate(model.scenery):
        pose = np.eye(4)
        pose[:3, 3] = box.xyz
        out.append(Obstacle(f'scenery_{i}', 'box', box.size, pose, box.rgba))
    if model.eyes is not None and 'left' in model.eyes.links:
        out.append(head_box(model, head_pose))
    return tuple(out)


def marker_links(model: 'ArmModel', thickness: float = 0.001) -> list[FixedLink]:  # noqa: F821
    """The hand's markers as thin dark boxes on links ``marker_<name>`` of the hand."""
    s = model.marker_side_length
    return [FixedLink(f'marker_{m.name}', 'hand', m.hand_T_marker,
                      (Visual('box', (s, s, thickness), rgba=(0.05, 0.05, 0.05, 1.0)),))
            for m in model.markers]


def drawn_arm_urdf(model: 'ArmModel', dh: ArrayLike | None = None, link_mass: float = 0.0) -> str:  # noqa: F821
    """The arm of ``dh`` (default: the model's) drawn from its table (:func:`model_visuals`), each
    link's primitives also its ``<collision>`` geometry: what the collision check and the
    simulator's contact monitor load for a description without ``urdf:``."""
    dh = model.dh if dh is None else np.asarray(dh, dtype=float)
    return dh_chain_urdf(dh, model.joint_names, model.limits, base=model.base, name=model.name,
                         root_link=model.root_frame, visuals=model_visuals(model, dh), collision=True,
                         link_mass=link_mass)


#: Thickness [m] of the plate a marker is printed on, behind its face (:func:`marker_plates`).
PLATE_THICKNESS = 0.005


def marker_plates(model: 'ArmModel', thickness: float = PLATE_THICKNESS) -> list[FixedLink]:  # noqa: F821
    """The plates the description's markers are printed on, as links on ``hand`` (collision geometry).

    A description read from a URDF draws no palm (its own links do): a marker held past a gripper
    is on a plate of its own, which the arm must keep off the table as much as its links. Each
    plate is a box the size of the printed quad (quiet zone included), ``thickness`` behind the
    marker's face, on a link ``marker_plate_<name>`` (:func:`marker_links` draws the black square
    itself, for a robot description's look).
    """
    quad = quad_side(model.marker_dictionary, model.marker_side_length)
    behind = xyz_rpy_to_transform([0.0, 0.0, -thickness / 2], [0, 0, 0])
    return [FixedLink(f'marker_plate_{m.name}', 'hand', np.asarray(m.hand_T_marker, dtype=float),
                      (Visual('box', (quad, quad, float(thickness)), behind, WHITE),))
            for m in model.markers]


def description_urdf(model: 'ArmModel', dh: ArrayLike | None = None, *, prefix: str = '',  # noqa: F821
                     rgba: tuple = WHITE) -> str:
    """The URDF a robot description topic carries: the arm of ``dh`` with its look and markers.

    Parameters
    ----------
    model : ArmModel
        Joint names, limits, base, root frame and markers.
    dh : array_like, shape (L, 4), optional
        The table drawn (default: the model's).
    prefix : str
        Link and joint name prefix below ``root_link`` (a second arm in one TF tree).
    rgba : tuple of 4 floats
        Shell colour.

    Returns
    -------
    str
        URDF whose links are the frames of :func:`body_schema.urdf.chain_transforms` with the
        same ``prefix`` and ``extra_links=marker_links(model)``.
    """
    dh = model.dh if dh is None else np.asarray(dh, dtype=float)
    return dh_chain_urdf(dh, model.joint_names, model.limits, base=model.base, name=model.name,
                         root_link=model.root_frame, visuals=model_visuals(model, dh, rgba),
                         extra_links=marker_links(model), prefix=prefix)
