"""Collision checking of an arm against its obstacles and itself (pure: no rclpy).

:class:`CollisionModel` answers two questions the selector asks before it commands anything:
does a configuration keep every checked pair of bodies at least ``margin`` apart
(:meth:`~CollisionModel.clear`), and does the straight joint-space path to it
(:meth:`~CollisionModel.path_clear`)? It also measures how far apart they are
(:meth:`~CollisionModel.distance`, :meth:`~CollisionModel.closest`).

Geometry. For a description written as a DH table the arm is the URDF this project builds from
it (:func:`body_schema.urdf.dh_chain_urdf`) with each link's drawn primitives
(:func:`body_schema.arm_visuals.model_visuals`: a cylinder along each DH link, a ball at the
joints, the hand's boxes) as its ``<collision>`` elements. For a description read from a URDF
(``urdf:``) it is that URDF's own ``<collision>`` geometry, the file's joint origins set to the
table (:func:`body_schema.urdf_model.arm_urdf`) and its root placed where the description puts
``base_link``, with the plates its markers are printed on
(:func:`body_schema.arm_visuals.marker_plates`), as the simulator's contact monitor loads it;
joints outside the chain (a gripper's fingers) are held at 0. The ``urdf`` argument takes any
URDF instead. Meshes are checked as their convex hulls (as PyBullet checks a mesh collision
shape): Coal's margins and distances are exact on convex shapes, and a hull only adds volume.
The static
bodies are the description's obstacles, scenery boxes and head
(:func:`body_schema.arm_visuals.static_bodies`). By default the arm is the description's nominal
table: on a real robot that is the maker's kinematics, millimetres from the truth, while the
estimate starts from a guess that may be decimetres off; the margin covers the difference.

Margins. A configuration is clear when every link keeps ``margin`` from every static body and
``self_margin`` from every other checked link (the description's ``collision:``; the obstacles'
poses are measured by hand, the links' relative placement is the kinematics').

Pairs. Every pair of the arm's links that are not neighbours in the chain, and every link with
every static body, except the description's ``allowed_pairs`` and the pairs that are closer than
the margin in every one of ``probe_configs`` configurations spread over the joint limits (they
touch by construction: the first link standing on the table it is mounted on, three links meeting
at a shoulder); :attr:`CollisionModel.auto_allowed` lists those.

Library: Pinocchio (forward kinematics of the URDF, geometry placements) and Coal (formerly
hpp-fcl; the narrow phase), chosen by measurement on this machine (docs/real_robot_arm.md,
"Collision checking"): all the pairs of one configuration in one C++ call, 0.12 ms for the UR5e's
82 raw pairs against 1.3 ms with PyBullet's per-pair closest points, and exact distances on the
analytic case where python-fcl 0.7 was 2 cm off.
"""
from __future__ import annotations

from dataclasses import dataclass
import coal
import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray
from scipy.stats import qmc

from .arm_visuals import drawn_arm_urdf, marker_plates, static_bodies
from .robot import ArmModel, Obstacle

__all__ = ['CollisionModel', 'Closest', 'PathCheck', 'obstacle_shape']


def obstacle_shape(o: Obstacle) -> 'coal.CollisionGeometry':
    """The Coal shape of an obstacle (centred on its pose, a cylinder along its z)."""
    if o.shape == 'box':
        return coal.Box(*o.size)
    if o.shape == 'cylinder':
        return coal.Cylinder(o.size[0], o.size[1])
    if o.shape == 'sphere':
        return coal.Sphere(o.size[0])
    raise ValueError(f'obstacle {o.name!r}: unknown shape {o.shape!r}')


@dataclass(frozen=True)
class Closest:
    """The closest checked pair at one configuration.

    Attributes
    ----------
    distance : float
        Their distance [m] (negative: penetrating, as deep as Coal measures it).
    pair : tuple of 2 str
        Link or obstacle names.
    """

    distance: float
    pair: tuple[str, str]


