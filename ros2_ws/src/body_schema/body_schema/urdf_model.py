"""A robot description's arm from a URDF: the chain, a standard DH table derived from its joint
axes, and the calibrated URDF written back (the only module that imports yourdfpy and xacro).

**Reading.** :func:`read_urdf` parses a ``.urdf`` (or expands a ``.xacro`` first) with yourdfpy;
:func:`urdf_chain` walks the joints from ``tip_link`` up to ``base_link`` (revolute, continuous and
fixed joints; any other type is refused with its name).

**Deriving standard DH** (:func:`derive_dh`), the classic construction from the joint axes at
``q = 0`` (in ``base_link``): DH frame ``k`` has its z on joint ``k``'s axis (the URDF's
``<axis>``, sign kept, so a positive ``q`` turns the same way), its x along the common normal from
the previous axis, its origin where that normal meets the axis. The cases:

* skew axes: the common normal is unique; ``a > 0`` is its length;
* intersecting axes (distance below :data:`LENGTH_TOL`): ``a = 0`` and ``x = +-(z_prev x z)``,
  the sign that keeps ``|offset| <= 90 deg`` (``+`` on a tie);
* parallel axes (``|z_prev x z|`` below :data:`PARALLEL_TOL`): the normal is not unique; as the
  standard convention does (Spong, Hutchinson & Vidyasagar), the one through the previous frame's
  origin, so ``d = 0``; coincident axes keep the previous x (``a = 0``, ``offset = 0``);
* nearly parallel axes (between :data:`PARALLEL_TOL` and :data:`NEAR_PARALLEL_DEG`): the normal is
  unique but far away, and standard DH is ill-conditioned there (a small change of the axis moves
  ``d`` by metres). The table is still exact; a :class:`NearlyParallelAxesWarning` names the
  joints. Hayati's extra ``beta`` parameter is the known remedy; it is not implemented.

Frame 0 (before the first joint) is free in standard DH: its origin is the foot of ``base_link``'s
origin on the first axis and its x the projection of ``base_link``'s x (y if that is the axis);
the base transform ``base_link -> frame 0`` takes the offset. The hand frame (after the last
joint) is built the same way toward the tip link's z line (the tip's origin and x where the
parallel / coincident cases leave the choice), so the tool transform ``hand -> tip_link`` that is
left over is ``Tz(d) Rz(theta)``, the identity when the tip sits on the last axis (a flange).

**Writing** (:func:`calibrated_urdf`): the same text with the chain's joint origins corrected so
that the URDF's forward kinematics equals a DH estimate; each link keeps its pose relative to its
joint's rotating DH frame (so meshes and inertials ride along), nothing else in the file changes.
"""
from __future__ import annotations

import io
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from . import kinematics
from .robot import RobotDescriptionError
from .urdf import FixedLink, append_fixed_links, transform_to_xyz_rpy

__all__ = ['UrdfDescriptionError', 'NearlyParallelAxesWarning', 'UrdfJoint', 'UrdfChain', 'DerivedDH',
           'PARALLEL_TOL', 'LENGTH_TOL', 'NEAR_PARALLEL_DEG', 'read_urdf', 'urdf_chain', 'derive_dh',
           'calibrated_tip_link', 'calibrated_urdf', 'model_chain', 'arm_urdf', 'write_calibrated_urdf',
           'next_dh_row']

#: ``|z_prev x z|`` below which consecutive axes count as parallel (URDF files write pi/2 to
#: about 12 digits, 5e-12 rad off).
PARALLEL_TOL = 1e-10
#: Distance between axes [m] below which they count as intersecting.
LENGTH_TOL = 1e-10
#: Angle [deg] below which non-parallel consecutive axes are "nearly parallel" (ill-conditioned).
NEAR_PARALLEL_DEG = 2.0
#: Joint types that move (a DH joint) and that are rigid.
MOVING, RIGID = ('revolute', 'continuous'), ('fixed',)


