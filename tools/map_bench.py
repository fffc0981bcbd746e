"""``make bench`` section: time of one online MAP update after 50 and after 500 observations.

Synthetic observations (noise drawn from the pose-dependent model), reached online from the
paper's initial spread; the median and p90 of 20 consecutive updates. The default window of 100
observations folds older ones into the prior and bounds the cost; with every observation kept
(``window 0``) it grows with their number. Run alone: ``python -m tools.map_bench``.
"""
from __future__ import annotations

import argparse
import sys

from body_schema import load_robot

from .map_study import timing


def main(argv: list[str] | None = None) -> str:
    """Measure and return the Markdown section (``--help`` lists the options)."""
    parser = argparse.ArgumentParser(prog='python -m tools.map_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--sizes', type=int, nargs='+', default=[50, 500],
                        help='numbers of observations after which one update is timed (default 50 500)')
    parser.add_argument('--repeats', type=int, default=20, help='consecutive updates timed at each size (default 20)')
    args = parser.parse_args(argv)
    _, table = timing(load_robot(), tuple(args.sizes), args.repeats)
    return '## dh_estimator: online MAP update (tools/map_bench.py)\n\n' + table + '\n'


if __name__ == '__main__':
    print(main(sys.argv[1:]))
