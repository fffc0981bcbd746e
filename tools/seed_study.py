"""Run the whole graph (``scripts/run_calibration.sh``) over many seeds and summarise the runs.

Each seed is one complete run in its own directory (``OUTPUT/seed_<S>``: bag, report,
``summary.json``), launched as a user would, on a free ROS domain the launcher picks; ``--jobs``
runs go at once. A seed whose ``summary.json`` exists is not run again (``--force`` re-runs it),
so an interrupted study continues where it stopped. The summary (``OUTPUT/summary.md``, also
printed) has one row per seed and the mean, median and range of the final flange error, the NEES
on the identifiable parameter combinations against its 95 % chi-square band and, where the camera
or marker pose is estimated, how many of their components lie within one and two sigma.

Usage (from the repository root; arguments after ``--`` go to every run)::

    python -m tools.seed_study --robot ur5e --strategy al --iterations 50 --seeds 1-10 --jobs 2 \\
        --output results/ur5e-study -- --camera-error "0.02 2" --marker-error "0.005 5" --no-images
"""
from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from body_schema.identifiability import average_nees_band
from calibration_interfaces.provenance import ENVIRONMENT_VARIABLES, distinct_environments, environment_differences

__all__ = ['parse_seeds', 'summarise', 'read_records', 'read_summary', 'read_run_env', 'main']

ROOT = Path(__file__).resolve().parents[1]
LAUNCHER = ROOT / 'scripts' / 'run_calibration.sh'


def parse_seeds(text: str) -> list[int]:
    """``"1-10"``, ``"1,3,7"`` or a mix (``"1-3,9"``) -> sorted distinct seeds.

    Raises
    ------
    ValueError
        If a part is not an integer or a range ``lo-hi`` with ``lo <= hi``; the message names it.
    """
    seeds: set[int] = set()
    for part in filter(None, (p.strip() for p in text.split(','))):
        lo, sep, hi = part.partition('-')
        try:
            a, b = (int(lo), int(hi)) if sep else (int(part), int(part))
        except ValueError:
            raise ValueError(f'--seeds: {part!r} is neither a seed nor a range lo-hi') from None
        if a > b or a < 0:
            raise ValueError(f'--seeds: range {part!r} is empty or negative')
        seeds.update(range(a, b + 1))
    if not seeds:
        raise ValueError(f'--seeds: no seed in {text!r}')
    return sorted(seeds)


