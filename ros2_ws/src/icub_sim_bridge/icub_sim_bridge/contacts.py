"""The simulator's own contact check: does the simulated arm touch an obstacle or itself? (no rclpy)

Independent of the selector's :class:`body_schema.collision.CollisionModel` (Pinocchio and Coal on
the nominal table, with margins): a second headless PyBullet client holds the *real* arm (the
simulator's table) and every static body, and Bullet's own narrow phase reports contacts (distance
<= 0) at each checked configuration. The arm's collision geometry is its drawn geometry, or for a
description read from a URDF that URDF's own ``<collision>`` elements (its joint origins corrected
to the table, :mod:`icub_sim_bridge.urdf_arm`; links named as in the URDF, a gripper beyond the tip
included) with the plates the markers are printed on
(:func:`body_schema.arm_visuals.marker_plates`). Pairs not checked: neighbouring links (parent and
child for a URDF), the description's ``allowed_pairs``, and pairs Bullet finds touching at every
probe configuration (a link standing on its table, a closed gripper's fingers).
:class:`ContactMonitor` keeps the count of configurations in contact, the pairs, and the least
clearance to a static body seen.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field

import numpy as np
import pybullet as p
from numpy.typing import ArrayLike
from pybullet_utils import bullet_client
from scipy.spatial.transform import Rotation

from body_schema.arm_visuals import drawn_arm_urdf, marker_plates, static_bodies
from body_schema.robot import ArmModel, Obstacle

from .urdf_arm import load_arm_urdf, write_arm_urdf

__all__ = ['ContactReport', 'ContactMonitor', 'create_static_body']


def create_static_body(client: bullet_client.BulletClient, o: Obstacle, *, visual: bool,
                       collision: bool) -> int | None:
    """A static PyBullet body for an obstacle (visual and/or collision shape); None if nothing to create.

    An obstacle with alpha 0 has no visual shape (checked, not drawn).
    """
    kind = {'box': p.GEOM_BOX, 'cylinder': p.GEOM_CYLINDER, 'sphere': p.GEOM_SPHERE}[o.shape]
    size = ({'halfExtents': [s / 2 for s in o.size]} if o.shape == 'box' else
            {'radius': o.size[0], 'length': o.size[1]} if o.shape == 'cylinder' else {'radius': o.size[0]})
    vs = client.createVisualShape(kind, rgbaColor=list(o.rgba), **size) if visual and o.rgba[3] > 0 else -1
    cs = -1
    if collision:
        csize = dict(size)
        if o.shape == 'cylinder':                     # createCollisionShape names it height
            csize['height'] = csize.pop('length')
        cs = client.createCollisionShape(kind, **csize)
    if vs < 0 and cs < 0:
        return None
    quat = Rotation.from_matrix(o.pose[:3, :3]).as_quat().tolist()
    return client.createMultiBody(0, cs, vs, basePosition=o.pose[:3, 3].tolist(), baseOrientation=quat)


@dataclass
class ContactReport:
    """What the monitor has seen so far.

    Attributes
    ----------
    checks : int
        Configurations checked.
    contacts : int
        Of them, configurations with at least one contact.
    pairs : dict of (str, str) to int
        Configurations in contact per body pair.
    min_clearance : float
        Least distance [m] between an arm link and a static body over the checks (inf: none).
    min_clearance_pair : tuple of 2 str
    """

    checks: int = 0
    contacts: int = 0
    pairs: dict[tuple[str, str], int] = field(default_factory=dict)
    min_clearance: float = float('inf')
    min_clearance_pair: tuple[str, str] = ('', '')


class ContactMonitor:
    """Checks configurations of the simulated arm for contacts, in a headless PyBullet client of its own.

    Parameters
    ----------
    robot : ArmModel
        Joint names, limits, markers, static bodies, allowed pairs.
    dh : array_like, shape (L, 4), optional
        The simulated arm's real table (default: the description's).
    head_pose : array_like, optional
        Head joints [rad] placing the head (default: the description's).
    clearance_range : float
        Distance [m] up to which the clearance to static bodies is measured (beyond: reported as inf).
    probe_configs : int
        Configurations over the joint limits that find the pairs touching everywhere.
    """

    def __init__(self, robot: ArmModel, dh: ArrayLike | None = None, *, head_pose: ArrayLike | None = None,
                 clearance_range: float = 0.3, probe_configs: int = 64) -> None:
        self.robot = robot
        self.clearance_range = float(clearance_range)
        table = robot.dh if dh is None else np.asarray(dh, dtype=float)
        self._tmp = tempfile.mkdtemp(prefix='icub_contacts_')
        self._client = bullet_client.BulletClient(connection_mode=p.DIRECT)
        c = self._client
        path = os.path.join(self._tmp, 'arm.urdf')
        if robot.urdf is None:
            urdf = drawn_arm_urdf(robot, table, link_mass=0.01)
            with open(path, 'w') as f:
                f.write(urdf)
            self.arm = c.loadURDF(path, useFixedBase=True, flags=p.URDF_USE_SELF_COLLISION)
        else:
            from body_schema.urdf_model import model_chain

            chain, derived = model_chain(robot)
            write_arm_urdf(robot, chain, derived, table, path, marker_plates(robot), collision=True)
            self.arm = load_arm_urdf(c, path, robot, derived, flags=p.URDF_USE_SELF_COLLISION)
        info = [c.getJointInfo(self.arm, i) for i in range(c.getNumJoints(self.arm))]
        names = {j[12].decode(): i for i, j in enumerate(info)}
        joints = {j[1].decode(): i for i, j in enumerate(info)}
        self._joints = [joints[j] for j in robot.joint_names]
        if robot.urdf is None:
            self.link_of = {names[ln]: ln for ln in robot.link_names if ln in names}
            chain_index = {ln: i for i, ln in enumerate(robot.link_names)}
            neighbours = lambda a, b: abs(chain_index[a] - chain_index[b]) <= 1  # noqa: E731
        else:
            # Every link with a collision shape, the base link too (index -1), under its URDF name.
            self.link_of = {i: n for n, i in names.items() if c.getCollisionShapeData(self.arm, i)}
            if c.getCollisionShapeData(self.arm, -1):
                self.link_of[-1] = c.getBodyInfo(self.arm)[0].decode()
            parent = {j[12].decode(): (c.getBodyInfo(self.arm)[0].decode() if j[16] < 0 else info[j[16]][12].decode())
                      for j in info}
            neighbours = lambda a, b: parent.get(a) == b or parent.get(b) == a  # noqa: E731
        self.statics: dict[int, str] = {}
        for o in static_bodies(robot, head_pose):
            body = create_static_body(c, o, visual=False, collision=True)
            if body is not None:
                self.statics[body] = o.name
        allowed = {frozenset(pair) for pair in robot.collision.allowed_pairs}
        links = list(self.link_of.values())
        self._unchecked = {frozenset((a, b)) for a in links for b in links
                           if a == b or neighbours(a, b)} | allowed
        self._unchecked |= self._always_touching(probe_configs)
        self.report = ContactReport()

    def _name(self, body: int, link: int) -> str:
        if body == self.arm:
            return self.link_of.get(link, '')
        return self.statics.get(body, '')

    def _touching(self) -> set[frozenset[str]]:
        """Body pairs in contact at the present configuration (every pair, none filtered)."""
        c = self._client
        c.performCollisionDetection()
        out = set()
        for pt in c.getContactPoints(bodyA=self.arm):
            if pt[8] > 0.0:
                continue
            a, b = self._name(pt[1], pt[3]), self._name(pt[2], pt[4])
            if a and b:
                out.add(frozenset((a, b)))
        return out

    def _set(self, q: ArrayLike) -> None:
        # One call for every joint: per-joint resets cost ~50 us each.
        self._client.resetJointStatesMultiDof(self.arm, self._joints, [[float(v)] for v in np.asarray(q, dtype=float)],
                                              [[0.0]] * len(self._joints))

    def _always_touching(self, n: int) -> set[frozenset[str]]:
        if n <= 0:
            return set()
        from scipy.stats import qmc

        lim = self.robot.limits
        probes = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * qmc.Sobol(lim.shape[0], rng=1).random(n)
        always: set[frozenset[str]] | None = None
        for q in probes:
            self._set(q)
            touching = self._touching()
            always = touching if always is None else always & touching
        return always or set()

    @property
    def unchecked(self) -> set[frozenset[str]]:
        """Body pairs not reported: neighbours, allowed, touching at every probe."""
        return set(self._unchecked)

    def check(self, q: ArrayLike) -> list[tuple[str, str]]:
        """Check the arm at ``q`` (L,) [rad]; the body pairs in contact (also added to :attr:`report`)."""
        self._set(q)
        r = self.report
        r.checks += 1
        pairs = sorted(tuple(sorted(pair)) for pair in self._touching() if pair not in self._unchecked)
        if pairs:
            r.contacts += 1
            for pair in pairs:
                r.pairs[pair] = r.pairs.get(pair, 0) + 1
        for body, name in self.statics.items():
            for pt in self._client.getClosestPoints(self.arm, body, self.clearance_range):
                link = self.link_of.get(pt[3], '')
                if not link or frozenset((link, name)) in self._unchecked:
                    continue
                if pt[8] < r.min_clearance:
                    r.min_clearance, r.min_clearance_pair = float(pt[8]), (link, name)
        return pairs

    def close(self) -> None:
        """Disconnect and remove the generated files."""
        if getattr(self, '_client', None) is not None:
            try:
                self._client.disconnect()
            except p.error:
                pass
            self._client = None
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 (interpreter shutdown)
            pass
