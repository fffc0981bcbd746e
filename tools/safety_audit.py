"""Audit the safety of recorded runs: contacts the simulator saw, targets and paths inside the margins,
refusals, the selection time the checks cost, and the accuracy (a seed study's directories, or runs).

Per run directory (``run_calibration.sh --output DIR``, or ``seed_<S>`` of :mod:`tools.seed_study`):

* **simulator contacts**: the last ``/diagnostics`` status named
  :data:`calibration_interfaces.outcome.CONTACT_DIAGNOSTIC` in ``calibration.mcap`` (checks,
  configurations in contact, the least clearance to a static body);
* **commanded inside a margin**: every commanded target and the straight joint-space path to it
  from the configuration the arm had reached (the first from the centre of the box, where the
  simulator starts), re-checked offline with :class:`body_schema.collision.CollisionModel` at
  ``--samples`` evenly spaced points: how many come closer than their margins;
* **refusals**: the progress records' ``refused`` and ``refused_paths``, or that the selector did
  not check at all (``run_calibration.sh --no-collision-check``: ``collision_check=0`` in the run's
  ``run.env``, or ``collision_check: false`` in its records);
* **selection time**: mean ``selection_s`` and the share of it the checks took (``safety_s``),
  i.e. the ratio to the same search without them;
* **accuracy**: the report's ``summary.json`` (final flange error).

Usage::

    python -m tools.safety_audit results/ur5e-safety --robot ur5e [--samples 200]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from body_schema import load_robot
from body_schema.collision import CollisionModel
from calibration_interfaces.mcap_reader import read_messages
from calibration_interfaces.outcome import CONTACT_DIAGNOSTIC, decode_contacts
from tools.seed_study import read_run_env

__all__ = ['audit_run', 'main']


def _contacts(bag: Path) -> dict[str, Any] | None:
    last = None
    for _topic, _t, msg in read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            if status.name == CONTACT_DIAGNOSTIC:
                last = decode_contacts({v.key: v.value for v in status.values})
    if last is None:
        return None
    return {'checks': last.checks, 'contacts': last.contacts, 'pairs': {f'{a}-{b}': n for (a, b), n in last.pairs.items()},
            'min_clearance_m': last.min_clearance}


def _checked(run: Path, records: list[dict[str, Any]]) -> bool:
    """Whether the selector checked its targets: the launcher's ``run.env`` says, else the records."""
    if (run / 'run.env').exists():
        checked = read_run_env(run).get('collision_check')
        if checked is not None:
            return checked != '0'
    return all(r.get('collision_check', True) for r in records)


def audit_run(run: Path, collision: CollisionModel, samples: int = 200) -> dict[str, Any]:
    """The audit of one run directory (see the module docstring)."""
    records = [json.loads(line) for line in (run / 'progress.jsonl').read_text().splitlines() if line.strip()]
    model = collision.robot
    prev = model.calibration_box.mean(axis=1)
    targets_inside = paths_inside = 0
    least = np.inf
    t = np.arange(1, samples + 1) / samples
    for r in records:
        target = np.radians(r['target_deg'])
        path = prev + t[:, None] * (target - prev)
        slack = collision.slack(path)
        targets_inside += bool(slack[-1] < 0)
        paths_inside += bool(np.min(slack) < 0)
        least = min(least, float(np.min(slack)))
        prev = np.radians(r['reached_deg'])
    sel = np.array([r['selection_s'] for r in records])
    safety = np.array([r.get('safety_s', 0.0) for r in records])
    out: dict[str, Any] = {
        'run': run.name, 'iterations': len(records), 'checked': _checked(run, records),
        'refused': int(sum(r.get('refused', 0) for r in records)),
        'refused_paths': int(sum(r.get('refused_paths', 0) for r in records)),
        'targets_inside_margin': targets_inside, 'paths_inside_margin': paths_inside, 'least_slack_m': least,
        'selection_s': float(sel.mean()) if len(sel) else float('nan'),
        'selection_ratio': float(sel.mean() / max((sel - safety).mean(), 1e-12)) if len(sel) else float('nan'),
        'contacts': _contacts(run / 'calibration.mcap') if (run / 'calibration.mcap').exists() else None}
    summary = run / 'summary.json'
    if summary.exists():
        s = json.loads(summary.read_text())
        out['final_mm'] = s['final']['position_mm']
        out['final_deg'] = s['final']['orientation_deg']
    return out