class UrdfDescriptionError(RobotDescriptionError):
    """The URDF cannot be read, has no chain between the links, or a joint type is unsupported."""


class NearlyParallelAxesWarning(UserWarning):
    """Consecutive joint axes are nearly but not exactly parallel: the derived table is exact but
    ill-conditioned (its ``d`` is far away and jumps with the axis)."""


@dataclass(frozen=True)
class UrdfJoint:
    """One joint of the chain: ``parent_T_child(q) = origin @ rot(axis, q)``.

    Attributes
    ----------
    name, kind : str
        Joint name and URDF type (``revolute``, ``continuous``, ``fixed``).
    parent, child : str
    origin : ndarray, shape (4, 4)
    axis : ndarray, shape (3,)
        Unit axis in the child frame (zeros for a fixed joint).
    limits : ndarray, shape (2,)
        ``[lower, upper]`` [rad]; ``[-2 pi, 2 pi]`` for a continuous joint.
    """

    name: str
    kind: str
    parent: str
    child: str
    origin: NDArray[np.float64]
    axis: NDArray[np.float64]
    limits: NDArray[np.float64]

    def transform(self, q: float = 0.0) -> NDArray[np.float64]:
        """``parent_T_child`` at joint position ``q``, shape (4, 4)."""
        if self.kind in RIGID:
            return self.origin
        t = np.eye(4)
        t[:3, :3] = Rotation.from_rotvec(self.axis * q).as_matrix()
        return self.origin @ t


@dataclass(frozen=True)
class UrdfChain:
    """The joints from ``base_link`` to ``tip_link`` in order, and the URDF they come from.

    Attributes
    ----------
    joints : tuple of UrdfJoint
    base_link, tip_link : str
    text : str
        The URDF document (a ``.xacro`` expanded).
    path : Path or None
    """

    joints: tuple[UrdfJoint, ...]
    base_link: str
    tip_link: str
    text: str
    path: Path | None = None

    @property
    def moving(self) -> tuple[UrdfJoint, ...]:
        """The revolute / continuous joints, base to tip (length L)."""
        return tuple(j for j in self.joints if j.kind in MOVING)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.moving)

    @property
    def limits(self) -> NDArray[np.float64]:
        """Joint limits [rad], shape (L, 2)."""
        return np.array([j.limits for j in self.moving])

    def frames(self, q: ArrayLike | None = None) -> list[NDArray[np.float64]]:
        """Each joint's child link pose in ``base_link`` at ``q`` (L,) (zeros if omitted)."""
        qv = np.zeros(len(self.moving)) if q is None else np.asarray(q, dtype=float)
        out, pose, k = [], np.eye(4), 0
        for j in self.joints:
            if j.kind in MOVING:
                pose = pose @ j.transform(qv[k])
                k += 1
            else:
                pose = pose @ j.transform()
            out.append(pose)
        return out

    def tip_pose(self, q: ArrayLike | None = None) -> NDArray[np.float64]:
        """``tip_link`` in ``base_link`` at ``q`` (L,), shape (4, 4) (the URDF's own kinematics)."""
        return self.frames(q)[-1] if self.joints else np.eye(4)


def read_urdf(path: str | Path) -> tuple[str, object]:
    """The URDF text (a ``.xacro`` expanded with the xacro package) and its yourdfpy model.

    Raises
    ------
    UrdfDescriptionError
        If the file is missing, xacro fails, or yourdfpy cannot parse it.
    """
    import yourdfpy

    p = Path(path)
    if not p.is_file():
        raise UrdfDescriptionError(f'urdf.file: {str(p)!r} does not exist')
    if p.suffix == '.xacro':
        import xacro
        try:
            text = xacro.process_file(str(p)).toprettyxml(indent='  ')
        except Exception as exc:  # xacro raises its own XacroException and plain errors alike
            raise UrdfDescriptionError(f'urdf.file: xacro could not expand {str(p)!r}: {exc}') from exc
    else:
        text = p.read_text()
    try:
        model = yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=False, load_meshes=False,
                                   build_collision_scene_graph=False, load_collision_meshes=False,
                                   mesh_dir=str(p.parent))
    except Exception as exc:  # lxml syntax errors, yourdfpy's own validation errors
        raise UrdfDescriptionError(f'urdf.file: {str(p)!r} is not a readable URDF: {exc}') from exc
    return text, model


