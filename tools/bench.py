"""``make bench``: run every benchmark and print their Markdown tables.

Each benchmark is a module of this ``tools`` tree (not installed with the nodes) with
``main(argv) -> str`` returning a Markdown section; the tables are printed and written to
``results/bench/<name>.md``. Usage, from the repository root: ``python -m tools.bench [name ...]``
with names from ``BENCHMARKS``.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

#: name -> (module, argv of its main). Names are the packages (or transport) each one measures.
BENCHMARKS: dict[str, tuple[str, list[str]]] = {
    'body_schema': ('tools.kinematics_bench', []),
    'icub_sim_bridge': ('tools.sim_bench', []),
    'marker_detector': ('tools.detector_bench', []),
    # Every camera encoding and the compressed transport against rgb8; detector time at 1280x1024.
    'camera_encodings': ('tools.encoding_bench', []),
    'dh_estimator': ('tools.map_bench', []),
    'active_selector': ('tools.loop_bench', []),
    # The selector's collision check: time per configuration, path and selection; agreement with Bullet.
    'collision': ('tools.collision_bench', []),
    # Batched candidates + local refinement vs DIRECT-L 1000 on recorded selection states (~5 min).
    'acquisition': ('tools.acquisition_bench', []),
    # 640x480 frames between processes, default Fast DDS vs the shipped shared-memory profile.
    'transport': ('tools.transport_bench', ['--profile', 'default', '--profile', 'shm']),
}


def main(argv: list[str] | None = None) -> int:
    """Run the named benchmarks (all by default); 2 for an unknown name (``--help``)."""
    parser = argparse.ArgumentParser(prog='python -m tools.bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('names', nargs='*', metavar='NAME', help=f'benchmarks to run (default: all of {", ".join(BENCHMARKS)})')
    parser.add_argument('--output', default='results/bench', help='directory of the <name>.md files (default results/bench)')
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    wanted = args.names or list(BENCHMARKS)
    unknown = [w for w in wanted if w not in BENCHMARKS]
    if unknown:
        print(f'unknown benchmark(s) {unknown}; choose from {sorted(BENCHMARKS)}', file=sys.stderr)
        return 2
    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in wanted:
        module, args = BENCHMARKS[name]
        text = importlib.import_module(module).main(list(args))
        (out_dir / f'{name}.md').write_text(text)
        print(text, flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
