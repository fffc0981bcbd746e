"""The topic contract of DESIGN.md section 2, as data (never imports rclpy).

The recorder, the bag player, the launch script's checks and the offline evaluation all read
the topic names and types from here, so the contract is written down once.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ContractTopic:
    """One topic of the contract.

    Attributes
    ----------
    name : str
        Absolute topic name.
    type : str
        ROS 2 type name as ``pkg/msg/Type``.
    latched : bool
        Published reliable + transient local (a fact, not a stream).
    sensor : bool
        Published with sensor-data QoS (best effort).
    """

    name: str
    type: str
    latched: bool = False
    sensor: bool = False


def _eye(eye: str) -> tuple[ContractTopic, ...]:
    return (ContractTopic(f'/camera/{eye}/image_raw', 'sensor_msgs/msg/Image', sensor=True),
            ContractTopic(f'/camera/{eye}/camera_info', 'sensor_msgs/msg/CameraInfo', latched=True),
            ContractTopic(f'/camera/{eye}/pose', 'geometry_msgs/msg/PoseStamped', latched=True))


CONTRACT: tuple[ContractTopic, ...] = (
    ContractTopic('/clock', 'rosgraph_msgs/msg/Clock'),
    ContractTopic('/joint_states', 'sensor_msgs/msg/JointState'),
    # The selector latches its current target, so a late recorder still records the first one.
    ContractTopic('/arm/command', 'trajectory_msgs/msg/JointTrajectory', latched=True),
    *_eye('left'),
    *_eye('right'),
    ContractTopic('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped'),
    ContractTopic('/markers', 'geometry_msgs/msg/PoseArray'),
    ContractTopic('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', latched=True),
    ContractTopic('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', latched=True),
    ContractTopic('/body_schema/true', 'std_msgs/msg/Float64MultiArray', latched=True),
    # Not in the DESIGN table but part of every run: the estimator's per-attempt outcome and the
    # selector's per-iteration record (JSON), which the offline evaluation aligns iterations on.
    ContractTopic('/body_schema/update_status', 'diagnostic_msgs/msg/DiagnosticStatus'),
    ContractTopic('/calibration/progress', 'std_msgs/msg/String'),
)

BY_NAME: dict[str, ContractTopic] = {t.name: t for t in CONTRACT}

#: Topics whose bandwidth dominates a bag; experiments leave them out.
IMAGE_TOPICS: tuple[str, ...] = tuple(t.name for t in CONTRACT if t.name.endswith('/image_raw'))
