"""Online EKF estimation of the arm's DH parameters from hand-pose observations, as a ROS 2 node."""