def _run(seed: int, out: Path, common: list[str], extra: list[str]) -> tuple[int, int, float]:
    """One launcher run; (seed, exit status, wall seconds). Its console goes to ``seed_<S>.log``."""
    d = out / f'seed_{seed}'
    t0 = time.monotonic()
    with open(out / f'seed_{seed}.log', 'w') as log:
        rc = subprocess.call([str(LAUNCHER), *common, '--seed', str(seed), '--output', str(d), '--overwrite',
                              *extra], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    return seed, rc, time.monotonic() - t0


def _spread(values: Sequence[float], fmt: str) -> str:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if not v.size:
        return 'n/a'
    return (f'mean {v.mean():{fmt}}, median {np.median(v):{fmt}}, min {v.min():{fmt}}, max {v.max():{fmt}}'
            + (f', std {v.std(ddof=1):{fmt}}' if v.size > 1 else ''))


def _within(block: dict[str, Any], k: float) -> tuple[int, int]:
    """Components of an extrinsic block whose |error| <= k sigma, and how many had a truth."""
    pairs = [(e, s) for e, s in zip(block['error'], block['sigma']) if e is not None and s is not None]
    return sum(abs(e) <= k * s for e, s in pairs), len(pairs)


def _innovation_lines(rec: Sequence[dict[str, Any]]) -> list[str]:
    """The noise law's truth-free check over the runs (``innovations`` of each ``summary.json``)."""
    from calibration_bringup.run_check import noise_law_cautions

    runs = [r for r in rec if r.get('innovations')]
    if not runs:
        return []
    inn = [r['innovations'] for r in runs]
    beyond, count = sum(i['beyond'] for i in inn), sum(i['count'] for i in inn)
    p = inn[0]['probability']
    cautioned = sum(bool(noise_law_cautions(r)) for r in runs)
    return [f"- innovations after the warm-up: median NIS per run {_spread([i['median'] for i in inn], '.1f')} "
            f'(5.3 if the noise law is right, 6 dof); beyond the {p:.2%} bound in '
            f'{beyond} of {count} ({count * (1 - p):.2f} expected), in {sum(i["beyond"] > 0 for i in inn)} of '
            f'{len(inn)} runs; the health check cautions against the law in {cautioned} of {len(inn)}']


def summarise(records: dict[int, dict[str, Any]], status: dict[int, int], command: str) -> str:
    """The Markdown summary of ``records`` (seed -> ``summary.json``) and exit ``status`` (seed -> rc)."""
    seeds = sorted(records)
    blocks = sorted({b for r in records.values() for b in r.get('extrinsics', {})})
    head = ['seed', 'exit', 'accepted / iterations', 'initial [mm / deg]', 'final [mm / deg]',
            'information limit [mm / deg]', 'NEES (95% band)'] + [f'{b} within 1 / 2 sigma' for b in blocks]
    lines = [f'Command: `{command}`', '', '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for s in seeds:
        r = records[s]
        band = r.get('nees_band') or [float('nan')] * 2
        nees = r.get('nees_identifiable')
        nees_text = 'n/a' if nees is None else (f'{nees:.1f}' + ('' if band[0] <= nees <= band[1] else ' (out)'))
        cells = [str(s), str(status.get(s, '-')), f"{r['outcomes'].get('accepted', 0)} / {r['iterations']}",
                 f"{r['initial']['position_mm']:.1f} / {r['initial']['orientation_deg']:.2f}",
                 f"**{r['final']['position_mm']:.2f} / {r['final']['orientation_deg']:.3f}**",
                 f"{r['information_limit']['position_mm']:.2f} / {r['information_limit']['orientation_deg']:.3f}",
                 f'{nees_text} ({band[0]:.1f}-{band[1]:.1f})']
        for b in blocks:
            blk = r.get('extrinsics', {}).get(b)
            cells.append('n/a' if blk is None else '{0} / {2} of {1}'.format(*_within(blk, 1), _within(blk, 2)[0]))
        lines.append('| ' + ' | '.join(cells) + ' |')
    rec = [records[s] for s in seeds]
    nees = [r.get('nees_identifiable') for r in rec]
    inside = sum(1 for r, v in zip(rec, nees) if v is not None and r['nees_band'][0] <= v <= r['nees_band'][1])
    scored = [(v, r['identifiable']) for r, v in zip(rec, nees) if v is not None and r.get('identifiable')]
    if scored:
        lo, hi = average_nees_band([k for _, k in scored])
        mean = float(np.mean([v for v, _ in scored]))
        anees = (f'; average over the runs {mean:.1f}, {"inside" if lo <= mean <= hi else "OUTSIDE"} its 95% '
                 f'band {lo:.1f}-{hi:.1f} (the test over many runs; a consistent estimator has each run inside '
                 f'its own band with probability 0.95, all {len(scored)} with {0.95 ** len(scored):.2f})')
    else:
        anees = ''
    lines += ['', f'Over {len(seeds)} seeds:', '',
              f"- final position error [mm]: {_spread([r['final']['position_mm'] for r in rec], '.2f')}",
              f"- final orientation error [deg]: {_spread([r['final']['orientation_deg'] for r in rec], '.3f')}",
              f'- NEES on the identifiable combinations: {_spread(nees, ".1f")}; inside the 95% band in '
              f'{inside} of {sum(v is not None for v in nees)} runs{anees}',
              *_innovation_lines(rec),
              f"- accepted observations: {_spread([r['outcomes'].get('accepted', 0) for r in rec], '.1f')}",
              f"- wall time per run [s]: {_spread([r['wall_seconds'] for r in rec], '.0f')}"]
    for b in blocks:
        k1 = [_within(r['extrinsics'][b], 1) for r in rec if b in r.get('extrinsics', {})]
        k2 = [_within(r['extrinsics'][b], 2) for r in rec if b in r.get('extrinsics', {})]
        lines.append(f'- {b} pose components within one sigma: {sum(a for a, _ in k1)} of {sum(n for _, n in k1)} '
                     f'(a consistent estimate: about 68%); within two: {sum(a for a, _ in k2)} (about 95%)')
    envs = distinct_environments(r.get('environment') for r in rec)
    unrecorded = sum(1 for r in rec if not r.get('environment'))
    if envs:
        where = (f'one numeric environment ({_environment_text(envs[0])})' if len(envs) == 1 else
                 f'{len(envs)} numeric environments (runs of two do not repeat one another step by step: '
                 f'{"; ".join(environment_differences(envs[0], envs[1]))})')
        lines.append(f'- made on {where}' + (f'; {unrecorded} runs recorded none' if unrecorded else ''))
    failed = sorted(s for s, rc in status.items() if rc != 0)
    if failed:
        lines.append(f'- runs that exited non-zero (see `seed_<S>.log`; 1 is the launcher\'s UNHEALTHY RUN): '
                     f'{failed}')
    return '\n'.join(lines) + '\n'


def _environment_text(env: dict[str, str]) -> str:
    """The entries of a numeric environment that choose kernels, on one line."""
    keys = ('cpu', 'numpy_simd', 'blas', 'opencv', *ENVIRONMENT_VARIABLES)
    return '; '.join(f'{k} {env[k]}' for k in keys if k in env)


def read_run_env(run: Path) -> dict[str, str]:
    """The launcher's ``run.env`` of a run directory, ``KEY=VALUE`` lines as it writes them (values
    shell-quoted: ``camera_error=0.02\\ 2`` reads ``'0.02 2'``, ``body_change=''`` reads ``''``).

    Raises
    ------
    FileNotFoundError
        If the run has no ``run.env``.
    """
    env = {}
    for line in (Path(run) / 'run.env').read_text().splitlines():
        if '=' in line:
            key, value = line.split('=', 1)
            words = shlex.split(value)
            env[key] = words[0] if words else ''
    return env


def read_records(directory: Path) -> dict[int, dict[str, Any]]:
    """Each finished seed's ``summary.json`` in a study's output ``directory`` (``seed_<S>/``), by seed.

    A seed directory without ``summary.json`` (a run that failed before its report) is left out.

    Raises
    ------
    ValueError
        If a ``summary.json`` is not JSON (the message names the file).
    """
    records = {}
    for d in Path(directory).glob('seed_*'):
        f = d / 'summary.json'
        if d.name[5:].isdigit() and f.exists():
            try:
                records[int(d.name[5:])] = json.loads(f.read_text())
            except json.JSONDecodeError as exc:
                raise ValueError(f'{f}: not a summary.json ({exc})') from None
    return records


_ROW = re.compile(r'^\| (\d+) \| [^|]* \| (\d+) / (\d+) \| [^|]* \| \*\*([\d.]+) / ([\d.]+)\*\* \| '
                  r'([\d.]+) / ([\d.]+) \|', re.MULTILINE)


def read_summary(text: str) -> dict[int, dict[str, Any]]:
    """The per-seed rows of a :func:`summarise` table, as partial ``summary.json`` records.

    For a study whose run directories are gone and only its committed ``summary.md`` is left:
    each seed's ``iterations``, ``outcomes.accepted``, ``final`` and ``information_limit``
    (position [mm], orientation [deg]), rounded as printed (2 and 3 decimals).

    Raises
    ------
    ValueError
        If ``text`` holds no seed row of that table.
    """
    out = {}
    for m in _ROW.finditer(text):
        seed, accepted, iterations = (int(v) for v in m.group(1, 2, 3))
        fmm, fdeg, lmm, ldeg = (float(v) for v in m.group(4, 5, 6, 7))
        out[seed] = {'iterations': iterations, 'outcomes': {'accepted': accepted},
                     'final': {'position_mm': fmm, 'orientation_deg': fdeg},
                     'information_limit': {'position_mm': lmm, 'orientation_deg': ldeg}}
    if not out:
        raise ValueError('no seed row of a seed study summary (| seed | exit | accepted / iterations | ...) '
                         f'in the text beginning {text[:80]!r}')
    return out


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index('--') + 1:] if '--' in argv else []
    own = argv[:argv.index('--')] if '--' in argv else argv
    ap = argparse.ArgumentParser(prog='python -m tools.seed_study', description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', default='icub_right_arm')
    ap.add_argument('--strategy', default='al')
    ap.add_argument('--iterations', type=int, default=50)
    ap.add_argument('--seeds', default='1-10', help='e.g. 1-10 or 1,3,7')
    ap.add_argument('--jobs', type=int, default=2, help='runs at once (each renders and solves: about one core)')
    ap.add_argument('--output', type=Path, required=True)
    ap.add_argument('--force', action='store_true', help='re-run seeds that already have a summary.json')
    args = ap.parse_args(own)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        ap.error(str(exc))
    if args.jobs < 1:
        ap.error(f'--jobs must be at least 1, got {args.jobs}')
    out = args.output.resolve()
    out.mkdir(parents=True, exist_ok=True)
    common = ['--robot', args.robot, '--strategy', args.strategy, '--iterations', str(args.iterations)]
    todo = [s for s in seeds if args.force or not (out / f'seed_{s}' / 'summary.json').exists()]
    status: dict[int, int] = {}
    if (out / 'status.json').exists():
        status = {int(k): v for k, v in json.loads((out / 'status.json').read_text()).items()}
    print(f'seed_study: {len(todo)} of {len(seeds)} seeds to run, {args.jobs} at a time -> {out}', flush=True)
    with ThreadPoolExecutor(args.jobs) as pool:
        for seed, rc, wall in pool.map(lambda s: _run(s, out, common, extra), todo):
            status[seed] = rc
            (out / 'status.json').write_text(json.dumps(status, indent=1))
            print(f'  seed {seed}: exit {rc} in {wall:.0f} s', flush=True)
    records = {s: r for s, r in read_records(out).items() if s in seeds}
    missing = [s for s in seeds if s not in records]
    command = 'python -m tools.seed_study ' + shlex.join([*own] + (['--', *extra] if extra else []))
    text = summarise(records, status, command) if records else 'no run produced a summary.json\n'
    if missing:
        text += f'\nNo summary.json (the run failed before its report; see its log): seeds {missing}\n'
    (out / 'summary.md').write_text(text)
    print(text)
    return 0 if not missing and all(status.get(s, 0) == 0 for s in seeds) else 1


if __name__ == '__main__':
    sys.exit(main())
