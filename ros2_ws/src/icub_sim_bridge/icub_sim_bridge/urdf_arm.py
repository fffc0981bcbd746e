"""A description's own URDF as the simulated arm: written with the real table and loaded into PyBullet.

Pure module (no rclpy), shared by the world (:mod:`icub_sim_bridge.world`: its visual meshes) and
the contact monitor (:mod:`icub_sim_bridge.contacts`: its collision geometry). The "real" robot is
the URDF with its joint origins corrected to the simulated table
(:func:`body_schema.urdf_model.calibrated_urdf`, the same file the estimator exports); a link
``hand`` (the DH frame after the last joint, where the markers are given) hangs from the tip, and
the links beyond the tip (a gripper) stay as written, their joints at 0.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import pybullet as p
from numpy.typing import ArrayLike, NDArray
from pybullet_utils import bullet_client
from scipy.spatial.transform import Rotation

from body_schema.robot import ArmModel
from body_schema.urdf import FixedLink
from body_schema.urdf_model import DerivedDH, UrdfChain, arm_urdf

__all__ = ['write_arm_urdf', 'load_arm_urdf', 'pose_matrix']


def write_arm_urdf(robot: ArmModel, chain: UrdfChain, derived: DerivedDH, dh: ArrayLike, path: str,
                   extra_links: Sequence[FixedLink] = (), collision: bool = False) -> None:
    """Write the description's URDF corrected to ``dh`` (L, 4), with ``hand`` and ``extra_links``
    (:func:`body_schema.urdf_model.arm_urdf`; ``collision``: the extra links' primitives collide too).

    Mesh filenames become absolute paths under the source URDF's directory (``path`` is elsewhere),
    so PyBullet finds them (pybullet_data's meshes).
    """
    with open(path, 'w') as f:
        f.write(arm_urdf(robot, dh, extra_links, chain=(chain, derived), link_mass=0.01, collision=collision))


def load_arm_urdf(client: bullet_client.BulletClient, path: str, robot: ArmModel, derived: DerivedDH,
                  flags: int = 0) -> int:
    """Load a file of :func:`write_arm_urdf` with a fixed base, ``base_link`` where the description puts it.

    Returns
    -------
    int
        The PyBullet body id.
    """
    # root frame -> base_link (H0; the derived base is base_link -> DH frame 0).
    placement = robot.base @ np.linalg.inv(derived.base)
    body = _load(client, path, placement, flags)
    base_link = robot.urdf.base_link
    if client.getBodyInfo(body)[0].decode() != base_link:
        # base_link below the URDF's root: place the root so that base_link lands on the placement.
        index = {client.getJointInfo(body, i)[12].decode(): i for i in range(client.getNumJoints(body))}
        st = client.getLinkState(body, index[base_link], computeForwardKinematics=True)
        world_t_base = pose_matrix(client, st[4], st[5])
        client.removeBody(body)
        body = _load(client, path, placement @ np.linalg.inv(world_t_base) @ placement, flags)
    return body


def _load(client: bullet_client.BulletClient, path: str, pose: NDArray[np.float64], flags: int) -> int:
    quat = Rotation.from_matrix(pose[:3, :3]).as_quat().tolist()
    return client.loadURDF(path, pose[:3, 3].tolist(), quat, useFixedBase=True,
                           flags=p.URDF_USE_INERTIA_FROM_FILE | flags)


def pose_matrix(client: bullet_client.BulletClient, xyz: Sequence[float], quat: Sequence[float]
                ) -> NDArray[np.float64]:
    """A PyBullet position and xyzw quaternion as a (4, 4) transform."""
    t = np.eye(4)
    t[:3, :3] = np.array(client.getMatrixFromQuaternion(quat)).reshape(3, 3)
    t[:3, 3] = xyz
    return t
