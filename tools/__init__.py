"""Benchmarks and studies of the calibration packages (``make bench``); not installed with the nodes.

They may import any package of ros2_ws/src; nothing there imports them (docs/architecture.md).
"""
