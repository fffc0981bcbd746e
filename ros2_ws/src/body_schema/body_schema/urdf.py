"""URDF export of a standard-DH chain (the simulator's arm, and later the calibrated models).

Each DH link ``H_i = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` becomes three URDF joints:

* ``<joint>_offset`` (fixed): ``Rz(offset_i)``, parent frame -> link ``<joint>_zero``;
* ``<joint>`` (revolute about z, with the joint limits): -> link ``<joint>_link``;
* ``<joint>_dh`` (fixed): ``Tz(d_i) Tx(a_i) Rx(alpha_i)`` -> link ``<joint>_frame`` (DH frame i).

The chain hangs from ``root_link`` through a fixed ``base`` transform (H0 times the blocked torso)
to link ``arm_base``, and ends with an identity fixed joint to the hand link. A ``prefix`` names a
second arm in the same tree (every link and joint but ``root_link``, e.g. ``estimate/``).
:func:`chain_transforms` gives the same joints as parent -> child transforms (what a robot state
publisher puts on ``/tf_static`` and ``/tf``), so a URDF and its TF frames cannot disagree. Geometry is optional:
pass :class:`Visual` lists keyed by link name, and extra rigidly attached links with
:class:`FixedLink`. The string is plain URDF; nothing here imports a simulator.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = ['Visual', 'FixedLink', 'FrameTransform', 'dh_chain_urdf', 'chain_transforms', 'model_urdf',
           'append_fixed_links', 'transform_to_xyz_rpy', 'xyz_rpy_to_transform', 'link_pose']


@dataclass(frozen=True)
class Visual:
    """One visual element of a link.

    Attributes
    ----------
    shape : {'box', 'cylinder', 'sphere', 'mesh'}
    size : tuple of float
        box: full extents (x, y, z) [m]; cylinder: (radius, length) along local z; sphere:
        (radius,); mesh: scale (x, y, z).
    origin : ndarray, shape (4, 4)
        Pose of the geometry in the link frame.
    rgba : tuple of 4 floats
    filename : str
        Mesh file (mesh only).
    """

    shape: str
    size: tuple[float, ...]
    origin: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    rgba: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    filename: str = ''

    def __post_init__(self) -> None:
        want = {'box': 3, 'cylinder': 2, 'sphere': 1, 'mesh': 3}
        if self.shape not in want:
            raise ValueError(f'Visual.shape must be one of {sorted(want)}, got {self.shape!r}')
        if len(self.size) != want[self.shape] or not all(np.isfinite(s) and s > 0 for s in self.size):
            raise ValueError(f'Visual {self.shape} needs {want[self.shape]} positive sizes, got {self.size}')
        if self.shape == 'mesh' and not self.filename:
            raise ValueError('Visual mesh needs a filename')


@dataclass(frozen=True)
class FixedLink:
    """A link rigidly attached to ``parent`` at ``parent_T_link`` (4, 4)."""

    name: str
    parent: str
    parent_T_link: NDArray[np.float64]
    visuals: tuple[Visual, ...] = ()


def transform_to_xyz_rpy(t: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """URDF origin of a homogeneous transform: ``xyz`` and fixed-axis ``rpy`` (R = Rz Ry Rx).

    Parameters
    ----------
    t : array_like, shape (4, 4)

    Returns
    -------
    xyz, rpy : ndarray, shape (3,) each
    """
    t = np.asarray(t, dtype=float)
    with warnings.catch_warnings():
        # At pitch = +-90 deg scipy warns about gimbal lock but still returns an exact rotation.
        warnings.simplefilter('ignore', UserWarning)
        rpy = Rotation.from_matrix(t[:3, :3]).as_euler('xyz')
    return t[:3, 3].copy(), rpy


def xyz_rpy_to_transform(xyz: ArrayLike, rpy: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`transform_to_xyz_rpy`, shape (4, 4)."""
    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler('xyz', np.asarray(rpy, dtype=float)).as_matrix()
    t[:3, 3] = np.asarray(xyz, dtype=float)
    return t