def urdf_chain(path: str | Path, base_link: str, tip_link: str) -> UrdfChain:
    """The serial chain between two links of a URDF.

    Raises
    ------
    UrdfDescriptionError
        If a link is unknown, ``tip_link`` does not descend from ``base_link``, a joint of the chain
        is of another type than revolute / continuous / fixed or mimics another, or a revolute
        joint has no limits.
    """
    text, model = read_urdf(path)
    robot = model.robot
    links = {ln.name for ln in robot.links}
    for key, link in (('base_link', base_link), ('tip_link', tip_link)):
        if link not in links:
            raise UrdfDescriptionError(f'urdf.{key}: no link {link!r} in {path}; links: {sorted(links)}')
    by_child = {j.child: j for j in robot.joints}
    chain, link = [], tip_link
    while link != base_link:
        if link not in by_child:
            raise UrdfDescriptionError(f'urdf: tip_link {tip_link!r} does not descend from base_link {base_link!r} '
                                       f'in {path} (reached the root {link!r})')
        chain.append(by_child[link])
        link = by_child[link].parent
    out = []
    for j in reversed(chain):
        if j.type not in MOVING + RIGID:
            raise UrdfDescriptionError(f'urdf: joint {j.name!r} is {j.type}; only revolute, continuous and fixed '
                                       'joints can be in the calibrated chain')
        if j.mimic is not None:
            raise UrdfDescriptionError(f'urdf: joint {j.name!r} mimics {j.mimic.joint!r}; a mimic joint cannot be '
                                       'calibrated on its own')
        axis = np.zeros(3)
        limits = np.array([-2 * np.pi, 2 * np.pi])
        if j.type in MOVING:
            axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=float)
            if not np.linalg.norm(axis) > 0:
                raise UrdfDescriptionError(f'urdf: joint {j.name!r} has a zero axis')
            axis = axis / np.linalg.norm(axis)
            if j.type == 'revolute':
                if j.limit is None or j.limit.lower is None or j.limit.upper is None:
                    raise UrdfDescriptionError(f'urdf: revolute joint {j.name!r} has no <limit lower upper>')
                limits = np.array([j.limit.lower, j.limit.upper], dtype=float)
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float)
        out.append(UrdfJoint(j.name, j.type, j.parent, j.child, origin, axis, limits))
    if not any(j.kind in MOVING for j in out):
        raise UrdfDescriptionError(f'urdf: no revolute joint between {base_link!r} and {tip_link!r}')
    return UrdfChain(tuple(out), base_link, tip_link, text, Path(path))


@dataclass(frozen=True)
class DerivedDH:
    """A standard DH table equivalent to a URDF chain.

    ``tip(q) = base @ prod_i H_i(q_i) @ tool`` equals the URDF's ``tip_link`` pose in ``base_link``.

    Attributes
    ----------
    dh : ndarray, shape (L, 4)
        ``(a, d, alpha, offset)`` per joint [m, m, rad, rad].
    base : ndarray, shape (4, 4)
        ``base_link`` -> DH frame 0.
    tool : ndarray, shape (4, 4)
        Hand (the frame after the last joint) -> ``tip_link``: ``Tz(d) Rz(theta)``.
    link_offsets : ndarray, shape (L, 4, 4)
        Each revolute joint's child link in its rotating DH frame ``F_k Rz(q_k + offset_k)``
        (constant; :func:`calibrated_urdf` keeps it).
    nearly_parallel : tuple of (str, str)
        The consecutive joints (or last joint and tip link) whose axes are nearly parallel.
    """

    dh: NDArray[np.float64]
    base: NDArray[np.float64]
    tool: NDArray[np.float64]
    link_offsets: NDArray[np.float64]
    nearly_parallel: tuple[tuple[str, str], ...] = ()


