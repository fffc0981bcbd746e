"""``make bench`` section: the batched acquisition optimiser against DIRECT-L 1000 on recorded states.

Records the selection states of seeded study runs (AL, UCSAL, CCSAL; seeds 0-2, every 5th of 50
iterations), then runs both optimisers on the same objective for each criterion x occlusion mode x
strategy (:mod:`tools.bench_acquisition`). About 5 minutes. Run alone: ``python -m tools.acquisition_bench``.
"""
from __future__ import annotations

import sys

from body_schema import load_robot
from body_schema.acquisition import SelectorConfig

from .bench_acquisition import bench_table, compare, record_states

MAX_EVALS = 1000


def main(argv: list[str] | None = None) -> str:
    model = load_robot()
    states = record_states(model, ['al', 'ucsal', 'ccsal'], range(3), 50, 5)
    batch = SelectorConfig(optimizer='batch')
    return bench_table(compare(model, states, MAX_EVALS, batch), MAX_EVALS, batch)


if __name__ == '__main__':
    print(main(sys.argv[1:]))
