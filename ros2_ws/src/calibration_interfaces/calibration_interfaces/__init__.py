"""The interface every node package shares, at the bottom of the layering (with body_schema).

Pure modules (never import rclpy): :mod:`.contract` (topics and their QoS), :mod:`.messages`
(message conversions), :mod:`.dh_file` (the DH table file), :mod:`.outcome` (the outcome
vocabulary and the estimator's status keys) and :mod:`.parameters` (parameters described on
settings dataclasses). :mod:`.node_util` holds the helpers that need rclpy.
"""

__all__: list[str] = []  # nothing re-exported: import the modules