def _unit_perpendicular(v: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64] | None:
    w = v - (v @ z) * z
    n = np.linalg.norm(w)
    return w / n if n > 1e-6 else None


def _angle(u: NDArray[np.float64], v: NDArray[np.float64], about: NDArray[np.float64]) -> float:
    """Angle turning unit ``u`` into unit ``v`` about unit ``about`` (both perpendicular to it)."""
    return float(np.arctan2(np.cross(u, v) @ about, u @ v))


def next_dh_row(frame: NDArray[np.float64], point: NDArray[np.float64], z_new: NDArray[np.float64],
                anchor: NDArray[np.float64], prefer_x: NDArray[np.float64]) -> tuple[NDArray[np.float64], str]:
    """The DH row from ``frame`` (z on the current axis) to the frame on line (point, z_new).

    One step of :func:`derive_dh` (also used by ``tools.parameterisation_study`` to build
    Hayati's rows on the same frames).

    Parameters
    ----------
    frame : (4, 4) array
        The current DH frame, its z on the current joint axis.
    point, z_new : (3,) arrays
        A point on the next joint axis and its unit direction.
    anchor : (3,) array
        Where the common normal is placed when the axes are parallel (the next joint's origin).
    prefer_x : (3,) array
        The x direction to take when the axes coincide (no normal defines it).

    Returns
    -------
    row : (4,) array
        ``(a, d, alpha, offset)``.
    case : str
        ``skew``, ``intersecting``, ``parallel`` or ``coincident``.
    """
    o, x, z = frame[:3, 3], frame[:3, 0], frame[:3, 2]
    n = np.cross(z, z_new)
    s = float(np.linalg.norm(n))
    if s < PARALLEL_TOL:
        on = point + ((anchor - point) @ z_new) * z_new      # the normal through the anchor
        c = o + ((on - o) @ z) * z
        v = on - c
        a = float(np.linalg.norm(v))
        if a < LENGTH_TOL:
            px = _unit_perpendicular(prefer_x, z)
            x_new, case, a = (px if px is not None else x), 'coincident', 0.0
        else:
            x_new, case = v / a, 'parallel'
    else:
        # closest points of o + t z and point + u z_new
        w0 = o - point
        b = z @ z_new
        denom = 1.0 - b * b
        t = (b * (z_new @ w0) - (z @ w0)) / denom
        c = o + t * z
        n_hat = n / s
        dist = float((point - o) @ n_hat)                    # signed distance along z x z_new
        if abs(dist) < LENGTH_TOL:
            x_new = n_hat if n_hat @ prefer_x >= -1e-12 else -n_hat
            a, case = 0.0, 'intersecting'
        else:
            x_new, a, case = np.sign(dist) * n_hat, abs(dist), 'skew'
    d = float((c - o) @ z)
    offset = _angle(x, x_new, z)
    offset = np.pi if offset <= -np.pi + 1e-12 else offset     # (-pi, pi]: a half turn is +180 deg
    alpha = _angle(z, z_new, x_new)
    alpha = np.pi if alpha <= -np.pi + 1e-12 else alpha
    return np.array([a, d, alpha, offset]), case


