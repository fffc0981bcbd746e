"""The report of one calibration run (``calibration_report``), written next to its bag.

Re-runs the filter on the bag with :func:`dh_estimator.evaluate.evaluate_bag` (the online
estimate is scored alongside), then writes ``metrics.csv``, ``error_vs_iteration.png``,
``error_vs_movement.png``, ``report.md`` (settings, summary, what is in the bag, how to open
it) and ``summary.json`` (the headline figures, for studies over many runs: :func:`summary_record`,
and under ``environment`` the numeric environment of the machine that wrote it,
:func:`calibration_interfaces.provenance.numeric_environment`) and prints the summary.
``scripts/run_calibration.sh`` calls it after every run. A bag cut short by a crash is read up to
its last complete record; the console and ``report.md`` say how many messages were recovered and
what was lost. An empty, missing or non-MCAP bag is one line on
stderr and exit status 1.

Usage::

    calibration_report --bag DIR/calibration.mcap [--output DIR] [--title TEXT] [--wall-seconds S]
                       [--params-file estimator.yaml] [--noise-model pose_dependent|constant]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from dh_estimator.estimator import ESTIMATORS
from dh_estimator.evaluate import (Evaluation, EvaluationSettings, evaluate_bag, plot_rows, summary_text,
                                   write_csv)

from body_schema.noise import NOISE_MODELS
from calibration_interfaces import mcap_reader
from calibration_interfaces.parameters import read_params_file
from calibration_interfaces.provenance import numeric_environment

__all__ = ['bag_contents', 'safety_record', 'render_report', 'summary_record', 'estimator_params_file', 'main']


def estimator_params_file() -> Path:
    """The installed ``config/estimator.yaml`` of this package (the launcher's estimator settings)."""
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory('calibration_bringup')) / 'config' / 'estimator.yaml'


def bag_contents(path: str | Path) -> list[tuple[str, str, int]]:
    """(topic, type, message count) of every channel in an MCAP file, sorted by topic."""
    return sorted((t.name, t.type, t.count) for t in mcap_reader.summary(path).topics.values())


def safety_record(path: str | Path) -> dict[str, object]:
    """What the bag says about safety: the selector's refusals (``/calibration/progress``) and the
    simulator's last contact report (``/diagnostics``, :data:`calibration_interfaces.outcome.CONTACT_DIAGNOSTIC`).

    Keys: ``checked`` (False if any selection was made without the collision check; records from
    before the key count as checked), ``refused``, ``refused_paths``, ``pose_list`` (iterations from a pose list), ``contacts``,
    ``contact_checks``, ``contact_pairs`` (``'a-b': n``), ``min_clearance_m`` (None: no report in the bag).
    """
    from calibration_interfaces.outcome import CONTACT_DIAGNOSTIC, decode_contacts

    refused = refused_paths = pose_list = 0
    checked = True
    contact = None
    for topic, _t, msg in mcap_reader.read_messages(path, ['/calibration/progress', '/diagnostics']):
        if topic == '/calibration/progress':
            r = json.loads(msg.data)
            refused += int(r.get('refused', 0))
            refused_paths += int(r.get('refused_paths', 0))
            pose_list += r.get('source') == 'pose_list'
            checked &= bool(r.get('collision_check', True))
        else:
            for status in msg.status:
                if status.name == CONTACT_DIAGNOSTIC:
                    contact = decode_contacts({v.key: v.value for v in status.values})
    return {'checked': checked, 'refused': refused, 'refused_paths': refused_paths, 'pose_list': pose_list,
            'contacts': None if contact is None else contact.contacts,
            'contact_checks': None if contact is None else contact.checks,
            'contact_pairs': {} if contact is None else {f'{a}-{b}': n for (a, b), n in contact.pairs.items()},
            'min_clearance_m': None if contact is None or not math.isfinite(contact.min_clearance)
            else contact.min_clearance}


