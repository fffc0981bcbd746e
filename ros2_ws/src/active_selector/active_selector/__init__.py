"""Active joint selection (R, AL, UCSAL, CCSAL) driving the calibration loop, as a ROS 2 node."""
