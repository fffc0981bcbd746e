"""``make bench`` section: the batched acquisition optimiser against DIRECT-L 1000 on recorded states.

Records the selection states of seeded study runs (AL, UCSAL, CCSAL; seeds 0-2, every 5th of 50
iterations), then runs both optimisers on the same objective for each criterion x occlusion mode x
strategy (:mod:`tools.bench_acquisition`). About 5 minutes. Run alone: ``python -m tools.acquisition_bench``.
"""
from __future__ import annotations

import argparse
import sys

from body_schema import load_robot
from body_schema.acquisition import SelectorConfig

from .bench_acquisition import bench_table, compare, record_states

MAX_EVALS = 1000


def main(argv: list[str] | None = None) -> str:
    """Record the states, compare the optimisers and return the Markdown table (``--help``)."""
    parser = argparse.ArgumentParser(prog='python -m tools.acquisition_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, default=3, help='study seeds whose selection states are recorded (default 3: 0-2)')
    parser.add_argument('--iterations', type=int, default=50, help='iterations of each recorded study run (default 50)')
    parser.add_argument('--every', type=int, default=5, help='record the state before every N-th selection (default 5)')
    parser.add_argument('--max-evals', type=int, default=MAX_EVALS, help=f'DIRECT-L evaluations (default {MAX_EVALS})')
    args = parser.parse_args(argv)
    model = load_robot()
    states = record_states(model, ['al', 'ucsal', 'ccsal'], range(args.seeds), args.iterations, args.every)
    batch = SelectorConfig(optimizer='batch')
    return bench_table(compare(model, states, args.max_evals, batch), args.max_evals, batch)


if __name__ == '__main__':
    print(main(sys.argv[1:]))
