"""Validate a run's inputs before anything starts: ``python -m calibration_interfaces.validate``.

``run_calibration.sh`` calls it before it takes a domain or starts a process: the robot
description through the loader every node uses (:func:`body_schema.robot.load_robot`) and, if
given, a pose list for it (:func:`calibration_interfaces.pose_list.read_pose_list`). Prints one
line: what was checked (exit 0), or the file and the bad field (exit 2). Imports nothing heavy
(no scipy, no rclpy), so the answer comes in about a second.

Usage::

    python -m calibration_interfaces.validate --robot my_arm.yaml [--poses plan.yaml]
"""
from __future__ import annotations

import argparse
import sys

from body_schema.robot import RobotDescriptionError, load_robot

from .pose_list import PoseListError, read_pose_list

__all__ = ['main']


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m calibration_interfaces.validate', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', required=True, help='packaged robot name or YAML path')
    ap.add_argument('--poses', help='a pose list for that robot')
    args = ap.parse_args(argv)
    try:
        model = load_robot(args.robot)
    except (RobotDescriptionError, OSError) as exc:
        print(f'--robot {args.robot}: ' + ' '.join(str(exc).split()), file=sys.stderr)
        return 2
    text = f'{model.name}: {model.n_joints} joints, {len(model.obstacle_names)} static bodies'
    if args.poses:
        try:
            poses = read_pose_list(args.poses, model)
        except (PoseListError, OSError) as exc:
            print(f'--poses {args.poses}: ' + ' '.join(str(exc).split()), file=sys.stderr)
            return 2
        text += f'; {len(poses.positions)} poses'
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
