"""Is a finished run a result to trust? (``run_calibration.sh`` asks after the report; no rclpy.)

A run can finish all its iterations and still be wrong: an estimator that stopped taking
observations ends most iterations ``timeout``, and an offline re-run of the bag that ends away
from the online estimate means the bag and the live graph saw different data. ``python -m
calibration_bringup.run_check DIR`` reads ``DIR/metrics.csv`` (written by the report), prints one
line per problem and exits 1 if there is one, 0 otherwise.
"""
from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = ['CheckSettings', 'check_rows', 'check_run', 'main']


@dataclass(frozen=True)
class CheckSettings:
    """Thresholds of a healthy run.

    Attributes
    ----------
    max_timeouts : float
        Largest fraction of iterations that may end ``timeout`` (no estimator verdict in time).
    max_disagreement_mm : float
        Largest difference [mm] between the offline re-run's final position error and the online
        estimate's; the orientation errors may differ by a tenth of it in degrees.
    check_agreement : bool
        False for a resumed run's bag: its re-run starts from the resumed estimate without the
        checkpoint's covariance, so it cannot reproduce the online estimate.
    """

    max_timeouts: float = 0.2
    max_disagreement_mm: float = 0.5
    check_agreement: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_timeouts <= 1.0:
            raise ValueError(f'max_timeouts must be a fraction in [0, 1], got {self.max_timeouts}')
        if not self.max_disagreement_mm >= 0.0:
            raise ValueError(f'max_disagreement_mm must be >= 0, got {self.max_disagreement_mm}')


def check_rows(rows: Sequence[dict[str, str]], settings: CheckSettings = CheckSettings()) -> list[str]:
    """The problems of a run, from the rows of its ``metrics.csv``.

    Parameters
    ----------
    rows : sequence of dict
        ``metrics.csv`` rows (``dh_estimator.evaluate.IterationRow`` fields as strings); row 0 is
        the initial guess.
    settings : CheckSettings

    Returns
    -------
    list of str
        One sentence per problem; empty for a healthy run.

    Raises
    ------
    ValueError
        If there is no iteration row or a needed column is missing.
    """
    iterations = list(rows[1:])
    if not iterations:
        raise ValueError('metrics.csv has no iteration row')
    try:
        timeouts = sum(r['outcome'] == 'timeout' for r in iterations)
        last = iterations[-1]
        d_pos = abs(float(last['position_mm']) - float(last['online_position_mm']))
        d_rot = abs(float(last['orientation_deg']) - float(last['online_orientation_deg']))
    except KeyError as exc:
        raise ValueError(f'metrics.csv has no column {exc}') from None
    problems = []
    if timeouts > settings.max_timeouts * len(iterations):
        problems.append(f'{timeouts} of {len(iterations)} iterations ended "timeout" (more than '
                        f'{settings.max_timeouts:.0%}): the estimator stalled or lost its inputs')
    if settings.check_agreement and (d_pos > settings.max_disagreement_mm
                                     or d_rot > settings.max_disagreement_mm / 10.0):
        problems.append(f'the offline re-run of the bag ends at {float(last["position_mm"]):.2f} mm / '
                        f'{float(last["orientation_deg"]):.2f} deg, the online estimate at '
                        f'{float(last["online_position_mm"]):.2f} mm / {float(last["online_orientation_deg"]):.2f} '
                        f'deg (limit {settings.max_disagreement_mm} mm): the bag and the live graph saw '
                        'different data')
    return problems


def check_run(directory: str | Path, settings: CheckSettings = CheckSettings()) -> list[str]:
    """:func:`check_rows` of ``directory/metrics.csv``.

    Raises
    ------
    FileNotFoundError
        If the directory has no ``metrics.csv`` (the report did not run).
    """
    with (Path(directory) / 'metrics.csv').open(newline='') as f:
        return check_rows(list(csv.DictReader(f)), settings)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='run_check', description=__doc__.split('\n\n')[0])
    ap.add_argument('directory', type=Path, help="the run's output directory")
    ap.add_argument('--max-timeouts', type=float, default=CheckSettings.max_timeouts,
                    help='largest fraction of iterations that may end "timeout"')
    ap.add_argument('--max-disagreement', type=float, default=CheckSettings.max_disagreement_mm,
                    help='largest offline-vs-online difference of the final position error [mm]')
    ap.add_argument('--resumed', action='store_true',
                    help='the bag is the resumed part of a run: skip the offline-vs-online check')
    args = ap.parse_args(argv)
    try:
        settings = CheckSettings(args.max_timeouts, args.max_disagreement, check_agreement=not args.resumed)
        problems = check_run(args.directory, settings)
    except (OSError, ValueError) as exc:
        print(f'run_check: {exc}', file=sys.stderr)
        return 1
    for p in problems:
        print(f'run_calibration: UNHEALTHY RUN: {p}', file=sys.stderr)
    if args.resumed:
        print('run_check: resumed run: offline-vs-online agreement not checked (the re-run of this part '
              "starts without the checkpoint's covariance)", file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
