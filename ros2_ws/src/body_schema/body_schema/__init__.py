"""Pure-Python body-schema core: chain model, kinematics, EKF, noise and occlusion models,
acquisition strategies (R, AL, UCSAL, CCSAL) and metrics. Never imports rclpy.

>>> import body_schema
>>> arm = body_schema.load_robot("icub_right_arm")
>>> arm.dh.shape
(7, 4)
"""
from .robot import ArmModel, CameraIntrinsics, MarkerPlacement, RobotDescriptionError, load_robot

__all__ = ['ArmModel', 'CameraIntrinsics', 'MarkerPlacement', 'RobotDescriptionError', 'load_robot']