def derive_dh(chain: UrdfChain) -> DerivedDH:
    """The standard DH table, base and tool transforms of a URDF chain (module docstring).

    Warns
    -----
    NearlyParallelAxesWarning
        For each pair of consecutive axes (and the last axis with the tip's z) less than
        :data:`NEAR_PARALLEL_DEG` apart but not parallel.
    """
    moving = chain.moving
    frames = chain.frames()
    child_poses = [f for f, j in zip(frames, chain.joints) if j.kind in MOVING]
    points = [f[:3, 3] for f in child_poses]
    axes = [f[:3, :3] @ j.axis for f, j in zip(child_poses, moving)]
    tip = chain.tip_pose()

    z0 = axes[0]
    o0 = points[0] + ((np.zeros(3) - points[0]) @ z0) * z0
    x0 = _unit_perpendicular(np.array([1.0, 0.0, 0.0]), z0)
    if x0 is None:
        x0 = _unit_perpendicular(np.array([0.0, 1.0, 0.0]), z0)
    base = np.eye(4)
    base[:3, 0], base[:3, 1], base[:3, 2], base[:3, 3] = x0, np.cross(z0, x0), z0, o0

    near_sin = np.sin(np.radians(NEAR_PARALLEL_DEG))
    rows, near = [], []
    frame = base
    targets = [(points[k + 1], axes[k + 1], None, moving[k + 1].name) for k in range(len(moving) - 1)]
    targets.append((tip[:3, 3], tip[:3, 2], tip[:3, 0], chain.tip_link))
    for k, (point, z_new, tip_x, name) in enumerate(targets):
        anchor = frame[:3, 3] if tip_x is None else point
        row, _case = next_dh_row(frame, point, z_new, anchor, frame[:3, 0] if tip_x is None else tip_x)
        s = np.linalg.norm(np.cross(frame[:3, 2], z_new))
        if PARALLEL_TOL <= s < near_sin:
            near.append((moving[k].name, name))
        rows.append(row)
        frame = frame @ kinematics.dh_link_transforms(row[None], np.zeros((1, 1)))[0, 0]
    dh = np.array(rows)
    dh_frames = kinematics.chain_frames(base, dh, np.zeros(len(dh)))
    tool = np.linalg.inv(dh_frames[-1]) @ tip
    offsets = np.array([np.linalg.inv(dh_frames[k] @ _rz(dh[k, 3])) @ child_poses[k] for k in range(len(dh))])
    for k, j in enumerate(moving):                           # the construction's own check
        f = dh_frames[k]
        off_axis = np.linalg.norm(np.cross(f[:3, 2], points[k] - f[:3, 3]))
        if f[:3, 2] @ axes[k] < 1 - 1e-9 or off_axis > 1e-6:
            raise UrdfDescriptionError(f'urdf: DH frame {k} does not sit on joint {j.name!r} '
                                       f'(axis cos {f[:3, 2] @ axes[k]:.12f}, {off_axis:.3g} m off)')
    for a, b in near:
        warnings.warn(f'urdf {chain.path}: the axes of {a!r} and {b!r} are nearly parallel (under '
                      f'{NEAR_PARALLEL_DEG} deg, not parallel): the standard DH table is exact but ill-conditioned '
                      f'(d of {a!r} = {dh[[j.name for j in moving].index(a), 1]:.4g} m); Hayati\'s beta parameter '
                      'is the remedy, not implemented', NearlyParallelAxesWarning, stacklevel=2)
    return DerivedDH(dh, base, tool, offsets, tuple(near))


def _rz(theta: float) -> NDArray[np.float64]:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _fmt(v: float) -> str:
    return repr(float(v)) if abs(v) > 0 else '0'


def _origin_xml(t: NDArray[np.float64]) -> str:
    xyz, rpy = transform_to_xyz_rpy(t)
    return f'<origin xyz="{" ".join(_fmt(v) for v in xyz)}" rpy="{" ".join(_fmt(v) for v in rpy)}"/>'


def _masked(text: str) -> str:
    """``text`` with every comment's content blanked (same length), so a search skips comments."""
    return re.sub(r'<!--.*?-->', lambda m: ' ' * len(m.group(0)), text, flags=re.S)


