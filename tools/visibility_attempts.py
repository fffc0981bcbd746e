"""How well the geometric visibility prior predicts the attempts a selector actually made.

:mod:`tools.visibility_fit` fits the prior (:class:`body_schema.occlusion.VisibilityPrior`) to
uniform configurations of the box. A selector does not pick uniformly: among candidates the prior
rates alike, it picks the most informative, and those sit where the prior is most often wrong
(a hand near the image border, close to the eye). This command takes the attempts of recorded
experiment runs (``runs/<method>/repNN.mcap``: each ``/calibration/progress`` record's reached
configuration), renders each in every eye of the description with that run's real arm
(``/body_schema/true``), runs the detector on it, and scores the prior's prediction from the real
arm (no estimate error) for a grid of its ``margin`` and ``margin_marker_widths``: mean
log-likelihood per eye and attempt, and how often the hand was seen where the prior said 0.8 or
more. The attempts are those of whatever settings the runs used. Exit status 1 when a requested
run has no recording (the table then covers fewer runs), 2 when none has.

Usage (from the repository root)::

    python -m tools.visibility_attempts results/tuning-stereo --method AL --repetitions 12
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from body_schema import kinematics, load_robot
from body_schema.occlusion import VisibilityPrior
from body_schema.robot import ArmModel

from .visibility_fit import seen_by_eye

#: (margin, marker widths) scored: the fixed margin fitted to uniform configurations first.
GRID = ((0.06, 0.0), (0.04, 0.0), (0.0, 0.35), (0.02, 0.35), (0.04, 0.35), (0.0, 0.5), (0.02, 0.5), (0.04, 0.5),
        (0.0, 0.7), (0.02, 0.7))


def attempts(bag: Path, n_joints: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The real table (L, 4) and the configurations reached at the judged attempts (K, L) [rad]."""
    from calibration_interfaces.mcap_reader import read_messages
    from calibration_interfaces.messages import msg_to_table

    true, reached = None, []
    for topic, _, msg in read_messages(bag, ['/body_schema/true', '/calibration/progress']):
        if topic == '/body_schema/true':
            true = msg_to_table(msg, n_joints)
        else:
            record = json.loads(msg.data)
            if record.get('detected') is not None and record.get('reached_deg') is not None \
                    and record.get('outcome') not in ('unreachable', 'timeout', 'bad_input'):
                reached.append(np.radians(record['reached_deg']))
    if true is None:
        raise ValueError(f'{bag}: no /body_schema/true (the real arm) recorded')
    return true, np.array(reached).reshape(-1, n_joints)


def score(model: ArmModel, marker_poses: NDArray[np.float64], seen: NDArray[np.bool_],
          eyes: Sequence[str], margin: float, widths: float) -> tuple[float, int, float]:
    """Mean log-likelihood per eye and attempt, predictions >= 0.8 and how often those were seen."""
    prior = VisibilityPrior(model.camera, margin=margin, marker_side=model.marker_side_length if widths else None,
                            margin_marker_widths=widths)
    p = np.stack([prior.probability(model.camera_pose(eye), marker_poses) for eye in eyes], axis=1)
    ll = float(np.mean(np.where(seen, np.log(p), np.log1p(-p))))
    high = p >= 0.8
    return ll, int(high.sum()), float(seen[high].mean()) if high.any() else float('nan')


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.visibility_attempts', description=__doc__.split('\n\n')[0])
    ap.add_argument('output', type=Path, help='an experiment output directory with recorded runs')
    ap.add_argument('--method', default='AL')
    ap.add_argument('--repetitions', type=int, default=12, help='the first N repetitions [12]')
    args = ap.parse_args(argv)
    model = load_robot('icub_right_arm')
    eyes = ('left', 'right')
    poses, seen, missing = [], [], 0
    markers = np.stack([m.hand_T_marker for m in model.markers])
    for rep in range(args.repetitions):
        bag = args.output / 'runs' / args.method / f'rep{rep:02d}.mcap'
        if not bag.exists():
            print(f'{bag}: missing; skipped', file=sys.stderr)
            missing += 1
            continue
        true_dh, q = attempts(bag, model.n_joints)
        poses.append(kinematics.chain_frames(model.base, true_dh, q)[:, -1, None] @ markers)
        seen.append(seen_by_eye(model, true_dh, q, eyes))
    if not poses:
        print(f'{args.output}: no recorded {args.method} runs', file=sys.stderr)
        return 2
    marker_poses, seen_all = np.concatenate(poses), np.concatenate(seen)
    pl, pr, pb = seen_all[:, 0].mean(), seen_all[:, 1].mean(), seen_all.all(1).mean()
    # The selector's eye_correlation c: P(both) = c min(pl, pr) + (1 - c) pl pr.
    c = (pb - pl * pr) / (min(pl, pr) - pl * pr) if min(pl, pr) > pl * pr else float('nan')
    print(f'{len(marker_poses)} attempts of {len(poses)} {args.method} runs, each rendered in both eyes of its real '
          f'arm: seen by the left eye {100 * pl:.1f} %, the right {100 * pr:.1f} %, either '
          f'{100 * seen_all.any(1).mean():.1f} %, both {100 * pb:.1f} % (eye correlation {c:.2f}).\n')
    print('| margin | marker widths | mean log-likelihood | predictions >= 0.8 | seen there |')
    print('|---|---|---|---|---|')
    for margin, widths in GRID:
        ll, n_high, rate = score(model, marker_poses, seen_all, eyes, margin, widths)
        print(f'| {margin:g} | {widths:g} | {ll:.3f} | {n_high} | {100 * rate:.0f} % |')
    # Fewer runs than asked for: a partial table, and the exit status says so.
    return 1 if missing else 0


if __name__ == '__main__':
    raise SystemExit(main())
