"""Consistency of an experiment's runs: the final NEES of each recorded run against its 95 % band.

``make experiment`` records each run's non-image topics (``runs/<method>/repNN.mcap``) but scores
only the error, which needs the truth and says nothing about whether the estimator's covariance
is honest. This command re-runs the estimator on each recording with the settings that run
used (``config.json``: the ``estimator.*`` parameters of its method) through
:func:`dh_estimator.evaluate.evaluate_bag`, and prints, per run, the final NEES over the
identifiable parameter combinations, its band, and the re-run's final error next to the online
one (they agree when the re-run reproduces the run), then how many runs lie inside their band and
how the innovations after the warm-up compare with the noise law (how many beyond its 99.99 %
bound, against the 1 in 10,000 a right law gives; the median of the runs' median NIS), then the
runs' average NEES against its band over the runs (Bar-Shalom's consistency test) and how widely
their NEES spread against a consistent estimator's (:func:`nees_dispersion`: how many would be in
band were the covariance centred right, with the spread they have). Exit
status 1 when a requested run has no finished recording (the table then covers fewer runs).
``--covariance`` re-runs the recordings with another posterior covariance than the runs used
(the MAP estimator's ``covariance`` setting): the same observations, so the same estimates as long
as the change test, whose innovations the covariance enters, fires where it did (the re-run vs online
column says whether they did). ``--set estimator.NAME=VALUE`` re-runs them with any other estimator parameter
changed; two columns count the runs' outlier verdicts online and in the re-run (the
MAP estimator's ``verdict_nfev``, for one, changes only the verdicts).

Usage (from the repository root)::

    python -m tools.experiment_nees results/experiment-ours --methods AL --repetitions 20
    python -m tools.experiment_nees results/experiment-ours --covariance sandwich_white
    python -m tools.experiment_nees results/experiment-ours --set estimator.verdict_nfev=200
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from body_schema.map_estimator import COVARIANCES


def estimator_parameters(config: dict[str, Any], method: str, covariance: str = '',
                         overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The estimator node's parameters of ``method``'s runs, from an experiment's ``config.json``.

    ``covariance``, if not empty, replaces the runs' posterior covariance setting; ``overrides``
    (parameter name to value) replace or add any others.

    Raises
    ------
    KeyError
        Naming the method, if ``config.json`` has no settings for it.
    """
    try:
        settings = config['settings'][method]
    except KeyError:
        raise KeyError(f'config.json has no settings for method {method!r}; it has '
                       f'{sorted(config.get("settings", {}))}') from None
    # The initial guess comes from the bag ('recorded'), so the seeds are not needed.
    params = {k.split('.', 1)[1]: v for k, v in settings.items() if k.startswith('estimator.')}
    return params | ({'covariance': covariance} if covariance else {}) | (overrides or {})


def parse_override(text: str) -> tuple[str, Any]:
    """``estimator.NAME=VALUE`` (the experiment's ``--set`` form and typing) -> ``(NAME, VALUE)``.

    Raises
    ------
    ValueError
        Naming ``text``, if it is not ``NODE.NAME=VALUE``, its node is not the estimator or the
        estimator has no such parameter.
    """
    from calibration_bringup.experiment import parse_override as parse
    from calibration_interfaces.parameters import parameter_specs
    from dh_estimator.node_settings import SETTINGS

    node, name, value = parse(text)
    if node != 'estimator':
        raise ValueError(f'--set {text!r}: only estimator parameters reach the re-run')
    # A misspelt name would otherwise re-run silently with the runs' own settings.
    known = {p.name for cls in SETTINGS for p in parameter_specs(cls)}
    if name not in known:
        raise ValueError(f'--set {text!r}: the estimator has no parameter {name!r}')
    return name, value


