"""The topic contract of the node graph, as data: names, types and QoS (never imports rclpy).

Every node publishes and subscribes the topics listed here with the QoS listed here; the
recorder, the bag player, the launch script's checks and the offline evaluation read the same
table, so the contract is written down once. :func:`calibration_interfaces.node_util.qos_profile`
turns a :class:`QosSpec` into an ``rclpy.qos.QoSProfile``.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

from .parameters import setting

__all__ = ['Reliability', 'Durability', 'QosSpec', 'SENSOR', 'RELIABLE', 'LATCHED', 'HISTORY', 'RECORD_DEPTH',
           'PUBLISH_TIME_SOURCE', 'ContractTopic',
           'CONTRACT', 'BY_NAME', 'IMAGE_TOPICS', 'COMPRESSED_IMAGE_TOPICS', 'IMAGE_TRANSPORTS', 'image_topic', 'topic',
           'ESTIMATE_FRAME_PREFIX', 'optical_frame', 'RUN_ID_TOPIC', 'RunSettings']


class Reliability(enum.StrEnum):
    """DDS reliability, named as rclpy's ``ReliabilityPolicy`` members (lower case)."""

    RELIABLE = 'reliable'
    BEST_EFFORT = 'best_effort'


class Durability(enum.StrEnum):
    """DDS durability, named as rclpy's ``DurabilityPolicy`` members (lower case)."""

    VOLATILE = 'volatile'
    TRANSIENT_LOCAL = 'transient_local'


@dataclass(frozen=True)
class QosSpec:
    """A keep-last QoS profile as data.

    Attributes
    ----------
    reliability : Reliability
    durability : Durability
    depth : int
        History depth (keep last).
    """

    reliability: Reliability
    durability: Durability
    depth: int

    @property
    def latched(self) -> bool:
        """Reliable + transient local: a fact a late subscriber still receives."""
        return self.durability is Durability.TRANSIENT_LOCAL and self.reliability is Reliability.RELIABLE


#: Streams of sensor data (rclpy's ``qos_profile_sensor_data``): best effort, keep last 5.
SENSOR = QosSpec(Reliability.BEST_EFFORT, Durability.VOLATILE, 5)
#: Messages that must arrive (commands, estimates, outcomes): reliable, keep last 10.
RELIABLE = QosSpec(Reliability.RELIABLE, Durability.VOLATILE, 10)
#: Latched facts (the true table, camera poses, the current target): the last one survives.
LATCHED = QosSpec(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 1)
#: Records of a run (the estimator's verdicts, the selector's iterations): a subscriber that
#: matches the publisher late (discovery between processes can take seconds on a loaded machine)
#: still receives the last 100. A volatile stream lost the first verdict that way: the selector
#: timed out on an observation the estimator had used.
HISTORY = QosSpec(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 100)
#: Keep-last depth of a recording subscriber's queue for a reliable topic: how many messages of
#: one topic may wait while the recorder's executor is busy. An rclpy executor takes one message
#: per topic per wait, so under load the fastest streams (/joint_states and /clock, 100 a second
#: each at rtf 2) back up first; at depth 100 (one second of them) a loaded run lost a fifth of
#: its joint states and logged the rest up to 2 s of sim time behind the hand poses they cover.
#: 2000 is 20 s of them; best-effort streams (images) keep the recorder's ``queue_depth``.
RECORD_DEPTH = 2000
#: What a bag's publish times are when its ``recording`` metadata says ``publish_time: source``:
#: each message's source timestamp, stamped by its publisher on the wall clock the graph's
#: processes share. Sorted by it, the messages of all topics come in the order they were
#: published, which is the order a subscriber that keeps up receives them in; the recorder's
#: arrival (log-time) order is only that while the recorder keeps up with every topic.
PUBLISH_TIME_SOURCE = 'source'


@dataclass(frozen=True)
class ContractTopic:
    """One topic of the contract.

    Attributes
    ----------
    name : str
        Absolute topic name.
    type : str
        ROS 2 type name as ``pkg/msg/Type``.
    qos : QosSpec
        What its publisher offers.
    """

    name: str
    type: str
    qos: QosSpec = RELIABLE

    @property
    def latched(self) -> bool:
        """Published reliable + transient local (a fact, not a stream)."""
        return self.qos.latched

    @property
    def sensor(self) -> bool:
        """Published best effort (sensor data)."""
        return self.qos.reliability is Reliability.BEST_EFFORT


#: How images travel (image_transport's names): ``raw`` sensor_msgs/Image on ``.../image_raw``,
#: ``compressed`` sensor_msgs/CompressedImage (JPEG or PNG) on ``.../image_raw/compressed``.
IMAGE_TRANSPORTS: tuple[str, ...] = ('raw', 'compressed')


def image_topic(camera: str, transport: str = 'raw') -> str:
    """The image topic of ``camera`` for ``transport`` (image_transport's naming).

    Raises
    ------
    ValueError
        If ``transport`` is not one of :data:`IMAGE_TRANSPORTS`.
    """
    if transport not in IMAGE_TRANSPORTS:
        raise ValueError(f'transport must be one of {list(IMAGE_TRANSPORTS)}, got {transport!r}')
    return f'/camera/{camera}/image_raw' + ('' if transport == 'raw' else f'/{transport}')