def table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the audits and their totals."""
    lines = ['| run | iterations | sim contacts (configurations checked) | least clearance to a static body [mm] '
             '| targets / paths inside the margins | refused: inside / behind a margin | selection [s] (x without checks) '
             '| final [mm / deg] |', '|---|---|---|---|---|---|---|---|']
    for r in rows:
        c = r['contacts'] or {}
        lines.append(f"| {r['run']} | {r['iterations']} | {c.get('contacts', 'n/a')} ({c.get('checks', 'n/a')}) | "
                     f"{1e3 * c.get('min_clearance_m', float('nan')):.0f} | {r['targets_inside_margin']} / "
                     f"{r['paths_inside_margin']} | "
                     + (f"{r['refused']} / {r['refused_paths']}" if r['checked'] else 'not checked')
                     + f" | {r['selection_s']:.2f} "
                     f"({r['selection_ratio']:.2f}) | {r.get('final_mm', float('nan')):.2f} / "
                     f"{r.get('final_deg', float('nan')):.3f} |")
    finals = np.array([r['final_mm'] for r in rows if 'final_mm' in r])
    contacts = sum((r['contacts'] or {}).get('contacts', 0) for r in rows)
    ratios = np.array([r['selection_ratio'] for r in rows])
    pairs: Counter[str] = Counter()
    for r in rows:
        pairs.update((r['contacts'] or {}).get('pairs') or {})
    touched = sum(bool((r['contacts'] or {}).get('contacts')) for r in rows)
    unchecked = sum(not r['checked'] for r in rows)
    lines.append('')
    lines.append(f'{len(rows)} runs' + (f' ({unchecked} without the collision check)' if unchecked else '')
                 + f': simulator contacts {contacts}'
                 + (f' in {touched} runs (configurations per pair: '
                    f'{", ".join(f"{k} {v}" for k, v in pairs.most_common())})' if contacts else '')
                 + '; targets inside the margins '
                 f'{sum(r["targets_inside_margin"] for r in rows)}, paths {sum(r["paths_inside_margin"] for r in rows)}; '
                 f'refused {sum(r["refused"] for r in rows)} inside and {sum(r["refused_paths"] for r in rows)} behind '
                 f'a margin; selection time x{ratios.mean():.2f} (median {np.median(ratios):.2f}, '
                 f'range {ratios.min():.2f}-{ratios.max():.2f}) of the search without the checks'
                 + (f'; final flange error mean {finals.mean():.2f} mm, median {np.median(finals):.2f}, std '
                    f'{finals.std(ddof=1) if len(finals) > 1 else 0:.2f}, range {finals.min():.2f}-{finals.max():.2f}'
                    if len(finals) else ''))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.safety_audit', description=__doc__.split('\n\n')[0])
    ap.add_argument('path', type=Path, help='a run directory, or a study directory of seed_<S> runs')
    ap.add_argument('--robot', default='icub_right_arm')
    ap.add_argument('--margin', type=float, help="collision margin [m] the runs used (default: the description's)")
    ap.add_argument('--samples', type=int, default=200, help='points checked per commanded path')
    args = ap.parse_args(argv)
    collision = CollisionModel(load_robot(args.robot), args.margin)
    runs = [args.path] if (args.path / 'progress.jsonl').exists() else \
        sorted((p for p in args.path.glob('seed_*') if p.name[5:].isdigit() and (p / 'progress.jsonl').exists()),
               key=lambda p: int(p.name[5:]))
    if not runs:
        ap.error(f'{args.path}: no run (progress.jsonl) found')
    print(table([audit_run(run, collision, args.samples) for run in runs]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
