"""ArUco hand-pose detection with a pose-dependent measurement-noise model, as a ROS 2 node."""