def _num(v: float) -> str:
    return repr(float(v)) if v != 0 else '0'


def _origin(t: ArrayLike) -> str:
    xyz, rpy = transform_to_xyz_rpy(t)
    return (f'<origin xyz="{" ".join(_num(v) for v in xyz)}" '
            f'rpy="{" ".join(_num(v) for v in rpy)}"/>')


def _geometry_xml(v: Visual) -> str:
    if v.shape == 'box':
        geom = f'<box size="{" ".join(_num(s) for s in v.size)}"/>'
    elif v.shape == 'cylinder':
        geom = f'<cylinder radius="{_num(v.size[0])}" length="{_num(v.size[1])}"/>'
    elif v.shape == 'sphere':
        geom = f'<sphere radius="{_num(v.size[0])}"/>'
    else:
        geom = f'<mesh filename={quoteattr(v.filename)} scale="{" ".join(_num(s) for s in v.size)}"/>'
    return geom


def _visual_xml(v: Visual, i: int) -> str:
    rgba = ' '.join(_num(c) for c in v.rgba)
    return (f'    <visual>\n      {_origin(v.origin)}\n      <geometry>{_geometry_xml(v)}</geometry>\n'
            f'      <material name="m{i}"><color rgba="{rgba}"/></material>\n    </visual>\n')


def _collision_xml(v: Visual) -> str:
    return f'    <collision>\n      {_origin(v.origin)}\n      <geometry>{_geometry_xml(v)}</geometry>\n    </collision>\n'


def _link_xml(name: str, visuals: Sequence[Visual], counter: list[int], mass: float,
              collision: bool = False) -> str:
    body = ''
    if mass > 0:
        # A tiny inertial keeps simulators from inventing 1 kg / unit inertia per link.
        body += (f'    <inertial><mass value="{_num(mass)}"/>'
                 f'<inertia ixx="1e-6" ixy="0" ixz="0" iyy="1e-6" iyz="0" izz="1e-6"/></inertial>\n')
    for v in visuals:
        body += _visual_xml(v, counter[0])
        counter[0] += 1
    if collision:
        body += ''.join(_collision_xml(v) for v in visuals if v.shape != 'mesh')
    return f'  <link name={quoteattr(name)}>\n{body}  </link>\n'


def _fixed_xml(name: str, parent: str, child: str, t: ArrayLike) -> str:
    return (f'  <joint name={quoteattr(name)} type="fixed">\n    <parent link={quoteattr(parent)}/>'
            f'\n    <child link={quoteattr(child)}/>\n    {_origin(t)}\n  </joint>\n')