def render_report(ev: Evaluation, bag: Path, title: str, wall_seconds: float | None,
                  safety: dict[str, object] | None = None) -> str:
    """The Markdown report of one run."""
    last = ev.rows[-1]
    outcomes = ev.outcome_counts
    lines = [f'# Calibration run: {title}', '',
             f'Bag: `{bag.name}`' + (f'; wall time {wall_seconds:.0f} s '
                                     f'({wall_seconds / max(last.iteration, 1):.2f} s per iteration)'
                                     if wall_seconds else ''), '']
    if ev.bag is not None and ev.bag.loss:
        lines += [f'**{ev.bag.loss}.** The numbers below are from the recovered part; '
                  f'`recover {bag.name}` writes a complete copy that every bag tool opens.', '']
    lines += ['## Summary', '', '```', summary_text(ev), '```', '',
             '| | initial | final (offline re-run) | final (online) |', '|---|---|---|---|',
             f'| average position error [mm] | {ev.rows[0].position_mm:.2f} | {last.position_mm:.2f} | '
             f'{last.online_position_mm:.2f} |',
             f'| average orientation error [deg] | {ev.rows[0].orientation_deg:.2f} | {last.orientation_deg:.2f} | '
             f'{last.online_orientation_deg:.2f} |',
             f'| information limit [mm, deg] | {ev.rows[0].expected_position_mm:.2f}, '
             f'{ev.rows[0].expected_orientation_deg:.2f} | {last.expected_position_mm:.2f}, '
             f'{last.expected_orientation_deg:.2f} | |', '',
             'Errors are averages over 1000 configurations drawn uniformly in the calibration box, '
             'against the simulated robot\'s real table (`/body_schema/true`). The information limit is '
             'the error the estimate\'s own covariance implies over the same box: how far this run\'s data '
             'can take the calibration. An achieved error well above it says the estimator, not the data, '
             'is the bottleneck; one well below it says the covariance is pessimistic.', '',
             'Outcomes: ' + ', '.join(f'{k} {v}' for k, v in sorted(outcomes.items())) +
             f'; accumulated joint movement {last.movement_deg:.0f} deg.', '',
             *(_safety_lines(safety) if safety else []),
             '![error vs iteration](error_vs_iteration.png)', '',
             '![error vs movement](error_vs_movement.png)', '',
             '## Bag contents', '', '| topic | type | messages |', '|---|---|---|']
    lines += [f'| `{t}` | `{ty}` | {n} |' for t, ty, n in bag_contents(bag)]
    lines += ['', '## Open it', '',
              f'- Foxglove Studio: *Open local file* → `{bag.name}` (images, joint states, estimates).',
              f'- Full ROS 2 install: `ros2 bag play {bag.name}` (add `--clock` for sim time) or '
              f'`ros2 bag info {bag.name}`.',
              f'- Here: `bag_player --ros-args -p bag:={bag.name}` replays it; '
              f'`evaluate {bag.name} --noise-model constant` re-runs the filter with other settings.',
              '- Per-iteration numbers: `metrics.csv`; the calibrated model: `model/`.', '']
    return '\n'.join(lines)


def _safety_lines(s: dict[str, object]) -> list[str]:
    contacts = ('no contact report in the bag' if s['contacts'] is None else
                f"{s['contacts']} of {s['contact_checks']} checked configurations in contact"
                + (f" ({', '.join(f'{k} {v}' for k, v in s['contact_pairs'].items())})" if s['contact_pairs'] else '')
                + ('' if s['min_clearance_m'] is None else f"; least clearance to an obstacle {1e3 * s['min_clearance_m']:.0f} mm"))
    selector = (f"the selector refused {s['refused']} candidates inside a collision margin and "
                f"{s['refused_paths']} behind one" if s['checked']
                else 'the selector did NOT check its targets against the obstacles (collision_check off)')
    return [f"Safety: {selector}; {s['pose_list']} targets came from a pose list; simulator: {contacts}.", '']