@dataclass(frozen=True)
class PathCheck:
    """The outcome of a straight joint-space path check.

    Attributes
    ----------
    clear : bool
        Every sample (the start excluded) keeps ``resolution / 2`` beyond its margins.
    samples : int
        Configurations checked before the answer was known.
    blocked_at : float
        Fraction of the way from start to target of the first blocked sample (NaN if clear).
    """

    clear: bool
    samples: int
    blocked_at: float = float('nan')


class CollisionModel:
    """Checks configurations and straight joint-space paths of an arm against a margin.

    Parameters
    ----------
    robot : ArmModel
        Joint names and limits, static bodies, ``collision`` settings (margin, allowed pairs).
    margin : float, optional
        Least distance [m] between a link and a static body; the description's ``collision.margin``
        if omitted.
    self_margin : float, optional
        Least distance [m] between two checked links; the description's ``collision.self_margin``,
        else ``margin``.
    dh : array_like, shape (L, 4), optional
        The arm's table (default: the description's nominal one).
    resolution : float, optional
        Path sampling [m]: no point of the arm moves more than this between two samples
        (default: half the margin, at least 5 mm).
    probe_configs : int
        Configurations over the joint limits (Sobol, seed 0) that find the always-touching pairs.
    urdf : str, optional
        An arm's URDF with ``<collision>`` elements instead of the description's geometry, its root
        link at the description's root frame: it must have the description's joints, by name (one
        configuration value each); its other joints are held at 0.

    Raises
    ------
    ValueError
        If the margin or resolution is negative or not finite, or the URDF lacks a joint.
    """

    def __init__(self, robot: ArmModel, margin: float | None = None, *, self_margin: float | None = None,
                 dh: ArrayLike | None = None, resolution: float | None = None, probe_configs: int = 128,
                 urdf: str | None = None) -> None:
        self.robot = robot
        c = robot.collision
        self.margin = float(c.margin if margin is None else margin)
        self.self_margin = float(self_margin if self_margin is not None
                                 else c.self_margin if c.self_margin is not None else self.margin)
        for name, v in (('margin', self.margin), ('self_margin', self.self_margin)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f'collision {name} must be finite and >= 0 m, got {v!r}')
        self.resolution = float(max(min(self.margin, self.self_margin) / 2, 0.005) if resolution is None
                                else resolution)
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f'path resolution must be finite and > 0 m, got {resolution!r}')
        table = robot.dh if dh is None else np.asarray(dh, dtype=float).reshape(robot.dh.shape)
        #: The URDF root link's pose in the description's root frame, (4, 4).
        self.root_T_model = np.eye(4)
        if urdf is None and robot.urdf is not None:
            urdf, self.root_T_model = _description_urdf(robot, table)
        elif urdf is None:
            urdf = drawn_arm_urdf(robot, table)
        self.urdf = urdf
        full = pin.buildModelFromXML(urdf)
        missing = [j for j in robot.joint_names if not full.existJointName(j)]
        if missing:
            raise ValueError(f'the URDF must have the joints {list(robot.joint_names)}; missing {missing}')
        geometry = pin.buildGeomFromUrdfString(full, urdf, pin.GeometryType.COLLISION)
        # Neighbours are never checked: consecutive links of the description's chain, and a link and
        # its parent in the URDF's tree (a gripper's links; read before any joint is held).
        chain = self.robot.link_names
        self._neighbours = {frozenset(p) for p in zip(chain, chain[1:])} | {
            frozenset((f.name, full.frames[full.frames[f.parentFrame].parentFrame].name))
            for f in full.frames if f.type == pin.FrameType.BODY and f.parentFrame > 0}
        held = [full.getJointId(n) for n in list(full.names)[1:] if n not in robot.joint_names]
        self.model, self.geometry = (pin.buildReducedModel(full, geometry, held, pin.neutral(full)) if held
                                     else (full, geometry))
        if self.model.nq != robot.n_joints:
            raise ValueError(f'the URDF must have one configuration value per joint of {list(robot.joint_names)}; '
                             f'it has {self.model.nq} (a continuous joint has 2)')
        # Our joint order -> Pinocchio's configuration vector.
        self._q_index = np.array([self.model.idx_qs[self.model.getJointId(j)] for j in robot.joint_names])
        for g in self.geometry.geometryObjects:
            if isinstance(g.geometry, coal.BVHModelBase):
                g.geometry.buildConvexHull(True, 'Qt')
                g.geometry = g.geometry.convex
        # Pinocchio names a link's collision objects '<link>_<k>'.
        self.body_of = [g.name.rsplit('_', 1)[0] for g in self.geometry.geometryObjects]
        self.obstacles = static_bodies(robot)
        model_T_root = np.linalg.inv(self.root_T_model)
        for o in self.obstacles:
            pose = model_T_root @ o.pose
            self.geometry.addGeometryObject(pin.GeometryObject(o.name, 0, 0, pin.SE3(pose[:3, :3], pose[:3, 3]),
                                                               obstacle_shape(o)))
            self.body_of.append(o.name)
        self.links = tuple(dict.fromkeys(b for b in self.body_of if b not in {o.name for o in self.obstacles}))
        self._static = {o.name for o in self.obstacles}
        self._data = self.model.createData()
        self.auto_allowed = self._add_pairs(probe_configs)
        #: The margin of each checked object pair [m] (static or self).
        self.pair_margins = self._margins()
        self._geometry_data = self._new_data()
        self._reach = self._pair_reach()
        self._path_data = self._new_data()
        self._target_data = self._new_data(self.resolution / 2)

    # ------------------------------------------------------------------------------ construction

    def _candidate_pairs(self) -> list[tuple[int, int]]:
        """Object pairs of bodies that are neither the same, neighbours, both static, nor allowed."""
        static = {o.name for o in self.obstacles}
        allowed = {frozenset(p) for p in self.robot.collision.allowed_pairs}
        out = []
        for i, a in enumerate(self.body_of):
            for j in range(i + 1, len(self.body_of)):
                b = self.body_of[j]
                if a == b or (a in static and b in static) or frozenset((a, b)) in allowed:
                    continue
                if frozenset((a, b)) in self._neighbours:
                    continue
                out.append((i, j))
        return out

    def _add_pairs(self, probe_configs: int) -> tuple[tuple[str, str], ...]:
        """Add the checked pairs; return the body pairs found touching at every probe."""
        candidates = self._candidate_pairs()
        for i, j in candidates:
            self.geometry.addCollisionPair(pin.CollisionPair(i, j))
        if probe_configs <= 0 or not candidates:
            return ()
        self.pair_margins = self._margins()
        data = self._new_data()
        lim = self.robot.limits
        probes = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * qmc.Sobol(lim.shape[0], rng=0).random(probe_configs)
        always = np.ones(len(candidates), dtype=bool)
        for q in probes:
            pin.computeCollisions(self.model, self._data, self.geometry, data, self._pin_q(q), False)
            always &= np.array([r.isCollision() for r in data.collisionResults])
        touching = {frozenset((self.body_of[i], self.body_of[j])) for (i, j), a in zip(candidates, always) if a}
        keep = [(i, j) for i, j in candidates if frozenset((self.body_of[i], self.body_of[j])) not in touching]
        self.geometry.removeAllCollisionPairs()
        for i, j in keep:
            self.geometry.addCollisionPair(pin.CollisionPair(i, j))
        return tuple(sorted(tuple(sorted(p)) for p in touching))

    def _margins(self) -> NDArray[np.float64]:
        return np.array([self.margin if (self.body_of[p.first] in self._static or self.body_of[p.second] in self._static)
                         else self.self_margin for p in self.geometry.collisionPairs])

    def _new_data(self, extra: float = 0.0) -> 'pin.GeometryData':
        """Geometry data whose collision requests report pairs closer than their margin + ``extra``."""
        data = pin.GeometryData(self.geometry)
        for r, m in zip(data.collisionRequests, self.pair_margins):
            r.security_margin = float(m + extra)
        return data

    def _pair_reach(self) -> NDArray[np.float64]:
        """How fast each checked object pair can close per unit of joint motion, shape (P, L) [m/rad].

        Row ``p``, column ``i``: a bound on how far the moving object of pair ``p`` (for two links, the
        one further down the chain, in the other's frame) lies from joint ``i``'s axis, if joint ``i``
        moves it relative to the other object; else 0. The bound is the lengths of the joint
        placements from joint ``i`` to the object's joint, its placement's offset and its local
        bounding box's half-diagonal (triangle inequality), so ``reach @ |dq|`` bounds how much each
        pair's distance changes along a straight joint-space step ``dq``.
        """
        m = self.model
        joints = [m.getJointId(name) for name in self.robot.joint_names]

        def chain(j: int) -> list[int]:
            out = []
            while j != 0:
                out.append(j)
                j = m.parents[j]
            return out

        def extent(k: int) -> float:
            obj = self.geometry.geometryObjects[k]
            obj.geometry.computeLocalAABB()
            aabb = obj.geometry.aabb_local
            return float(np.linalg.norm(obj.placement.translation)) + \
                float(np.linalg.norm(np.maximum(np.abs(aabb.min_), np.abs(aabb.max_))))

        def reach(k: int, moving: set[int]) -> NDArray[np.float64]:
            """Row for object k moved by the joints in ``moving``."""
            row = np.zeros(len(joints))
            parent = self.geometry.geometryObjects[k].parentJoint
            for i, ji in enumerate(joints):
                if ji not in moving:
                    continue
                length, j = 0.0, parent
                while j != ji:
                    length += float(np.linalg.norm(m.jointPlacements[j].translation))
                    j = m.parents[j]
                row[i] = length + extent(k)
            return row

        rows = []
        for pair in self.geometry.collisionPairs:
            a, b = pair.first, pair.second
            if self.body_of[a] in self._static:
                a, b = b, a
            if self.body_of[b] in self._static:       # a link and a still body: every joint above the link
                rows.append(reach(a, set(chain(self.geometry.geometryObjects[a].parentJoint))))
                continue
            ca = set(chain(self.geometry.geometryObjects[a].parentJoint))
            cb = set(chain(self.geometry.geometryObjects[b].parentJoint))
            if ca <= cb:            # b is further down: the joints between them move b in a's frame
                rows.append(reach(b, cb - ca))
            else:
                rows.append(reach(a, ca - cb))
        return np.array(rows).reshape(len(rows), len(joints))

    def _pin_q(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.zeros(self.model.nq)
        out[self._q_index] = q
        return out

    # ------------------------------------------------------------------------------ queries

    @property
    def pairs(self) -> tuple[tuple[str, str], ...]:
        """The body pairs checked (link or obstacle names), each once."""
        seen = dict.fromkeys(tuple(sorted((self.body_of[p.first], self.body_of[p.second])))
                             for p in self.geometry.collisionPairs)
        return tuple(seen)

    def _configs(self, q: ArrayLike) -> tuple[NDArray[np.float64], bool]:
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q2 = q[None] if single else q
        if q2.ndim != 2 or q2.shape[1] != self.robot.n_joints or not np.all(np.isfinite(q2)):
            raise ValueError(f'configurations must be finite, shape ({self.robot.n_joints},) or '
                             f'(N, {self.robot.n_joints}), got {q.shape}')
        return q2, single

    def clear(self, q: ArrayLike, extra: float = 0.0) -> NDArray[np.bool_] | bool:
        """Whether every checked pair keeps its margin (plus ``extra`` [m]) at each configuration.

        Parameters
        ----------
        q : array_like, shape (L,) or (N, L)
        extra : float
            Added to every pair's margin [m].

        Returns
        -------
        bool or ndarray of bool, shape (N,)
        """
        q2, single = self._configs(q)
        data = self._geometry_data if extra == 0.0 else self._new_data(extra)
        out = np.array([not pin.computeCollisions(self.model, self._data, self.geometry, data, self._pin_q(qi), True)
                        for qi in q2])
        return bool(out[0]) if single else out

    def _distances(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance [m] of every checked object pair at one configuration (L,)."""
        pin.computeDistances(self.model, self._data, self.geometry, self._geometry_data, self._pin_q(q))
        return np.array([r.min_distance for r in self._geometry_data.distanceResults])

    def pair_distances(self, q: ArrayLike) -> dict[tuple[str, str], float]:
        """Distance [m] of every checked body pair (names sorted) at one configuration (L,)."""
        q2, _ = self._configs(q)
        out: dict[tuple[str, str], float] = {}
        for p, d in zip(self.geometry.collisionPairs, self._distances(q2[0])):
            key = tuple(sorted((self.body_of[p.first], self.body_of[p.second])))
            out[key] = min(out.get(key, np.inf), float(d))
        return out

    def closest(self, q: ArrayLike) -> Closest:
        """The pair nearest to its margin at one configuration (L,), with its distance."""
        q2, _ = self._configs(q)
        if not len(self.geometry.collisionPairs):
            return Closest(float('inf'), ('', ''))
        d = self._distances(q2[0])
        k = int(np.argmin(d - self.pair_margins))
        p = self.geometry.collisionPairs[k]
        return Closest(float(d[k]), (self.body_of[p.first], self.body_of[p.second]))

    def slack(self, q: ArrayLike) -> NDArray[np.float64] | float:
        """Least ``distance - margin`` [m] over the checked pairs, shape () or (N,) (inf without pairs):
        negative inside a margin."""
        q2, single = self._configs(q)
        if not len(self.geometry.collisionPairs):
            out = np.full(len(q2), np.inf)
        else:
            out = np.array([float(np.min(self._distances(qi) - self.pair_margins)) for qi in q2])
        return float(out[0]) if single else out

    def path_bound(self, q0: ArrayLike, q1: ArrayLike) -> NDArray[np.float64]:
        """A bound [m] per checked object pair on how much its distance changes along the straight
        path ``q0 -> q1``, shape (P,) (:meth:`_pair_reach` times ``|q1 - q0|``)."""
        dq = np.abs(np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float))
        return self._reach @ dq

    def path_clear(self, q0: ArrayLike, q1: ArrayLike) -> PathCheck:
        """Whether the straight joint-space path from ``q0`` (where the arm is) to ``q1`` keeps the margins.

        Conservative advancement: at each sample every pair's slack ``s`` (distance minus margin)
        must be at least ``resolution / 2``; the next sample is as far on as no pair's distance can
        change by more than ``max(s, resolution)`` (:meth:`path_bound`, per pair: a link only moves
        with the joints above it, two links only with the joints between them). Between two
        samples every pair therefore keeps its margin: by its slack where that exceeds the step,
        else because both ends keep half the step. The start is where the arm is already: a pair it
        has inside (or within half a step of) its margin must only keep what it has there, so a path
        that leaves a margin passes and one that goes deeper does not. The target must keep
        ``resolution / 2`` beyond its margins.

        Parameters
        ----------
        q0, q1 : array_like, shape (L,)

        Returns
        -------
        PathCheck
        """
        a, _ = self._configs(q0)
        b, _ = self._configs(q1)
        a, b = a[0], b[0]
        if not len(self.geometry.collisionPairs):
            return PathCheck(True, 0)
        # The target first, keeping half a step beyond its margins: most refused paths end there.
        if pin.computeCollisions(self.model, self._data, self.geometry, self._target_data, self._pin_q(b), True):
            return PathCheck(False, 1, 1.0)
        bound = self.path_bound(a, b)                   # per pair, over the whole path
        active = bound > 0
        if not np.any(active):
            return PathCheck(True, 1)
        half, data = self.resolution / 2, self._path_data
        for k in range(len(active)):
            if active[k]:
                data.activateCollisionPair(k)
            else:
                data.deactivateCollisionPair(k)

        def slack(q: NDArray[np.float64]) -> NDArray[np.float64]:
            pin.computeDistances(self.model, self._data, self.geometry, data, self._pin_q(q))
            return np.array([r.min_distance if on else np.inf
                             for r, on in zip(data.distanceResults, active)]) - self.pair_margins

        t, samples, s = 0.0, 1, slack(a)
        # A pair the start already has inside (or near) its margin may not come closer than there.
        floor = np.minimum(half, s)
        while True:
            # A pair whose slack exceeds what the rest of the path can take from it is done with.
            done = active & (s > bound * (1.0 - t))
            if np.any(done):
                active &= ~done
                if not np.any(active):
                    return PathCheck(True, samples)
                for k in np.nonzero(done)[0]:
                    data.deactivateCollisionPair(int(k))
            t = min(1.0, t + float(np.min(np.maximum(s[active], self.resolution) / bound[active])))
            if t >= 1.0:
                return PathCheck(True, samples)
            samples += 1
            s = slack(a + t * (b - a))
            if np.any(s < floor):
                return PathCheck(False, samples, t)

    def path_distance(self, q0: ArrayLike, q1: ArrayLike, samples: int = 50) -> Closest:
        """The pair nearest to its margin over ``samples`` evenly spaced points of the straight
        path (start excluded), with its distance: what a progress record reports."""
        a, _ = self._configs(q0)
        b, _ = self._configs(q1)
        best, best_slack = Closest(float('inf'), ('', '')), float('inf')
        for t in np.arange(1, samples + 1) / samples:
            c = self.closest(a[0] + t * (b[0] - a[0]))
            m = self.margin if (c.pair[0] in self._static or c.pair[1] in self._static) else self.self_margin
            if c.distance - m < best_slack:
                best, best_slack = c, c.distance - m
        return best

    def describe(self) -> str:
        """One paragraph: margin, what is checked, what is allowed."""
        return (f'collision model of {self.robot.name}: margin {self.margin * 1e3:.0f} mm to static bodies, '
                f'{self.self_margin * 1e3:.0f} mm between links, path resolution '
                f'{self.resolution * 1e3:.0f} mm; {len(self.pairs)} body pairs checked among links '
                f'{list(self.links)} and static bodies {[o.name for o in self.obstacles]}; allowed: neighbouring '
                f'links, {[list(p) for p in self.robot.collision.allowed_pairs]} (description), '
                f'{[list(p) for p in self.auto_allowed]} (closer than the margin in every probe configuration)')


def _description_urdf(robot: ArmModel, table: NDArray[np.float64]) -> tuple[str, NDArray[np.float64]]:
    """The URDF of a description read from one, its joint origins set to ``table`` (L, 4), with
    its markers' plates, and where its root link lies in the description's root frame, (4, 4).

    The file the simulator's contact monitor loads as the arm (:func:`body_schema.urdf_model.arm_urdf`
    with :func:`body_schema.arm_visuals.marker_plates`); ``base_link`` lands where the description
    puts it (``robot.base`` is root -> DH frame 0, the derived base ``base_link`` -> DH frame 0).
    """
    from .urdf_model import arm_urdf, model_chain    # here: yourdfpy is loaded for URDF descriptions only

    chain, derived = model_chain(robot)
    text = arm_urdf(robot, table, marker_plates(robot), chain=(chain, derived), collision=True)
    root_T_base_link = robot.base @ np.linalg.inv(derived.base)
    model = pin.buildModelFromXML(text)
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    model_T_base_link = data.oMf[model.getFrameId(chain.base_link)].homogeneous   # base_link below the root
    return text, root_T_base_link @ np.linalg.inv(model_T_base_link)