def _eye(eye: str) -> tuple[ContractTopic, ...]:
    return (ContractTopic(image_topic(eye), 'sensor_msgs/msg/Image', SENSOR),
            # Published by the simulator only when asked for (compressed_format); a real camera's
            # image_transport publishes it whenever someone subscribes.
            ContractTopic(image_topic(eye, 'compressed'), 'sensor_msgs/msg/CompressedImage', SENSOR),
            ContractTopic(f'/camera/{eye}/camera_info', 'sensor_msgs/msg/CameraInfo', LATCHED),
            ContractTopic(f'/camera/{eye}/pose', 'geometry_msgs/msg/PoseStamped', LATCHED))


CONTRACT: tuple[ContractTopic, ...] = (
    ContractTopic('/clock', 'rosgraph_msgs/msg/Clock'),
    ContractTopic('/joint_states', 'sensor_msgs/msg/JointState'),
    # The selector latches its current target, so a late recorder still records the first one.
    ContractTopic('/arm/command', 'trajectory_msgs/msg/JointTrajectory', LATCHED),
    *_eye('left'),
    *_eye('right'),
    ContractTopic('/hand_pose', 'geometry_msgs/msg/PoseWithCovarianceStamped'),
    ContractTopic('/markers', 'geometry_msgs/msg/PoseArray'),
    ContractTopic('/body_schema/estimate', 'std_msgs/msg/Float64MultiArray', LATCHED),
    ContractTopic('/body_schema/covariance', 'std_msgs/msg/Float64MultiArray', LATCHED),
    ContractTopic('/body_schema/true', 'std_msgs/msg/Float64MultiArray', LATCHED),
    # The simulated camera's and marker's real offsets from the poses the graph is told (2 x 6).
    ContractTopic('/body_schema/true_extrinsics', 'std_msgs/msg/Float64MultiArray', LATCHED),
    # URDFs for 3D views: the real arm (sim) and the estimate (estimator; links under 'estimate/').
    ContractTopic('/robot_description', 'std_msgs/msg/String', LATCHED),
    ContractTopic('/body_schema/robot_description', 'std_msgs/msg/String', LATCHED),
    # The estimator's per-attempt outcome (keys: calibration_interfaces.outcome.StatusKey) and
    # the selector's per-iteration record (JSON), which the offline evaluation aligns on.
    ContractTopic('/body_schema/update_status', 'diagnostic_msgs/msg/DiagnosticStatus', HISTORY),
    ContractTopic('/calibration/progress', 'std_msgs/msg/String', HISTORY),
    # The detector's verdict on every frame (calibration_interfaces.outcome.FrameStatus: detected,
    # no marker, bad input with the reason), so a bad frame is not mistaken for a hidden hand.
    ContractTopic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray'),
    # Which run the graph belongs to, latched by every node of a launched run (RunSettings): a
    # node that receives another id shares its domain with another run and stops.
    ContractTopic('/calibration/run_id', 'std_msgs/msg/String', LATCHED),
)

#: The topic on which every node of a launched run latches its run id.
RUN_ID_TOPIC = '/calibration/run_id'


@dataclass(frozen=True)
class RunSettings:
    """The run a node belongs to (every node executable declares it, see ``node_util.spin_node``).

    Attributes
    ----------
    run_id : str
        Latched on :data:`RUN_ID_TOPIC`; another id on the same topic means two runs share one
        ROS domain, and the node stops instead of mixing their messages. Empty: no check.
    """

    run_id: str = setting('', 'Id of the run this node belongs to (the launcher sets it); a node that '
                              'sees another run id on /calibration/run_id stops. Empty: no check')

BY_NAME: dict[str, ContractTopic] = {t.name: t for t in CONTRACT}

#: TF frame (and URDF link) prefix of the estimated arm: ``estimate/arm_base`` ... ``estimate/hand``
#: hang from the real arm's ``root_link``, so a 3D view draws the estimate as a second arm.
ESTIMATE_FRAME_PREFIX = 'estimate/'


def optical_frame(eye: str) -> str:
    """The optical frame of camera ``eye`` (z forward, x right, y down): images' ``frame_id``."""
    return f'{eye}_camera_optical_frame'

#: Topics whose bandwidth dominates a bag (either transport); experiments leave them out.
IMAGE_TOPICS: tuple[str, ...] = tuple(t.name for t in CONTRACT if t.type in ('sensor_msgs/msg/Image',
                                                                              'sensor_msgs/msg/CompressedImage'))
#: The compressed transport's image topics (a run on the raw transport has none).
COMPRESSED_IMAGE_TOPICS: tuple[str, ...] = tuple(t.name for t in CONTRACT if t.type == 'sensor_msgs/msg/CompressedImage')


def topic(name: str) -> ContractTopic:
    """The contract entry of ``name``.

    Raises
    ------
    KeyError
        If ``name`` is not a contract topic; the message lists the known names.
    """
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f'{name!r} is not a contract topic; known: {sorted(BY_NAME)}') from None
