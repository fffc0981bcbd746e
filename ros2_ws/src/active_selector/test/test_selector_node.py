"""The selector node in-process: without an estimate it waits, says why, and commands nothing."""
import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

import body_schema
from active_selector.selector_node import LATCHED, Phase, SelectorNode

ARM = body_schema.load_robot()


def test_waits_for_estimate_and_says_why(ros, capfd):
    node = ros.add(SelectorNode(context=ros.context, parameter_overrides=[
        Parameter('strategy', value='al'), Parameter('wait_report_period', value=0.2)]))
    probe = ros.node('probe')
    commands = []
    probe.create_subscription(JointTrajectory, '/arm/command', commands.append, 10)
    js = probe.create_publisher(JointState, '/joint_states', 10)
    cam = probe.create_publisher(PoseStamped, '/camera/left/pose', LATCHED)
    pose = PoseStamped()
    pose.header.frame_id = 'root_link'
    pose.pose.orientation.w = 1.0
    cam.publish(pose)
    ros.spin_until(lambda: js.get_subscription_count() > 0, 10.0, 'discovery')
    q = np.mean(ARM.calibration_box, axis=1)
    ros.spin_until(lambda: (js.publish(JointState(name=list(ARM.joint_names), position=q.tolist())) or
                            node.q is not None and node.camera_pose is not None), 10.0, 'joints and camera pose')
    ros.spin_for(0.6)
    assert node.phase is Phase.WAITING
    assert node.waiting_for == ['/body_schema/estimate', '/body_schema/covariance']
    assert commands == []
    err = capfd.readouterr().err
    assert 'waiting for /body_schema/estimate, /body_schema/covariance before selecting' in err