def _set_origin(text: str, joint: str, t: NDArray[np.float64]) -> str:
    """``text`` with joint ``joint``'s ``<origin>`` replaced by ``t`` (inserted if it has none)."""
    masked = _masked(text)
    m = re.search(r'<joint\b[^>]*?\bname\s*=\s*(["\'])' + re.escape(joint) + r'\1[^>]*>', masked)
    if m is None:
        raise UrdfDescriptionError(f'urdf: joint {joint!r} not found in the text')
    end = masked.index('</joint>', m.end())
    o = re.search(r'<origin\b[^>]*?(/>|>.*?</origin>)', masked[m.end():end], flags=re.S)
    if o is None:
        return text[:m.end()] + '\n    ' + _origin_xml(t) + text[m.end():]
    return text[:m.end() + o.start()] + _origin_xml(t) + text[m.end() + o.end():]


def calibrated_tip_link(chain: UrdfChain) -> str:
    """The link of :func:`calibrated_urdf`'s document that carries the DH tip (``hand @ tool``):
    ``tip_link``, or the added ``<tip_link>_calibrated`` when ``tip_link`` is the last revolute
    joint's own child."""
    return f'{chain.tip_link}_calibrated' if chain.joints[-1].kind in MOVING else chain.tip_link


def calibrated_urdf(chain: UrdfChain, derived: DerivedDH, dh: ArrayLike, tool: ArrayLike | None = None,
                    mesh_base: str | Path | None = None) -> str:
    """The chain's URDF with its joint origins corrected to the DH table ``dh``.

    Each revolute joint ``k``'s child link keeps its pose in the rotating DH frame
    ``F_k Rz(q_k + offset_k)`` (``derived.link_offsets``), so a joint's ``<axis>`` and every link's
    meshes, inertials and collision shapes stay as written; fixed joints between revolute ones are
    kept; the first fixed joint after the last revolute one takes the tip (``hand @ tool``). When
    the tip link is the last revolute joint's own child (no fixed joint after it), a link
    ``<tip_link>_calibrated`` is added on a fixed joint ``<tip_link>_calibrated_joint``: a URDF
    joint's child sits on its axis, and an estimate may move the tip off it.

    Parameters
    ----------
    chain : UrdfChain
    derived : DerivedDH
        :func:`derive_dh` of ``chain`` (its base and link offsets).
    dh : array_like, shape (L, 4)
        The table to write (e.g. the estimate).
    tool : array_like, shape (4, 4), optional
        Hand -> tip; ``derived.tool`` if omitted.
    mesh_base : str or Path, optional
        For a file written to another directory than the URDF's: relative mesh filenames become
        absolute paths under this directory (the URDF's own), so PyBullet and Pinocchio still find
        them, and so do ``package://NAME/...`` ones that name a file under it (PyBullet's reading,
        pybullet_data's Panda); other ``package://`` and absolute ones are left. None: the filenames
        are left as written.

    Returns
    -------
    str
        The URDF text.
    """
    dh = np.asarray(dh, dtype=float)
    if dh.shape != derived.dh.shape:
        raise ValueError(f'dh must have shape {derived.dh.shape}, got {dh.shape}')
    tool_t = derived.tool if tool is None else np.asarray(tool, dtype=float)
    frames = kinematics.chain_frames(derived.base, dh, np.zeros(len(dh)))
    tip = frames[-1] @ tool_t
    child = [frames[k] @ _rz(dh[k, 3]) @ derived.link_offsets[k] for k in range(len(dh))]
    text, pose, k = chain.text, np.eye(4), 0
    last = max(i for i, j in enumerate(chain.joints) if j.kind in MOVING)
    for i, j in enumerate(chain.joints):
        if j.kind in MOVING:
            new = child[k]
            k += 1
        elif i == last + 1:
            rest = np.eye(4)
            for later in chain.joints[i + 1:]:
                rest = rest @ later.origin
            new = tip @ np.linalg.inv(rest)
        else:
            pose = pose @ j.origin
            continue
        text = _set_origin(text, j.name, np.linalg.inv(pose) @ new)
        pose = new
    if calibrated_tip_link(chain) != chain.tip_link:
        name = calibrated_tip_link(chain)
        extra = (f'  <link name="{name}"/>\n  <joint name="{name}_joint" type="fixed">\n'
                 f'    <parent link="{chain.tip_link}"/>\n    <child link="{name}"/>\n'
                 f'    {_origin_xml(np.linalg.inv(pose) @ tip)}\n  </joint>\n')
        cut = _masked(text).rindex('</robot>')
        text = text[:cut] + extra + text[cut:]
    if mesh_base is not None:
        base_dir = Path(mesh_base).resolve()

        def absolute(m: re.Match[str]) -> str:
            name = m.group(3)
            if name.startswith('package://') and (base_dir / name[len('package://'):]).is_file():
                name = name[len('package://'):]      # PyBullet's reading of it (pybullet_data's Panda)
            if '://' in name or Path(name).is_absolute():
                return m.group(0)
            return f'{m.group(1)}{m.group(2)}{base_dir / name}{m.group(2)}'

        text = re.sub(r'(<mesh\b[^>]*?\bfilename\s*=\s*)(["\'])(.*?)\2', absolute, text)
    return text


