"""``make bench``: run every package's benchmark and print their Markdown tables.

Each package that has a benchmark exposes ``<package>.bench.main(argv) -> str`` returning a
Markdown section; the tables are printed and written to ``results/bench/<package>.md``.
Usage: ``python -m calibration_bringup.bench [package ...]``.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

PACKAGES = ('body_schema', 'icub_sim_bridge', 'marker_detector', 'dh_estimator', 'active_selector')


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    wanted = argv or list(PACKAGES)
    out_dir = Path('results/bench')
    out_dir.mkdir(parents=True, exist_ok=True)
    for pkg in wanted:
        try:
            mod = importlib.import_module(f'{pkg}.bench')
        except ModuleNotFoundError as exc:
            if exc.name not in (f'{pkg}.bench',):
                raise
            print(f'## {pkg}\n\n(no benchmark yet)\n')
            continue
        text = mod.main([])
        (out_dir / f'{pkg}.md').write_text(text)
        print(text, flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
