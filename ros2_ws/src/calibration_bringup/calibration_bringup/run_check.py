"""Is a finished run a result to trust? (``run_calibration.sh`` asks after the report; no rclpy.)

A run can finish all its iterations and still be wrong: an estimator that stopped taking
observations ends most iterations ``timeout``, a run in which no observation reached the estimate
(the hand never seen, or every sighting refused) ends at its initial guess, and an offline re-run
of the bag whose final DH table differs from the online estimate means the bag and the live graph
saw different data.
``python -m calibration_bringup.run_check DIR`` reads ``DIR/metrics.csv`` and ``DIR/report.md``
(both written by ``calibration_report``), prints one line per problem and exits 1 if there is
one, 0 otherwise.

It then reads the innovations of ``DIR/summary.json`` (the truth-free check of the noise law,
:class:`body_schema.noise.InnovationCheck`) and prints a ``CAUTION`` line per finding against the
law: exceedances of the change test's bound far beyond the expected count, or a median NIS above a
right law's. Those make the final covariance (NEES, information limit) optimistic but leave the
estimate itself usable, so they do not fail the run.
"""
from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from body_schema.noise import CAUTION_ALPHA, InnovationCheck
from calibration_interfaces.outcome import Outcome

__all__ = ['CheckSettings', 'observations_used', 'check_rows', 'dh_difference', 'check_run', 'noise_law_cautions',
           'main']

#: The report's line with the largest |offline - online| difference of the final DH tables
#: (``dh_estimator.evaluate.summary_text``).
_DH_DIFFERENCE = re.compile(r'max \|offline - online\| DH difference\s+([-+0-9.eEinfa]+)')


@dataclass(frozen=True)
class CheckSettings:
    """Thresholds of a healthy run.

    Attributes
    ----------
    max_timeouts : float
        Largest fraction of iterations that may end ``timeout`` (no estimator verdict in time).
    max_dh_difference : float
        Largest |offline re-run - online| difference of any final DH parameter [m or rad]; a
        healthy run's two agree to 1e-9.
    check_agreement : bool
        False for a resumed run's bag: its re-run starts from the resumed estimate without the
        checkpoint's covariance, so it cannot reproduce the online estimate.
    noise_law_alpha : float
        Significance of each test of the noise law against the innovations (a right law is
        cautioned against in about twice this fraction of runs).
    """

    max_timeouts: float = 0.2
    max_dh_difference: float = 1e-4
    check_agreement: bool = True
    noise_law_alpha: float = CAUTION_ALPHA

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_timeouts <= 1.0:
            raise ValueError(f'max_timeouts must be a fraction in [0, 1], got {self.max_timeouts}')
        if not self.max_dh_difference >= 0.0:
            raise ValueError(f'max_dh_difference must be >= 0, got {self.max_dh_difference}')
        if not 0.0 < self.noise_law_alpha < 1.0:
            raise ValueError(f'noise_law_alpha must be in (0, 1), got {self.noise_law_alpha}')


def observations_used(outcomes: Iterable[str]) -> int:
    """How many of a run's iteration outcomes moved the estimate: accepted, or used as an outlier
    under the robust loss (nothing else does)."""
    return sum(o in (Outcome.ACCEPTED, Outcome.OUTLIER) for o in outcomes)


def check_rows(rows: Sequence[dict[str, str]], dh_diff: float | None,
               settings: CheckSettings = CheckSettings()) -> list[str]:
    """The problems of a run, from the rows of its ``metrics.csv`` and its final DH difference.

    Parameters
    ----------
    rows : sequence of dict
        ``metrics.csv`` rows (``dh_estimator.evaluate.IterationRow`` fields as strings); row 0 is
        the initial guess.
    dh_diff : float or None
        Largest |offline - online| final DH difference (:func:`dh_difference`); None if unknown.
    settings : CheckSettings

    Returns
    -------
    list of str
        One sentence per problem; empty for a healthy run.

    Raises
    ------
    ValueError
        If there is no iteration row or no ``outcome`` column.
    """
    iterations = list(rows[1:])
    if not iterations:
        raise ValueError('metrics.csv has no iteration row')
    try:
        timeouts = sum(r['outcome'] == 'timeout' for r in iterations)
    except KeyError as exc:
        raise ValueError(f'metrics.csv has no column {exc}') from None
    problems = []
    if observations_used(r['outcome'] for r in iterations) == 0:
        seen = Counter(r['outcome'] for r in iterations).most_common()
        problems.append(f'no observation reached the estimate in {len(iterations)} iterations ('
                        + ', '.join(f'{n} {o}' for o, n in seen) + '): the final estimate is the initial '
                        'guess; check that the camera sees the marker inside the calibration box')
    if timeouts > settings.max_timeouts * len(iterations):
        problems.append(f'{timeouts} of {len(iterations)} iterations ended "timeout" (more than '
                        f'{settings.max_timeouts:.0%}): the estimator stalled or lost its inputs')
    if settings.check_agreement:
        if dh_diff is None:
            problems.append('the report does not say how far the offline re-run ends from the online estimate')
        elif not dh_diff <= settings.max_dh_difference:        # NaN too
            last = iterations[-1]
            problems.append(f'the offline re-run of the bag ends {dh_diff:.2e} (m or rad) away from the online '
                            f'estimate (limit {settings.max_dh_difference:.0e}; final position error '
                            f'{float(last["position_mm"]):.2f} mm re-run, {float(last["online_position_mm"]):.2f} mm '
                            'online): the bag and the live graph saw different data')
    return problems