def nees_dispersion(nees: Sequence[float], dofs: Sequence[int]) -> dict[str, float]:
    """How the runs' final NEES spread, against how a consistent estimator's would.

    A consistent estimator's NEES is chi-square with ``k`` degrees of freedom, so ``log NEES`` has
    mean ``digamma(k/2) + log 2`` and standard deviation ``sqrt(trigamma(k/2))`` (0.27 for k = 28).
    Runs whose NEES spreads wider than that miss their per-run band however well the covariance is
    centred; ``in_band_if_centred`` is the share of runs a log-normal NEES with the runs' own spread
    of ``log NEES``, centred where a consistent one is, would put inside the 95 % band (about 0.95
    at the chi-square's own spread). The average NEES and its band over the runs are Bar-Shalom's
    test of consistency over many runs (:func:`body_schema.identifiability.average_nees_band`).

    Parameters
    ----------
    nees : sequence of float, length N >= 2
        Each run's final NEES.
    dofs : sequence of int, length N
        Each run's NEES degrees of freedom.

    Returns
    -------
    dict
        ``average``, ``average_band`` (lo, hi), ``log_sd``, ``chi2_log_sd`` (at the mean dof) and
        ``in_band_if_centred``.

    Raises
    ------
    ValueError
        If fewer than two runs are given, the lengths differ or a NEES is not positive.
    """
    from scipy import special, stats

    from body_schema.identifiability import average_nees_band

    x, k = np.asarray(nees, dtype=float), np.asarray(dofs, dtype=float)
    if x.size < 2 or x.shape != k.shape:
        raise ValueError(f'nees_dispersion needs >= 2 runs and one dof per run, got {x.size} NEES and {k.size} dofs')
    if np.any(~np.isfinite(x) | (x <= 0)):
        raise ValueError(f'nees_dispersion: every NEES must be finite and > 0, got {x.tolist()}')
    log_sd = float(np.std(np.log(x), ddof=1))
    centre = special.digamma(k / 2) + np.log(2.0)
    lo, hi = np.array([average_nees_band([int(d)]) for d in k]).T         # each run's own band
    inside = stats.norm.cdf((np.log(hi) - centre) / log_sd) - stats.norm.cdf((np.log(lo) - centre) / log_sd)
    return {'average': float(x.mean()), 'average_band': average_nees_band([int(d) for d in k]),
            'log_sd': log_sd, 'chi2_log_sd': float(np.sqrt(special.polygamma(1, k.mean() / 2))),
            'in_band_if_centred': float(inside.mean())}


