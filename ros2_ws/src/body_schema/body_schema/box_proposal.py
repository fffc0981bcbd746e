"""Propose a calibration box for a description that has none (issue #33 item 6).

The box the selector searches should be where the hand's markers are seen most of the time but
not all of it (60-85% detected: the visibility model has something to learn and the data span the
workspace), keep the arm above the plane it is mounted on, and turn the last joint wide (it turns
the marker in its own plane: orientation data without hiding it). Choosing one by hand took
rendered measurements (``icub_sim_bridge.visibility``); this module proposes one from geometry
alone, render-free, in two steps:

1. **Centre.** Scrambled Sobol candidates within the limits are scored by the geometric
   visibility prior (:class:`body_schema.occlusion.VisibilityPrior`: the marker faces a camera
   and projects inside its image) over a small neighbourhood with the last joint wide, by the
   marker's facing angle, by its apparent size (a marker under ~60 px leaves its planar pose
   ambiguous), and by the fraction of the neighbourhood that puts a link origin below the mount
   plane or that the description's collision check refuses; a candidate whose own configuration
   is below the plane or refused is not considered.
2. **Widths.** Starting from a narrow box around the centre, the joint whose widening costs the
   least estimated visibility per unit of its range is widened, step by step, while the estimate
   over uniform (Sobol) samples of the box stays at or above ``target``, and the below-plane and
   colliding fractions at most ``max_below`` and ``max_colliding``.

The estimate is geometric: it ignores the arm hiding its own hand and detector failures, so a
rendered measurement of the result (``python -m tools.box_proposal --check N``) may differ; the
figures for the packaged arms are in docs/calibrate-your-arm.md ("Proposing a box").

Command::

    python -m body_schema.box_proposal --robot NAME_OR_YAML [--seed 1] [--samples 512]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from scipy.stats import qmc

from . import kinematics
from .noise import view_geometry
from .occlusion import VisibilityPrior
from .robot import ArmModel, RobotDescriptionError, load_robot, robot_path

__all__ = ['BAND', 'NoFacingConfigurationError', 'ProposedBoxWarning', 'BoxProposal', 'geometric_visibility',
           'below_plane', 'propose_box', 'proposed_box', 'cache_dir', 'box_yaml', 'describe', 'parser', 'run', 'main']

#: The band the proposed box's visibility should be in, and the target inside it.
BAND = (0.60, 0.85)
#: Marker width in the image [px] above which its planar pose is unambiguous (docs: 8 cm at 1.7 m, 56 px).
UNAMBIGUOUS_PX = 60.0


class NoFacingConfigurationError(RobotDescriptionError):
    """No configuration within the limits shows a marker to a camera (or none keeps the arm above the plane)."""


class ProposedBoxWarning(UserWarning):
    """A description without ``calibration_box`` got a proposed one (the message has the line to paste)."""


@dataclass(frozen=True)
class BoxProposal:
    """A proposed calibration box and what the geometry estimates of it.

    Attributes
    ----------
    box : ndarray, shape (L, 2)
        Joint box [rad], inside the limits.
    centre : ndarray, shape (L,)
        The configuration it was grown around [rad].
    visibility : float
        Estimated fraction of uniform configurations of the box with a marker seen (geometric).
    per_camera : dict of str to float
        The same per camera.
    below_plane : float
        Fraction of configurations with a link origin or a marker below the mount plane (NaN: no plane).
    colliding : float
        Fraction refused by the description's collision check (NaN: not checked).
    cameras : tuple of str
        The cameras the estimate is for.
    n_samples : int
        Samples of the box behind each estimate.
    """

    box: NDArray[np.float64]
    centre: NDArray[np.float64]
    visibility: float
    per_camera: dict[str, float]
    below_plane: float
    colliding: float
    cameras: tuple[str, ...]
    n_samples: int

    @property
    def in_band(self) -> bool:
        """Whether :attr:`visibility` lies in :data:`BAND`."""
        return BAND[0] <= self.visibility <= BAND[1]


def _cameras(model: ArmModel, cameras: tuple[str, ...] | None) -> tuple[str, ...]:
    """The cameras to score: given, else ``left`` (the graph's primary slot) if there, else all."""
    if model.camera is None or not model.markers:
        raise NoFacingConfigurationError(f'robot {model.name!r}: needs a camera section and hand markers to '
                                         'propose a calibration box')
    names = model.camera_names
    if cameras is None:
        cameras = ('left',) if 'left' in names else names
    unknown = sorted(set(cameras) - set(names))
    if not cameras or unknown:
        raise ValueError(f'robot {model.name!r}: unknown cameras {unknown}; it has {list(names)}')
    return tuple(cameras)


def _marker_poses(model: ArmModel, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Markers in the root frame, (N, M, 4, 4), for q of shape (N, L)."""
    hand = model.forward_kinematics(q)
    return np.stack([hand @ m.hand_T_marker for m in model.markers], axis=1)


def _seen(model: ArmModel, q: NDArray[np.float64], cameras: tuple[str, ...]) -> tuple[NDArray[np.float64],
                                                                                      NDArray[np.float64]]:
    """Geometric detection probability per camera (C, N) and a facing-and-size quality (N,) in [0, 1]."""
    prior = VisibilityPrior(model.camera, max_view_angle_deg=89.0, floor=1e-9, ceiling=1.0 - 1e-9,
                            marker_side=model.marker_side_length)
    markers = _marker_poses(model, q)
    p, quality = [], np.zeros(q.shape[0])
    for name in cameras:
        cam = model.camera_pose(name)
        p.append(prior.probability(cam, markers))
        r, phi = view_geometry(cam, markers)                                   # (N, M)
        size = np.clip(model.camera.fx * model.marker_side_length * np.cos(np.radians(np.minimum(phi, 90.0)))
                       / np.maximum(r, 1e-6) / UNAMBIGUOUS_PX, 0.0, 1.0)
        quality = np.maximum(quality, np.max(size, axis=1))
    return np.array(p), quality


def geometric_visibility(model: ArmModel, q: ArrayLike, cameras: tuple[str, ...] | None = None
                         ) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]:
    """Geometric probability that a marker is seen, for configurations ``q``.

    The visibility prior (:class:`~body_schema.occlusion.VisibilityPrior`, its defaults) on the
    nominal table, without its floor and ceiling: the marker faces the camera and projects inside
    its image. A configuration is seen if any of ``cameras`` sees it (independently).

    Parameters
    ----------
    model : ArmModel
    q : array_like, shape (N, L)
        Configurations [rad].
    cameras : tuple of str, optional
        Default: ``left`` if the description has it (the graph's primary camera), else all.

    Returns
    -------
    p : ndarray, shape (N,)
        Probability that some camera sees a marker.
    per_camera : dict of str to ndarray (N,)
    """
    names = _cameras(model, cameras)
    p, _ = _seen(model, np.atleast_2d(np.asarray(q, dtype=float)), names)
    return 1.0 - np.prod(1.0 - p, axis=0), dict(zip(names, p))


def below_plane(model: ArmModel, q: ArrayLike, plane_z: float = 0.0) -> NDArray[np.bool_]:
    """Whether a link origin (a DH frame after a joint, the hand) or a marker is below ``z = plane_z``.

    Parameters
    ----------
    q : array_like, shape (N, L)

    Returns
    -------
    ndarray, shape (N,), bool
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    z = kinematics.chain_frames(model.base, model.dh, q)[:, 1:, 2, 3]          # (N, L) without the base
    zm = _marker_poses(model, q)[..., 2, 3]                                     # (N, M)
    return np.any(z < plane_z - 1e-9, axis=1) | np.any(zm < plane_z - 1e-9, axis=1)


def _unit(n: int, dim: int, seed: int) -> NDArray[np.float64]:
    """``n`` scrambled Sobol points in [0, 1)^dim (n rounded up to a power of two)."""
    return qmc.Sobol(dim, scramble=True, seed=seed).random_base2(int(np.ceil(np.log2(max(n, 2)))))


def propose_box(model: ArmModel, *, seed: int = 1, n_samples: int = 512, n_candidates: int = 1024,
                target: float = 0.75, max_below: float = 0.03, max_colliding: float = 0.03,
                last_half_width: float = np.radians(170.0), max_half_width: float = np.radians(90.0),
                plane_z: float | None = 0.0, collision: bool = True,
                cameras: tuple[str, ...] | None = None) -> BoxProposal:
    """Propose a joint box inside the limits whose markers a camera sees in about ``target`` of it.

    Parameters
    ----------
    model : ArmModel
        The description (its nominal table, cameras, markers, limits and obstacles; its box is ignored).
    seed : int
        Seed of the Sobol scrambling: the same seed gives the same box.
    n_samples : int
        Samples of a box per estimate (rounded up to a power of two).
    n_candidates : int
        Candidate centres (rounded up to a power of two).
    target : float
        Visibility the widening stops at (inside :data:`BAND`).
    max_below : float
        Largest fraction of the box's configurations with a link origin or marker below the mount plane.
    max_colliding : float
        Largest fraction of the box's configurations that the description's collision check
        (:class:`body_schema.collision.CollisionModel`: obstacles and the arm itself, with the
        description's margins) refuses; the centre itself must be clear.
    last_half_width : float
        Half-width of the last joint's range [rad] (clipped to its limits).
    max_half_width : float
        Largest half-width of any other joint [rad].
    plane_z : float or None
        Height of the mount plane in the root frame [m]; None: no plane (a humanoid's waist).
    collision : bool
        Whether to use the collision check (False: the plane alone).
    cameras : tuple of str, optional
        Default: ``left`` if the description has it, else all its cameras.

    Returns
    -------
    BoxProposal

    Raises
    ------
    NoFacingConfigurationError
        If the description has no camera or markers, or no configuration within the limits shows
        a marker to a camera (above the mount plane, clear of collisions).
    ValueError
        If an argument is out of range.
    """
    if not BAND[0] <= target <= BAND[1]:
        raise ValueError(f'target must be in {BAND}, got {target}')
    if not (0.0 <= max_below < 1.0 and 0.0 <= max_colliding < 1.0) or n_samples < 16 or n_candidates < 16:
        raise ValueError('max_below and max_colliding must be in [0, 1), n_samples and n_candidates at least 16')
    names = _cameras(model, cameras)
    lim = np.asarray(model.limits, dtype=float)
    n_joints = lim.shape[0]
    last = min(last_half_width, 0.5 * (lim[-1, 1] - lim[-1, 0]))
    checker = None
    if collision:
        from .collision import CollisionModel       # here: Pinocchio and Coal only when asked for

        checker = CollisionModel(model)

    def box_of(centre: NDArray[np.float64], half: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.stack([np.maximum(centre - half, lim[:, 0]), np.minimum(centre + half, lim[:, 1])], axis=-1)

    def refused(q: NDArray[np.float64]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Below the plane (N,) and refused by the collision check (N,)."""
        low = np.zeros(q.shape[0], dtype=bool) if plane_z is None else below_plane(model, q, plane_z)
        hit = np.zeros(q.shape[0], dtype=bool) if checker is None else ~np.asarray(checker.clear(q))
        return low, hit

    # 1. Centre: candidates within the limits, each scored over a neighbourhood with the last joint wide.
    cand = qmc.scale(_unit(n_candidates, n_joints, seed), lim[:, 0], lim[:, 1])
    cand[:, -1] = 0.5 * (lim[-1, 0] + lim[-1, 1])
    low, hit = refused(cand)
    if not np.any(~low & ~hit):
        raise NoFacingConfigurationError(f'robot {model.name!r}: every candidate configuration puts a link below '
                                         f'the mount plane z = {plane_z} m or in collision')
    cand = cand[~low & ~hit]
    local = _unit(32, n_joints, seed + 1) * 2.0 - 1.0                            # (K, L) in [-1, 1]
    half0 = np.full(n_joints, np.radians(20.0))
    half0[-1] = last
    hoods = np.clip(cand[:, None, :] + local[None] * half0, lim[:, 0], lim[:, 1])  # (C, K, L)
    flat = hoods.reshape(-1, n_joints)
    p, quality = _seen(model, flat, names)
    seen = (1.0 - np.prod(1.0 - p, axis=0)).reshape(hoods.shape[:2])
    low, hit = refused(flat)
    score = (seen * (0.5 + 0.5 * quality.reshape(hoods.shape[:2]))).mean(axis=1) \
        - (low | hit).reshape(hoods.shape[:2]).mean(axis=1)
    best = int(np.argmax(score))
    if seen[best].mean() < BAND[0]:
        raise NoFacingConfigurationError(
            f'robot {model.name!r}: no configuration within the limits shows a marker to camera(s) {list(names)} '
            f'(best of {len(cand)} candidates: seen in {100 * seen[best].mean():.0f}% of its neighbourhood); '
            'check the camera pose (optical frame: z forward) and the markers\' rpy (z out of the face)')
    centre = cand[best]

    # 2. Widths: greedily widen the joint that costs the least visibility per unit of its range.
    unit = _unit(n_samples, n_joints, seed + 2)

    def estimate(half: NDArray[np.float64]) -> tuple[float, NDArray[np.float64], float, float]:
        b = box_of(centre, half)
        q = b[:, 0] + unit * (b[:, 1] - b[:, 0])
        pc, _ = _seen(model, q, names)
        lo, hi = refused(q)
        return float(np.mean(1.0 - np.prod(1.0 - pc, axis=0))), pc.mean(axis=1), float(lo.mean()), float(hi.mean())

    cap = np.minimum(np.full(n_joints, max_half_width), 0.5 * (lim[:, 1] - lim[:, 0]))
    cap[-1] = last
    half = np.minimum(np.full(n_joints, np.radians(5.0)), cap)
    half[-1] = last
    vis, per, frac, coll = estimate(half)
    open_ = set(range(n_joints - 1))
    while open_:
        trials = []
        for j in sorted(open_):
            h = half.copy()
            h[j] = min(cap[j], max(h[j] * 1.25, h[j] + np.radians(2.0)))
            v, pc, f, c = estimate(h)
            if v < target or f > max(max_below, frac) or c > max(max_colliding, coll):   # never worse than now
                open_.discard(j)
                continue
            trials.append(((vis - v) / ((h[j] - half[j]) / cap[j]), j, h, v, pc, f, c))
            if h[j] >= cap[j]:
                open_.discard(j)
        if not trials:
            break
        _, j, half, vis, per, frac, coll = min(trials, key=lambda t: (t[0], t[1]))
    return BoxProposal(box_of(centre, half), centre, vis, {n: float(v) for n, v in zip(names, per)},
                       frac if plane_z is not None else float('nan'), coll if checker is not None else float('nan'),
                       names, unit.shape[0])


#: Bump when the proposer's choices change: cached proposals of an older version are not reused.
PROPOSER_VERSION = 2       # 2: a URDF description checked with its own collision meshes
_CACHE: dict[str, NDArray[np.float64]] = {}


def _cache_key(model: ArmModel) -> str:
    """A digest of everything the proposal depends on: kinematics, limits, cameras, markers, obstacles."""
    h = hashlib.sha256(f'v{PROPOSER_VERSION} {model.joint_names} {model.camera} {model.marker_side_length} '
                       f'{model.collision} {[(o.shape, o.size) for o in model.obstacles]} {model.scenery}'.encode())
    for a in [model.dh, model.base, model.tool, model.limits] + [model.camera_pose(c) for c in model.camera_names] \
            + [m.hand_T_marker for m in model.markers] + [o.pose for o in model.obstacles]:
        h.update(np.round(np.asarray(a, dtype=float), 12).tobytes())
    return h.hexdigest()[:24]


def cache_dir() -> Path:
    """Where proposals are cached: ``$BODY_SCHEMA_CACHE``, else ``$XDG_CACHE_HOME/body_schema`` (``~/.cache``)."""
    env = os.environ.get('BODY_SCHEMA_CACHE')
    if env:
        return Path(env)
    return Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache') / 'body_schema'


def proposed_box(model: ArmModel, source: str = '<dict>', angle_unit: str = 'deg') -> NDArray[np.float64]:
    """The box :func:`~body_schema.robot.load_robot` uses for a description without one, shape (L, 2) [rad].

    :func:`propose_box` with its defaults, once per description: kept in this process and in
    :func:`cache_dir` (one small JSON file a description), since every node loads the
    description and a proposal takes seconds. A robot watched by its own eyes (a humanoid, whose
    root frame is its waist) has no mount plane. Warns (:class:`ProposedBoxWarning`) with the line to
    paste into the YAML; where nothing faces a camera it warns why and returns the joint limits.
    """
    key = _cache_key(model)
    if key in _CACHE:
        return _CACHE[key].copy()
    path = cache_dir() / f'box_{key}.json'
    note = ''
    try:
        box = np.radians(np.array(json.loads(path.read_text())['box_deg'], dtype=float))
        note = f' (cached in {path})'
    except (OSError, ValueError, KeyError, TypeError):
        try:
            proposal = propose_box(model, plane_z=None if model.eyes is not None else 0.0)
        except NoFacingConfigurationError as exc:
            warnings.warn(ProposedBoxWarning(f'{source}: no calibration_box and none could be proposed ({exc}); '
                                             'the box is the joint limits'), stacklevel=4)
            _CACHE[key] = model.limits.copy()
            return model.limits.copy()
        box = proposal.box
        note = (f' (geometric visibility {100 * proposal.visibility:.0f}%, {100 * proposal.below_plane:.1f}% below '
                f'the mount plane, {100 * proposal.colliding:.1f}% colliding)')
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({'robot': model.name, 'source': source, 'box_deg': np.degrees(box).tolist(),
                                        'visibility': proposal.visibility, 'below_plane': proposal.below_plane,
                                        'colliding': proposal.colliding}))
        except OSError:
            pass
    _CACHE[key] = box.copy()
    warnings.warn(ProposedBoxWarning(f'{source}: no calibration_box; proposed one{note}. To keep it, paste into '
                                     f'the description:\n{box_yaml(box, model.limits, angle_unit)}'), stacklevel=4)
    return box.copy()


def box_yaml(box: ArrayLike, limits: ArrayLike, angle_unit: str = 'deg') -> str:
    """The box as a ``calibration_box:`` line in ``angle_unit``, rounded inward so it stays inside ``limits``.

    Parameters
    ----------
    box, limits : array_like, shape (L, 2)
        [rad].
    angle_unit : {'deg', 'rad'}
    """
    box, limits = np.asarray(box, dtype=float), np.asarray(limits, dtype=float)
    if angle_unit == 'deg':
        lo, hi = np.ceil(np.degrees(box[:, 0]) - 1e-9), np.floor(np.degrees(box[:, 1]) + 1e-9)
        rows = [f'[{lo_:g}, {hi_:g}]' for lo_, hi_ in zip(lo, hi)]
    else:
        lo, hi = np.ceil(box[:, 0] * 1000 - 1e-9) / 1000, np.floor(box[:, 1] * 1000 + 1e-9) / 1000
        rows = [f'[{lo_:.3f}, {hi_:.3f}]' for lo_, hi_ in zip(lo, hi)]
    return 'calibration_box: [' + ', '.join(rows) + ']'


def angle_unit_of(name_or_path: str) -> str:
    """The ``angle_unit`` a description is written in (``rad`` if it says none)."""
    p = Path(name_or_path)
    path = p if (p.suffix in ('.yaml', '.yml') or p.exists()) else robot_path(name_or_path)
    data = yaml.safe_load(path.read_text()) or {}
    return str(data.get('angle_unit', 'rad'))


def describe(proposal: BoxProposal, model: ArmModel, angle_unit: str) -> str:
    """The box to paste and what the geometry estimates of it, as printed by the command."""
    per = ', '.join(f'{n} {100 * v:.1f}%' for n, v in proposal.per_camera.items())
    band = 'in' if proposal.in_band else 'OUTSIDE'
    return (f'# Proposed by body_schema.box_proposal ({proposal.n_samples} Sobol samples of the box): a marker\n'
            f'# seen (geometric estimate) in {100 * proposal.visibility:.1f}% ({per}; {band} the '
            f'{100 * BAND[0]:.0f}-{100 * BAND[1]:.0f}% band),\n'
            + (f'# {100 * proposal.below_plane:.1f}% of configurations with a link origin or marker below the mount '
               'plane,\n' if np.isfinite(proposal.below_plane) else '# no mount plane,\n')
            + (f'# {100 * proposal.colliding:.1f}% refused by the collision check (obstacles, the arm itself).\n'
               if np.isfinite(proposal.colliding) else '# the collision check not run.\n')
            + box_yaml(proposal.box, model.limits, angle_unit))


def parser() -> argparse.ArgumentParser:
    """The command's arguments (``tools.box_proposal`` adds ``--check``)."""
    ap = argparse.ArgumentParser(description='Propose a calibration box (printed as YAML to paste) for a robot '
                                             'description, from the geometric visibility prior.')
    ap.add_argument('--robot', required=True, help='packaged description name or YAML path')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--samples', type=int, default=512, help='Sobol samples of the box per estimate')
    ap.add_argument('--candidates', type=int, default=1024, help='Sobol candidate centres')
    ap.add_argument('--target', type=float, default=0.75, help='visibility the widening stops at')
    ap.add_argument('--max-below', type=float, default=0.03,
                    help='largest fraction of the box below the mount plane z = 0')
    ap.add_argument('--max-colliding', type=float, default=0.03,
                    help='largest fraction of the box the collision check refuses')
    ap.add_argument('--no-plane', action='store_true', help='no mount plane (a humanoid\'s waist frame)')
    ap.add_argument('--no-collision', action='store_true', help='no collision check (the plane alone)')
    ap.add_argument('--camera', action='append', help='camera to score (repeatable; default left, else all)')
    return ap


def run(args: argparse.Namespace) -> tuple[ArmModel, BoxProposal] | None:
    """Propose for parsed :func:`parser` arguments and print the box; None (the error printed) if none."""
    model = load_robot(args.robot, propose_box=False)
    try:
        proposal = propose_box(model, seed=args.seed, n_samples=args.samples, n_candidates=args.candidates,
                               target=args.target, max_below=args.max_below, max_colliding=args.max_colliding,
                               plane_z=None if args.no_plane else 0.0, collision=not args.no_collision,
                               cameras=tuple(args.camera) if args.camera else None)
    except (RobotDescriptionError, ValueError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return None
    print(describe(proposal, model, angle_unit_of(args.robot)))
    return model, proposal


def main(argv: list[str] | None = None) -> int:
    return 0 if run(parser().parse_args(argv)) is not None else 2


if __name__ == '__main__':
    sys.exit(main())