def dh_difference(report: str) -> float | None:
    """The final |offline - online| DH difference the report states, None if it states none."""
    m = _DH_DIFFERENCE.search(report)
    return float(m.group(1)) if m else None


def check_run(directory: str | Path, settings: CheckSettings = CheckSettings()) -> list[str]:
    """:func:`check_rows` of ``directory/metrics.csv`` and ``directory/report.md``.

    Raises
    ------
    FileNotFoundError
        If either file is missing (the report did not run).
    """
    directory = Path(directory)
    with (directory / 'metrics.csv').open(newline='') as f:
        rows = list(csv.DictReader(f))
    return check_rows(rows, dh_difference((directory / 'report.md').read_text()), settings)


def noise_law_cautions(summary: dict, alpha: float = CheckSettings.noise_law_alpha) -> list[str]:
    """The findings against the noise law in a run's ``summary.json`` record (its ``innovations``).

    Parameters
    ----------
    summary : dict
        The record ``calibration_report`` writes; a run without innovations after the warm-up
        (or a record from before they were kept) has none, and gives no finding.
    alpha : float
        Significance of each test (:meth:`InnovationCheck.cautions`).

    Raises
    ------
    ValueError
        If the ``innovations`` entry lacks a field or holds a value of the wrong kind.
    """
    inn = summary.get('innovations')
    if not inn or inn.get('median') is None:
        return []
    try:
        check = InnovationCheck(int(inn['count']), float(inn['median']), int(inn['beyond']),
                                float(inn['probability']), float(inn['bound']))
    except KeyError as exc:
        raise ValueError(f'summary.json: innovations has no field {exc}') from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f'summary.json: innovations {inn!r} unreadable: {exc}') from None
    return check.cautions(alpha)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='run_check', description=__doc__.split('\n\n')[0])
    ap.add_argument('directory', type=Path, help="the run's output directory")
    ap.add_argument('--max-timeouts', type=float, default=CheckSettings.max_timeouts,
                    help='largest fraction of iterations that may end "timeout"')
    ap.add_argument('--max-dh-difference', type=float, default=CheckSettings.max_dh_difference,
                    help='largest |offline - online| final DH difference [m or rad]')
    ap.add_argument('--resumed', action='store_true',
                    help='the bag is the resumed part of a run: skip the offline-vs-online check')
    args = ap.parse_args(argv)
    try:
        settings = CheckSettings(args.max_timeouts, args.max_dh_difference, check_agreement=not args.resumed)
        problems = check_run(args.directory, settings)
    except (OSError, ValueError) as exc:
        print(f'run_check: {exc}', file=sys.stderr)
        return 1
    for p in problems:
        print(f'run_calibration: UNHEALTHY RUN: {p}', file=sys.stderr)
    summary = args.directory / 'summary.json'
    try:
        cautions = noise_law_cautions(json.loads(summary.read_text()), settings.noise_law_alpha) \
            if summary.exists() else []
    except (OSError, ValueError) as exc:      # json.JSONDecodeError is a ValueError
        print(f'run_check: {summary}: {exc}', file=sys.stderr)
        cautions = []
    for c in cautions:
        print(f'run_calibration: CAUTION (noise law): {c}', file=sys.stderr)
    if args.resumed:
        print('run_check: resumed run: offline-vs-online agreement not checked (the re-run of this part '
              "starts without the checkpoint's covariance)", file=sys.stderr)
    return 1 if problems else 0


if __name__ == '__main__':
    sys.exit(main())