def run_nees(root: Path, method: str, repetitions: Sequence[int], covariance: str = '',
             overrides: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """NEES and final errors of ``method``'s recorded runs ``repetitions`` under ``root`` (re-run with
    the posterior ``covariance`` if not empty, else the runs' own, and the estimator parameters
    ``overrides``)."""
    from dh_estimator.evaluate import EvaluationSettings, evaluate_bag

    config = json.loads((root / 'config.json').read_text())
    settings = EvaluationSettings.from_parameters(estimator_parameters(config, method, covariance, overrides))
    out = []
    for rep in repetitions:
        bag = root / 'runs' / method / f'rep{rep:02d}.mcap'
        table = root / 'runs' / method / f'rep{rep:02d}.csv'
        if not bag.exists() or not table.exists():
            print(f'{method} rep {rep}: no finished recording ({bag.name}); skipped', file=sys.stderr)
            continue
        with table.open(newline='') as f:
            records = list(csv.DictReader(f))
        online = max(records, key=lambda r: int(r['iteration']))
        ev = evaluate_bag(bag, settings)
        lo, hi = ev.nees_band or (float('nan'), float('nan'))
        inn = ev.innovations
        out.append({'method': method, 'repetition': rep, 'nees': ev.nees_identifiable, 'band': (lo, hi),
                    'dof': ev.identifiable,
                    'in_band': bool(lo <= ev.nees_identifiable <= hi),
                    'position_mm': ev.rows[-1].position_mm, 'online_position_mm': float(online['position_mm']),
                    'innovations': 0 if inn is None else inn.count, 'beyond': 0 if inn is None else inn.beyond,
                    'median_nis': float('nan') if inn is None else inn.median,
                    'online_outliers': sum(r['outcome'] == 'outlier' for r in records),
                    'outlier_verdicts': ev.counters.get('outlier_verdicts', 0)})
    return out


def _dispersion_cells(rows: Sequence[dict[str, Any]]) -> str:
    """The table's last three cells (n/a below two runs with a NEES)."""
    usable = [r for r in rows if np.isfinite(r['nees']) and r['nees'] > 0]
    if len(usable) < 2:
        return 'n/a | n/a | n/a'
    d = nees_dispersion([r['nees'] for r in usable], [r['dof'] for r in usable])
    lo, hi = d['average_band']
    return (f'{d["average"]:.1f} ({lo:.1f}-{hi:.1f}) | {d["log_sd"]:.2f} ({d["chi2_log_sd"]:.2f}) | '
            f'{d["in_band_if_centred"] * len(usable):.1f} of {len(usable)}')


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m tools.experiment_nees', description=__doc__.split('\n\n')[0])
    ap.add_argument('output', type=Path, help='an experiment output directory (config.json, runs/)')
    ap.add_argument('--methods', nargs='+', default=['AL'])
    ap.add_argument('--repetitions', type=int, default=20, help='the first N repetitions [20]')
    ap.add_argument('--covariance', choices=COVARIANCES, default='',
                    help="re-run with this posterior covariance instead of the runs' own")
    ap.add_argument('--set', action='append', default=[], metavar='estimator.NAME=VALUE', dest='overrides',
                    help='re-run with this estimator parameter changed (repeatable)')
    args = ap.parse_args(argv)
    try:
        overrides = dict(parse_override(o) for o in args.overrides)
    except ValueError as exc:
        print(f'experiment_nees: {exc}', file=sys.stderr)
        return 2
    if not (args.output / 'config.json').exists():
        print(f'{args.output}: no config.json (not an experiment output directory)', file=sys.stderr)
        return 2
    first = json.loads((args.output / 'config.json').read_text())['seed_base']
    missing = 0
    print('| method | runs | NEES in its band | NEES median | band (95 %) | innovations beyond the 99.99 % bound '
          '(expected) | median NIS (5.3) | re-run vs online (max diff mm) | outlier verdicts online | '
          're-run | average NEES (its 95 % band) | spread of log NEES (consistent) | in band if centred |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    for method in args.methods:
        rows = run_nees(args.output, method, range(args.repetitions), args.covariance, overrides)
        missing += args.repetitions - len(rows)
        for r in rows:
            print(f'  {method} rep {r["repetition"]} (seed {first + r["repetition"]}): NEES {r["nees"]:.1f} '
                  f'band {r["band"][0]:.1f}-{r["band"][1]:.1f} {"in" if r["in_band"] else "OUT"}; '
                  f'{r["position_mm"]:.3f} mm (online {r["online_position_mm"]:.3f}); outlier verdicts '
                  f'{r["online_outliers"]} online, {r["outlier_verdicts"]} re-run', file=sys.stderr)
        if not rows:
            continue
        nees = np.array([r['nees'] for r in rows])
        diff = max(abs(r['position_mm'] - r['online_position_mm']) for r in rows)
        band = rows[0]['band']
        count, beyond = sum(r['innovations'] for r in rows), sum(r['beyond'] for r in rows)
        medians = [r['median_nis'] for r in rows if np.isfinite(r['median_nis'])]   # none: runs too short
        median_nis = f'{np.median(medians):.1f}' if medians else 'n/a'
        print(f'| {method} | {len(rows)} | {sum(r["in_band"] for r in rows)} of {len(rows)} | {np.median(nees):.1f} | '
              f'{band[0]:.1f}-{band[1]:.1f} | {beyond} of {count} ({count * 1e-4:.2f}) | '
              f'{median_nis} | {diff:.3f} | {sum(r["online_outliers"] for r in rows)} | '
              f'{sum(r["outlier_verdicts"] for r in rows)} | {_dispersion_cells(rows)} |')
    if missing:
        # A table over fewer runs than asked for is partial: say so in the exit status too.
        print(f'experiment_nees: {missing} of the requested runs have no finished recording', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