def _rz(theta: float) -> NDArray[np.float64]:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _dh_fixed(a: float, d: float, alpha: float) -> NDArray[np.float64]:
    """``Tz(d) Tx(a) Rx(alpha)``."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[1, 0, 0, a], [0, c, -s, 0], [0, s, c, d], [0, 0, 0, 1.0]])


@dataclass(frozen=True)
class FrameTransform:
    """One URDF joint as a transform: ``parent_T_child`` (4, 4), fixed or at a joint position."""

    parent: str
    child: str
    parent_T_child: NDArray[np.float64]


def _chain_joints(dh: NDArray[np.float64], names: Sequence[str], base: NDArray[np.float64], root_link: str,
                  hand_link: str, prefix: str) -> list[tuple[str, str, str, NDArray[np.float64] | None]]:
    """``(joint, parent, child, transform)`` per URDF joint in chain order; None for revolute."""
    out: list[tuple[str, str, str, NDArray[np.float64] | None]] = [
        (f'{prefix}arm_base_fixed', root_link, f'{prefix}arm_base', base)]
    parent = f'{prefix}arm_base'
    for j, (a, d, alpha, offset) in zip(names, dh):
        zero, moving, frame = f'{prefix}{j}_zero', f'{prefix}{j}_link', f'{prefix}{j}_frame'
        out += [(f'{prefix}{j}_offset', parent, zero, _rz(offset)), (f'{prefix}{j}', zero, moving, None),
                (f'{prefix}{j}_dh', moving, frame, _dh_fixed(a, d, alpha))]
        parent = frame
    out.append((f'{prefix}{hand_link}_fixed', parent, f'{prefix}{hand_link}', np.eye(4)))
    return out


def chain_transforms(dh: ArrayLike, joint_names: Sequence[str], q: ArrayLike | None = None, *,
                     base: ArrayLike | None = None, root_link: str = 'root_link', hand_link: str = 'hand',
                     prefix: str = '', extra_links: Sequence[FixedLink] = ()
                     ) -> tuple[list[FrameTransform], list[FrameTransform]]:
    """The joints of :func:`dh_chain_urdf`'s URDF as transforms: what goes on TF.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
    joint_names : sequence of str, length L
    q : array_like, shape (L,), optional
        Joint positions [rad]; without them no moving transforms are returned.
    base, root_link, hand_link, prefix, extra_links
        As for :func:`dh_chain_urdf` (extra links are named with the prefix too).

    Returns
    -------
    fixed : list of FrameTransform
        The fixed joints (``/tf_static``), chain order, then the extra links.
    moving : list of FrameTransform
        ``<joint>_zero -> <joint>_link`` = ``Rz(q)`` per revolute joint (``/tf``); empty without q.

    Raises
    ------
    ValueError
        If ``dh`` is not (L, 4) with L names, or ``q`` does not have L finite values.
    """
    dh = np.asarray(dh, dtype=float)
    if dh.ndim != 2 or dh.shape[1] != 4 or dh.shape[0] != len(joint_names):
        raise ValueError(f'dh must have shape ({len(joint_names)}, 4), got {dh.shape}')
    qv = None if q is None else np.asarray(q, dtype=float)
    if qv is not None and (qv.shape != (dh.shape[0],) or not np.all(np.isfinite(qv))):
        raise ValueError(f'q must be {dh.shape[0]} finite joint positions, got {np.ravel(qv).tolist()}')
    base_t = np.eye(4) if base is None else np.asarray(base, dtype=float)
    fixed, moving = [], []
    for i, (_joint, parent, child, t) in enumerate(_chain_joints(dh, joint_names, base_t, root_link,
                                                                  hand_link, prefix)):
        if t is not None:
            fixed.append(FrameTransform(parent, child, t))
        elif qv is not None:
            moving.append(FrameTransform(parent, child, _rz(qv[(i - 1) // 3])))
    fixed += [FrameTransform(f'{prefix}{e.parent}' if e.parent != root_link else root_link, f'{prefix}{e.name}',
                             np.asarray(e.parent_T_link, dtype=float)) for e in extra_links]
    return fixed, moving


def dh_chain_urdf(dh: ArrayLike, joint_names: Sequence[str], limits: ArrayLike, *,
                  base: ArrayLike | None = None, name: str = 'arm', root_link: str = 'root_link',
                  hand_link: str = 'hand', visuals: Mapping[str, Sequence[Visual]] | None = None,
                  extra_links: Sequence[FixedLink] = (), velocity: float = 1.0,
                  effort: float = 10.0, link_mass: float = 0.0, prefix: str = '',
                  collision: bool = False) -> str:
    """URDF text of a standard-DH serial chain.

    Parameters
    ----------
    dh : array_like, shape (L, 4)
        ``(a, d, alpha, offset)`` per joint [m, m, rad, rad].
    joint_names : sequence of str, length L
    limits : array_like, shape (L, 2)
        ``[lower, upper]`` [rad].
    base : array_like, shape (4, 4), optional
        ``root_link`` -> DH frame 0 (identity if omitted).
    name : str
        Robot name.
    root_link, hand_link : str
        Names of the first and last links.
    visuals : mapping of link name -> sequence of Visual, optional
        Geometry per link. Link names: ``root_link``, ``arm_base``, ``<joint>_zero``,
        ``<joint>_link``, ``<joint>_frame``, ``hand_link`` and the ``extra_links``.
    extra_links : sequence of FixedLink
        Links rigidly attached to any earlier link (e.g. markers on the hand).
    velocity, effort : float
        Written into every ``<limit>`` [rad/s, N m].
    link_mass : float
        If positive, every link gets this mass and a tiny inertia.
    prefix : str
        Prepended to every link and joint name except ``root_link`` (``visuals`` keys and the
        extra links' names and parents are given without it).
    collision : bool
        Also write each ``visuals`` primitive (not meshes, not the extra links') as the link's
        ``<collision>`` geometry, in the same order (what :mod:`body_schema.collision` checks).

    Returns
    -------
    str
        The URDF document.

    Raises
    ------
    ValueError
        If shapes disagree, a value is not finite, a limit interval is empty or a name repeats.
    """
    dh = np.asarray(dh, dtype=float)
    limits = np.asarray(limits, dtype=float)
    names = [str(n) for n in joint_names]
    if dh.ndim != 2 or dh.shape[1] != 4:
        raise ValueError(f'dh must have shape (L, 4), got {dh.shape}')
    if len(names) != dh.shape[0] or limits.shape != (dh.shape[0], 2):
        raise ValueError(f'{dh.shape[0]} DH rows need as many joint names (got {len(names)}) and '
                         f'limits of shape ({dh.shape[0]}, 2) (got {limits.shape})')
    if not (np.all(np.isfinite(dh)) and np.all(np.isfinite(limits))):
        raise ValueError(f'dh and limits must be finite: dh={dh.tolist()}, limits={limits.tolist()}')
    if np.any(limits[:, 0] >= limits[:, 1]):
        i = int(np.argmax(limits[:, 0] >= limits[:, 1]))
        raise ValueError(f'joint {names[i]!r}: lower limit {limits[i, 0]} not below upper {limits[i, 1]}')
    base_t = np.eye(4) if base is None else np.asarray(base, dtype=float)
    if base_t.shape != (4, 4):
        raise ValueError(f'base must have shape (4, 4), got {base_t.shape}')
    visuals = dict(visuals or {})
    counter = [0]

    visuals = {(k if k == root_link else f'{prefix}{k}'): v for k, v in visuals.items()}
    links: list[str] = [root_link]
    xml = [f'<?xml version="1.0"?>\n<robot name={quoteattr(name)}>\n']
    xml.append(_link_xml(root_link, visuals.get(root_link, ()), counter, link_mass, collision))
    limit_rows = iter(limits)
    for joint, parent, child, t in _chain_joints(dh, names, base_t, root_link, hand_link, prefix):
        links.append(child)
        xml.append(_link_xml(child, visuals.get(child, ()), counter, link_mass, collision))
        if t is not None:
            xml.append(_fixed_xml(joint, parent, child, t))
            continue
        lo, hi = next(limit_rows)
        xml.append(f'  <joint name={quoteattr(joint)} type="revolute">\n    <parent link={quoteattr(parent)}/>'
                   f'\n    <child link={quoteattr(child)}/>\n    <origin xyz="0 0 0" rpy="0 0 0"/>\n'
                   f'    <axis xyz="0 0 1"/>\n    <limit lower="{_num(lo)}" upper="{_num(hi)}" '
                   f'effort="{_num(effort)}" velocity="{_num(velocity)}"/>\n  </joint>\n')
    for extra in extra_links:
        child = f'{prefix}{extra.name}'
        parent = extra.parent if extra.parent == root_link else f'{prefix}{extra.parent}'
        if parent not in links:
            raise ValueError(f'extra link {extra.name!r}: unknown parent {extra.parent!r}')
        links.append(child)
        xml.append(_link_xml(child, list(visuals.get(child, ())) + list(extra.visuals), counter, link_mass))
        xml.append(_fixed_xml(f'{child}_fixed', parent, child, extra.parent_T_link))
    if len(set(links)) != len(links):
        dup = sorted({ln for ln in links if links.count(ln) > 1})
        raise ValueError(f'duplicate link names {dup}; rename the joints or extra links')
    unknown = sorted(set(visuals) - set(links))
    if unknown:
        raise ValueError(f'visuals given for unknown links {unknown}')
    xml.append('</robot>\n')
    return ''.join(xml)


def append_fixed_links(urdf: str, extra_links: Sequence[FixedLink], link_mass: float = 0.0,
                       collision: bool = False) -> str:
    """Any URDF document with more links rigidly attached to its links (e.g. markers on a flange).

    Parameters
    ----------
    urdf : str
        A URDF document (e.g. one read from a file, its joint origins corrected).
    extra_links : sequence of FixedLink
        Attached in order (a later one may hang from an earlier one), each on a fixed joint
        ``<name>_fixed``.
    link_mass : float
        If positive, each new link gets this mass and a tiny inertia.
    collision : bool
        Also write each new link's boxes, cylinders and spheres as its ``<collision>`` geometry.

    Returns
    -------
    str
        The document with the links inserted before ``</robot>``.

    Raises
    ------
    ValueError
        If a parent is not a link of the document, or a new name is already one.
    """
    import xml.etree.ElementTree as ET

    links = {ln.get('name') for ln in ET.fromstring(urdf).findall('link')}
    xml, counter = [], [0]
    for extra in extra_links:
        if extra.parent not in links:
            raise ValueError(f'extra link {extra.name!r}: unknown parent {extra.parent!r}')
        if extra.name in links:
            raise ValueError(f'extra link {extra.name!r}: the URDF already has a link of that name')
        links.add(extra.name)
        xml.append(_link_xml(extra.name, extra.visuals, counter, link_mass, collision))
        xml.append(_fixed_xml(f'{extra.name}_fixed', extra.parent, extra.name, extra.parent_T_link))
    cut = urdf.rindex('</robot>')
    return urdf[:cut] + ''.join(xml) + urdf[cut:]


def model_urdf(model: 'ArmModel', **kwargs) -> str:  # noqa: F821 (avoid an import cycle)
    """URDF of an :class:`~body_schema.robot.ArmModel` (its DH table, base and limits).

    Keyword arguments go to :func:`dh_chain_urdf`; ``name`` defaults to the model's name.
    """
    kwargs.setdefault('name', model.name)
    kwargs.setdefault('root_link', model.root_frame)
    return dh_chain_urdf(model.dh, model.joint_names, model.limits, base=model.base, **kwargs)


def link_pose(urdf: str, link: str, q: Mapping[str, float] | None = None) -> NDArray[np.float64]:
    """Pose of ``link`` in the URDF's root link, by walking its joints (a check of a written URDF).

    Parameters
    ----------
    urdf : str
        A URDF document as this module writes it (revolute joints about their z axis).
    link : str
    q : mapping of joint name to angle [rad], optional
        Revolute joints not given are at 0.

    Returns
    -------
    ndarray, shape (4, 4)

    Raises
    ------
    ValueError
        If a revolute joint's axis is not z, or ``link`` is not in the document.
    """
    import xml.etree.ElementTree as ET

    q = dict(q or {})
    root = ET.fromstring(urdf)
    parent_of: dict[str, tuple[str, NDArray[np.float64]]] = {}
    for j in root.findall('joint'):
        o = j.find('origin')
        t = xyz_rpy_to_transform([float(v) for v in o.get('xyz').split()], [float(v) for v in o.get('rpy').split()])
        if j.get('type') == 'revolute':
            axis = j.find('axis').get('xyz')
            if [float(v) for v in axis.split()] != [0.0, 0.0, 1.0]:
                raise ValueError(f'joint {j.get("name")!r}: axis {axis!r}, only "0 0 1" is walked')
            t = t @ _rz(q.get(j.get('name'), 0.0))
        parent_of[j.find('child').get('link')] = (j.find('parent').get('link'), t)
    if link not in parent_of and not any(ln.get('name') == link for ln in root.findall('link')):
        raise ValueError(f'link {link!r} is not in the URDF')
    pose = np.eye(4)
    while link in parent_of:
        link, t = parent_of[link]
        pose = t @ pose
    return pose
