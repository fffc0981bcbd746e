"""PyBullet simulation of the iCub right arm with an ArUco-marked hand and eye cameras, bridged to ROS 2."""
