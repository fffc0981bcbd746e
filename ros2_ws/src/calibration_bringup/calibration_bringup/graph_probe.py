"""Is a ROS graph already talking on a domain? (``run_calibration.sh --domain-id N`` asks before starting.)

``python -m calibration_bringup.graph_probe --domain-id N [--seconds S]`` joins domain ``N`` with a
probe node for ``S`` seconds (discovery of other participants takes a moment) and exits 1,
naming what it found, if any other node or topic is there; 0 if the domain is quiet. Discovery
uses the caller's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (the launcher sets LOCALHOST).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

__all__ = ['graph_on_domain', 'main']

#: Topics every node has; not evidence of another graph.
_OWN_TOPICS = {'/rosout', '/parameter_events'}


def graph_on_domain(domain_id: int, seconds: float = 2.5) -> tuple[list[str], list[str]]:
    """The other nodes and the topics seen on ``domain_id`` within ``seconds`` of discovery.

    Returns
    -------
    nodes, topics : list of str
        Fully qualified node names (not the probe) and topic names (not ``/rosout``,
        ``/parameter_events``); both empty on a quiet domain.
    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = Node('run_calibration_domain_probe', context=context, enable_rosout=False,
                start_parameter_services=False)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        nodes: list[str] = []
        topics: list[str] = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (nodes or topics):
            executor.spin_once(timeout_sec=0.05)
            nodes = [f'{ns.rstrip("/")}/{n}' for n, ns in node.get_node_names_and_namespaces()
                     if n != node.get_name()]
            topics = [t for t, _ in node.get_topic_names_and_types() if t not in _OWN_TOPICS]
        return nodes, topics
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='graph_probe', description=__doc__.split('\n\n')[0])
    ap.add_argument('--domain-id', type=int, required=True)
    ap.add_argument('--seconds', type=float, default=2.5, help='how long discovery may take')
    args = ap.parse_args(argv)
    nodes, topics = graph_on_domain(args.domain_id, args.seconds)
    if nodes or topics:
        print(f'graph_probe: ROS_DOMAIN_ID {args.domain_id} is in use: nodes {nodes or "none"}, '
              f'topics {topics or "none"}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
