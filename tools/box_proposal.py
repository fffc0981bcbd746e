"""Propose a calibration box and check it in the simulator: the rendered visibility beside the estimate.

``body_schema.box_proposal`` proposes the box from geometry alone (body_schema may not import the
simulator); this command adds ``--check N``: render N uniform configurations of the proposed box
with the description's camera and count those where ArUco detects a marker
(``icub_sim_bridge.visibility``). Usage::

    python -m tools.box_proposal --robot my_arm.yaml [--seed 1] [--samples 512] [--check 100]
"""
from __future__ import annotations

import sys

from body_schema import box_proposal


def main(argv: list[str] | None = None) -> int:
    ap = box_proposal.parser()
    ap.description = __doc__.split('\n\n')[0]
    ap.add_argument('--check', type=int, default=0, metavar='N',
                    help='render N uniform configurations of the box and detect the markers (0: no check)')
    args = ap.parse_args(argv)
    out = box_proposal.run(args)
    if out is None:
        return 2
    model, proposal = out
    if args.check > 0:
        from icub_sim_bridge.visibility import measure_visibility

        for camera in proposal.cameras:
            res = measure_visibility(model, args.check, args.seed, eye=camera, box=proposal.box)
            print(f'# rendered ({camera}, {args.check} configurations, seed {args.seed}): a marker detected in '
                  f'{100 * res.fraction:.1f}% (+- {100 * res.stderr():.1f}); geometric estimate '
                  f'{100 * proposal.per_camera[camera]:.1f}%')
    return 0


if __name__ == '__main__':
    sys.exit(main())