def summary_record(ev: Evaluation, title: str, wall_seconds: float | None,
                   safety: dict[str, object] | None = None) -> dict[str, object]:
    """The run's headline figures as plain JSON values (NaN as None), the same as ``report.md``'s.

    Keys: ``title``, ``wall_seconds``, ``iterations``, ``outcomes`` (count per outcome),
    ``initial`` / ``final`` / ``online`` (``position_mm``, ``orientation_deg``), ``information_limit``,
    ``movement_deg``, ``identifiable``, ``parameters``, ``nees_identifiable``, ``nees_band`` (95 %),
    ``unidentifiable``, ``extrinsics`` (block -> ``error`` and ``sigma``, mm and deg),
    ``max_online_offline_difference``, ``innovations`` (``count``, ``median`` NIS, ``beyond`` its
    ``bound`` of chi-square ``probability``; None without updates after the warm-up), ``safety``
    (:func:`safety_record`, when given).
    """
    def num(v: float) -> float | None:
        return None if v is None or not math.isfinite(v) else float(v)

    first, last = ev.rows[0], ev.rows[-1]
    return {
        'title': title, 'wall_seconds': num(wall_seconds) if wall_seconds else None,
        'iterations': last.iteration, 'outcomes': ev.outcome_counts,
        'initial': {'position_mm': num(first.position_mm), 'orientation_deg': num(first.orientation_deg)},
        'final': {'position_mm': num(last.position_mm), 'orientation_deg': num(last.orientation_deg)},
        'online': {'position_mm': num(last.online_position_mm), 'orientation_deg': num(last.online_orientation_deg)},
        'information_limit': {'position_mm': num(last.expected_position_mm),
                              'orientation_deg': num(last.expected_orientation_deg)},
        'movement_deg': num(last.movement_deg),
        'identifiable': ev.identifiable, 'parameters': ev.parameters or int(ev.final_dh.size),
        'nees_identifiable': num(ev.nees_identifiable),
        'nees_band': None if ev.nees_band is None else list(ev.nees_band),
        'unidentifiable': list(ev.unidentifiable),
        'extrinsics': {k: {'error': [num(v) for v in e], 'sigma': [num(v) for v in sg]}
                       for k, (e, sg) in ev.extrinsics.items()},
        'max_online_offline_difference': num(ev.max_online_offline_difference),
        'innovations': None if ev.innovations is None else {
            'count': ev.innovations.count, 'median': num(ev.innovations.median), 'beyond': ev.innovations.beyond,
            'bound': ev.innovations.bound, 'probability': ev.innovations.probability},
        **({'safety': safety} if safety is not None else {}),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``calibration_report``; returns the exit status."""
    ap = argparse.ArgumentParser(prog='calibration_report', description=__doc__.split('\n\n')[0])
    ap.add_argument('--bag', type=Path, required=True, help='MCAP file of the run')
    ap.add_argument('--output', type=Path, help='report directory (default: the bag\'s)')
    ap.add_argument('--title', default='', help='one line describing the run')
    ap.add_argument('--wall-seconds', type=float, help='wall time of the run, for the report')
    ap.add_argument('--params-file', type=Path,
                    help="the estimator's parameter file of the run (the re-run uses the same settings); "
                         "default: this package's config/estimator.yaml, which scripts/run_calibration.sh uses")
    ap.add_argument('--noise-model', choices=list(NOISE_MODELS),
                    help="the estimator's noise_model during the run, if the launcher overrode the file's")
    ap.add_argument('--estimator', choices=list(ESTIMATORS),
                    help="the estimator during the run, if the launcher overrode the file's")
    ap.add_argument('--robot', help="the run's robot description (packaged name or YAML path), if the launcher "
                                    "overrode the file's")
    ap.add_argument('--camera-prior', help="the estimator's camera_prior during the run, if the launcher set it")
    ap.add_argument('--marker-prior', help="the estimator's marker_prior during the run, if the launcher set it")
    args = ap.parse_args(argv)
    out = args.output or args.bag.parent
    try:
        values = dict(read_params_file(args.params_file or estimator_params_file(), 'dh_estimator'))
        if args.noise_model is not None:
            values['noise_model'] = args.noise_model
        if args.estimator is not None:
            values['estimator'] = args.estimator
        if args.robot is not None:
            values['robot'] = args.robot
        for key in ('camera_prior', 'marker_prior'):
            if getattr(args, key) is not None:
                values[key] = getattr(args, key)
        ev = evaluate_bag(args.bag, EvaluationSettings.from_parameters(values))
        write_csv(ev.rows, out / 'metrics.csv')
        plot_rows(ev.rows, out, title=args.title)
        safety = safety_record(args.bag)
        text = render_report(ev, args.bag, args.title or args.bag.stem, args.wall_seconds, safety)
    except (FileNotFoundError, ValueError) as exc:
        print(f'calibration_report: {exc}', file=sys.stderr)
        return 1
    (out / 'report.md').write_text(text)
    # The run's nodes ran here, with this environment: whether the run repeats elsewhere depends on it.
    record = {**summary_record(ev, args.title or args.bag.stem, args.wall_seconds, safety),
              'environment': numeric_environment()}
    (out / 'summary.json').write_text(json.dumps(record, indent=1) + '\n')
    print(summary_text(ev))
    print(f'report: {out / "report.md"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