def model_chain(model: 'ArmModel') -> tuple[UrdfChain, DerivedDH]:  # noqa: F821 (import cycle)
    """The URDF chain of a description read from one (``model.urdf``) and its derived DH.

    Raises
    ------
    UrdfDescriptionError
        If the description was not read from a URDF.
    """
    if model.urdf is None:
        raise UrdfDescriptionError(f'robot {model.name!r} was not read from a URDF (no urdf: key)')
    chain = urdf_chain(model.urdf.path, model.urdf.base_link, model.urdf.tip_link)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', NearlyParallelAxesWarning)     # said when the description was loaded
        return chain, derive_dh(chain)


def arm_urdf(model: 'ArmModel', dh: ArrayLike, extra_links: Sequence[FixedLink] = (), *,  # noqa: F821
             chain: tuple[UrdfChain, DerivedDH] | None = None, link_mass: float = 0.0,
             collision: bool = False) -> str:
    """The arm of a description read from a URDF, as the simulator and the collision check load it.

    :func:`calibrated_urdf` of the description at ``dh`` (mesh filenames absolute), with a link
    ``hand`` (the DH frame after the last joint, where the markers are given) on the tip and
    ``extra_links`` (e.g. markers, hung from ``hand``); the links beyond the tip (a gripper) as written.

    Parameters
    ----------
    model : ArmModel
        A description with ``urdf``.
    dh : array_like, shape (L, 4)
    extra_links : sequence of FixedLink
    chain : (UrdfChain, DerivedDH), optional
        :func:`model_chain` of ``model``, if already read.
    link_mass, collision
        As :func:`body_schema.urdf.append_fixed_links` (for the added links).

    Raises
    ------
    UrdfDescriptionError
        If the description was not read from a URDF.
    """
    source, derived = model_chain(model) if chain is None else chain
    text = calibrated_urdf(source, derived, dh, model.tool, mesh_base=model.urdf.path.parent)
    hand = FixedLink('hand', calibrated_tip_link(source), np.linalg.inv(model.tool))
    return append_fixed_links(text, [hand, *extra_links], link_mass=link_mass, collision=collision)


def write_calibrated_urdf(model: 'ArmModel', dh: ArrayLike, path: str | Path) -> Path:  # noqa: F821 (import cycle)
    """Write the URDF of a description read from one (``model.urdf``), corrected to ``dh``.

    Mesh filenames relative to the source URDF are made absolute when ``path`` is in another
    directory (:func:`calibrated_urdf`'s ``mesh_base``).

    Raises
    ------
    UrdfDescriptionError
        If the description was not read from a URDF.
    """
    chain, derived = model_chain(model)
    out = Path(path)
    same_dir = out.parent.resolve() == model.urdf.path.parent
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(calibrated_urdf(chain, derived, dh, model.tool, mesh_base=None if same_dir else model.urdf.path.parent))
    return out
