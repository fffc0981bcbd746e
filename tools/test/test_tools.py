"""Every module of tools/ is a maintained tool: a ``--help``, a section in docs/tools.md, and a run.

The runs use small settings (a few iterations, one seed) and check what each tool prints: the
table its documentation shows, with the rows it promises. Tools with a test file of their own
(detector_accuracy, error_replay, fit_noise, seed_study, transport_bench; fault_table through
tests/test_faults.py; detector_bench and sim_bench through test_readme_tables.py) are only
checked here for ``--help`` and their docs section.
"""
from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
TOOLS = sorted(p.stem for p in (ROOT / 'tools').glob('*.py') if p.stem != '__init__')
DOCS = ROOT / 'docs' / 'tools.md'


def _rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the Markdown table whose header line starts with ``header_start``."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header_start))
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith('|'):
            break
        rows.append([c.strip() for c in ln.strip().strip('|').split('|')])
    return rows


def test_the_tools_are_found() -> None:
    assert {'bench', 'selector_study', 'seed_study', 'bench_acquisition'} <= set(TOOLS)


@pytest.mark.parametrize('name', TOOLS)
def test_every_tool_answers_help(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    module = importlib.import_module(f'tools.{name}')
    with pytest.raises(SystemExit) as stop:
        module.main(['--help'])
    assert stop.value.code == 0
    assert 'usage:' in capsys.readouterr().out


@pytest.mark.parametrize('name', TOOLS)
def test_every_tool_has_a_section_in_the_docs(name: str) -> None:
    # docs/tools.md: one "## `tools.<name>` {#<name>}" section per module (other pages link to the anchor).
    assert re.search(rf'^## `tools\.{name}` \{{#{name}\}}$', DOCS.read_text(), re.M), name


def test_the_docs_list_no_tool_that_is_gone() -> None:
    listed = set(re.findall(r'^## `tools\.(\w+)`', DOCS.read_text(), re.M))
    assert listed == set(TOOLS)


def test_kinematics_bench_measures_every_row() -> None:
    from tools import kinematics_bench

    rows = _rows(kinematics_bench.main(['--scale', '0.01']), '| operation |')
    assert [r[0] for r in rows] == [
        'batched FK, 1000 configurations', 'pose Jacobian w.r.t. 28 DH parameters',
        'EKF update (paper: 1 linearisation)', 'EKF update, iterated (5 linearisations)',
        'acquisition cost, one evaluation (50 occlusion samples)',
        'acquisition cost, one stereo evaluation (the local search: both eyes, visibility prior)',
        'AL selection, DIRECT-L, 2000 evaluations']
    assert all(float(r[1].split()[0]) > 0 for r in rows)


def test_map_bench_times_each_size_and_window() -> None:
    from tools import map_bench

    rows = _rows(map_bench.main(['--sizes', '3', '6', '--repeats', '2']), '| MAP update after N')
    assert [r[0] for r in rows] == ['3 (default: window 100)', '6 (default: window 100)',
                                    '3 (all kept: window 0)', '6 (all kept: window 0)']
    assert all(float(r[1]) > 0 for r in rows)


def test_bench_writes_each_section_and_refuses_an_unknown_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    from tools import bench

    assert bench.main(['no_such_bench']) == 2
    monkeypatch.setattr(bench, 'BENCHMARKS', {'dh_estimator': ('tools.map_bench', ['--sizes', '2', '--repeats', '1'])})
    assert bench.main(['--output', str(tmp_path)]) == 0
    written = (tmp_path / 'dh_estimator.md').read_text()
    assert written.startswith('## dh_estimator') and written in capsys.readouterr().out


def test_collision_bench_times_each_geometry_and_finds_the_simulator_agreeing() -> None:
    from tools import collision_bench

    text = collision_bench.main(['--robots', 'panda', '--configs', '20', '--selections', '2', '--agreement', '40'])
    rows = _rows(text, '| robot | geometry |')
    assert rows[0][1].startswith('drawn from the DH table (built') and rows[1][1].startswith('its URDF (used; built')
    assert int(rows[1][2]) > int(rows[0][2])          # the gripper and the plate add pairs
    assert all(float(r[3]) > 0 for r in rows[:2])
    agreement = _rows(text, '| robot | configurations |')
    assert agreement[0][0] == 'panda' and agreement[0][-1] == '0'


def test_acquisition_bench_compares_every_criterion_mode_and_strategy() -> None:
    from tools import acquisition_bench

    text = acquisition_bench.main(['--seeds', '1', '--iterations', '4', '--every', '2', '--max-evals', '20'])
    rows = _rows(text, '| criterion |')
    assert {(r[0], r[1], r[2]) for r in rows} == {(c, o, s) for c in ('a_optimal', 'v_optimal')
                                                  for o in ('paper', 'gain') for s in ('al', 'ucsal', 'ccsal')}
    assert all(int(r[3]) == 2 for r in rows)  # states before selections 1 and 3 of 4


def test_loop_bench_reports_the_budget_of_a_short_run() -> None:
    from tools import loop_bench

    text = loop_bench.main(['--iterations', '2'])
    assert 'medians over 2 AL iterations' in text
    rows = dict((r[0], r[1]) for r in _rows(text, '| step |'))
    assert float(rows['move to target (sim, 30 deg/s)'].split()[0]) > 0
    assert rows['compute / move'].endswith('%')


def test_selector_study_prints_a_result_per_run(capsys: pytest.CaptureFixture[str]) -> None:
    from tools import selector_study

    assert selector_study.main(['--seeds', '1', '--iterations', '3']) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result['args']['iterations'] == 3
    assert result['movement_deg'] > 0 and 0 <= result['discarded'] <= 3


def test_estimator_study_compares_both_estimators_and_writes_its_summary(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools import estimator_study

    assert estimator_study.main(['--seeds', '1', '--iterations', '3', '--output', str(tmp_path)]) == 0
    rows = _rows(capsys.readouterr().out, '| estimator |')
    assert [r[0] for r in rows] == ['map', 'ekf']
    assert [r[0] for r in _rows((tmp_path / 'summary.md').read_text(), '| estimator |')] == ['map', 'ekf']
    assert len(json.loads((tmp_path / 'runs.json').read_text())) == 2


def test_map_study_consistency_scores_map_and_ekf(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools import map_study

    assert map_study.main(['consistency', '--seeds', '2', '--observations', '15', '--output', str(tmp_path)]) == 0
    rows = _rows(capsys.readouterr().out, '| estimator |')
    assert [r[0] for r in rows] == ['MAP', 'EKF (paper, 1 linearisation)']
    assert list(tmp_path.glob('*.json'))


def test_visibility_fit_bins_every_rendered_configuration(capsys: pytest.CaptureFixture[str]) -> None:
    from tools import visibility_fit

    assert visibility_fit.main(['--seeds', '1', '--configs', '10']) == 0
    out = capsys.readouterr().out
    assert 'best fit:' in out
    assert sum(int(r[1]) for r in _rows(out, '| predicted |')) == 10


def test_box_proposal_prints_a_box_and_its_rendered_check(capsys: pytest.CaptureFixture[str]) -> None:
    from tools import box_proposal

    assert box_proposal.main(['--robot', 'ur5e', '--samples', '64', '--candidates', '64', '--no-collision',
                              '--check', '4']) == 0
    out = capsys.readouterr().out
    assert re.search(r'^calibration_box: \[\[.*\]\]$', out, re.M)
    assert re.search(r'^# rendered \(left, 4 configurations, seed 1\): a marker detected in [\d.]+%', out, re.M)


def test_nees_dispersion_finds_a_consistent_spread_and_a_wider_one() -> None:
    from scipy import stats

    from tools.experiment_nees import nees_dispersion

    k = np.full(4000, 28)
    right = stats.chi2.rvs(28, size=4000, random_state=np.random.default_rng(0))
    d = nees_dispersion(right, k)
    assert d['chi2_log_sd'] == pytest.approx(0.272, abs=0.002)
    assert d['log_sd'] == pytest.approx(d['chi2_log_sd'], rel=0.05)
    assert 0.93 < d['in_band_if_centred'] < 0.96                 # the log-normal stand-in for chi-square
    assert d['average_band'][0] < d['average'] < d['average_band'][1]
    # The same centre, every log NEES spread 1.5x wider: fewer in band however well centred, and
    # the same average test passes or fails on the centre alone.
    centre = np.mean(np.log(right))
    wide = nees_dispersion(np.exp(centre + 1.5 * (np.log(right) - centre)), k)
    assert wide['log_sd'] == pytest.approx(1.5 * d['log_sd'])
    assert wide['in_band_if_centred'] < 0.85
    with pytest.raises(ValueError, match='>= 2 runs'):
        nees_dispersion([20.0], [28])
    with pytest.raises(ValueError, match=r'finite and > 0, got \[20.0, 0.0\]'):
        nees_dispersion([20.0, 0.0], [28, 28])


@pytest.fixture(scope='module')
def recorded_experiment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One recorded AL run of four iterations with the defaults (both eyes), on the real graph."""
    import io
    import os

    from calibration_bringup import experiment as ex

    out = tmp_path_factory.mktemp('experiment')
    config = ex.ExperimentConfig(repetitions=1, iterations=4, methods=('AL',), jobs=1, output=out, seed_base=3,
                                 domain_base=200 + 2 * (os.getpid() % 7) + 1, figures=False)
    log = io.StringIO()
    assert ex.run_experiment(config, stream=log).failures == [], log.getvalue()
    return out


@pytest.mark.slow
def test_experiment_nees_reruns_each_recorded_run_to_its_online_error(recorded_experiment: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from tools import experiment_nees

    assert experiment_nees.main([str(recorded_experiment), '--methods', 'AL', '--repetitions', '1']) == 0
    (row,) = _rows(capsys.readouterr().out, '| method | runs |')
    assert row[:3] == ['AL', '1', row[2]] and row[2].endswith('of 1')
    assert float(row[3]) > 0 and float(row[7]) < 1e-6          # the re-run ends at the online error
    assert row[8] == row[9]                                     # ... with the online verdicts
    assert row[10:] == ['n/a'] * 3                              # one run: no spread to measure
    with pytest.raises(KeyError, match="no settings for method 'CCSAL'"):
        experiment_nees.run_nees(recorded_experiment, 'CCSAL', [0])
    # A repetition that was never run makes the table partial, and the exit status says so.
    assert experiment_nees.main([str(recorded_experiment), '--methods', 'AL', '--repetitions', '2']) == 1
    assert 'of the requested runs have no finished recording' in capsys.readouterr().err
    # Another posterior covariance reaches the re-run's estimator, and only its covariance setting.
    config = json.loads((recorded_experiment / 'config.json').read_text())
    own = experiment_nees.estimator_parameters(config, 'AL')
    assert experiment_nees.estimator_parameters(config, 'AL', 'gauss_newton') == own | {'covariance': 'gauss_newton'}
    from dh_estimator.evaluate import EvaluationSettings
    settings = EvaluationSettings.from_parameters(experiment_nees.estimator_parameters(config, 'AL', 'gauss_newton'))
    assert settings.estimator.map_settings('sandwich_hc3').covariance == 'gauss_newton'   # over the description's
    assert experiment_nees.main([str(recorded_experiment), '--repetitions', '1', '--covariance', 'gauss_newton']) == 0
    (row,) = _rows(capsys.readouterr().out, '| method | runs |')
    assert float(row[7]) < 1e-6
    with pytest.raises(SystemExit):
        experiment_nees.main([str(recorded_experiment), '--covariance', 'robust'])
    # Any other estimator parameter reaches the re-run's estimator.
    assert experiment_nees.estimator_parameters(config, 'AL', overrides={'verdict_nfev': 200}) == \
        own | {'verdict_nfev': 200}
    assert experiment_nees.parse_override('estimator.verdict_nfev=200') == ('verdict_nfev', 200)
    assert experiment_nees.main([str(recorded_experiment), '--repetitions', '1',
                                 '--set', 'estimator.verdict_nfev=200']) == 0
    (row,) = _rows(capsys.readouterr().out, '| method | runs |')
    assert int(row[9]) <= int(row[8])
    assert experiment_nees.main([str(recorded_experiment), '--set', 'selector.seed=1']) == 2
    with pytest.raises(ValueError, match="no parameter 'verdict_nfv'"):
        experiment_nees.parse_override('estimator.verdict_nfv=200')


@pytest.mark.slow
def test_visibility_attempts_scores_every_grid_point_on_the_rendered_attempts(
        recorded_experiment: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools import visibility_attempts

    assert visibility_attempts.main([str(recorded_experiment), '--repetitions', '1']) == 0
    out = capsys.readouterr().out
    assert re.search(r'^4 attempts of 1 AL runs', out, re.M), out
    rows = _rows(out, '| margin | marker widths |')
    assert [(float(r[0]), float(r[1])) for r in rows] == list(visibility_attempts.GRID)
    assert all(float(r[2]) < 0 for r in rows)
    assert visibility_attempts.main([str(recorded_experiment), '--repetitions', '2']) == 1     # rep01 missing


def test_experiment_compare_bounds_the_ratio_of_means_in_pairs() -> None:
    from calibration_bringup.experiment_figures import MethodRuns, paired_finals, paired_ratio_interval

    def ratio_interval(first: MethodRuns, second: MethodRuns, column: str) -> tuple[float, float]:
        return paired_ratio_interval(*paired_finals(first, second, column))     # as compare() pairs them

    rng = np.random.default_rng(4)
    base = rng.uniform(0.05, 0.2, 50)               # seeds differ much more than the two runs of a seed

    def runs(final: np.ndarray, reps: np.ndarray) -> MethodRuns:
        return MethodRuns('AL', reps, {'position_mm': np.stack([np.full_like(final, 100.0), final], axis=1)})

    reps = np.arange(50)
    first, second = runs(base, reps), runs(base * 1.1 * rng.lognormal(0.0, 0.03, 50), reps)
    low, high = ratio_interval(first, second, 'position_mm')
    assert low < 1.1 < high and high - low < 0.05   # paired: the seeds' spread cancels
    # Unpaired, the same numbers would give an interval as wide as the seeds' spread: the pairing
    # follows the repetitions, not the row order.
    shuffled = runs(second.columns['position_mm'][::-1, 1], reps[::-1])
    assert ratio_interval(first, shuffled, 'position_mm') == (low, high)
    assert np.isnan(ratio_interval(first, runs(base[:1], reps[:1]), 'position_mm')[0])


def test_experiment_compare_refuses_two_experiments_with_nothing_to_pair() -> None:
    from calibration_bringup.experiment_figures import MethodRuns
    from tools.experiment_compare import compare

    def runs(method: str, reps: list[int]) -> dict[str, MethodRuns]:
        cols = {c: np.ones((len(reps), 2)) for c in ('position_mm', 'orientation_deg', 'discarded', 'movement_deg')}
        return {method: MethodRuns(method, np.array(reps), cols)}

    with pytest.raises(ValueError, match=r"no method in both experiments: \['AL'\] and \['R'\]"):
        compare(runs('AL', [0, 1]), runs('R', [0, 1]), ['a', 'b'])
    with pytest.raises(ValueError, match='AL: no seed in both experiments'):
        compare(runs('AL', [0, 1]), runs('AL', [1000, 1001]), ['a', 'b'])
    assert len(compare(runs('AL', [0, 1]), runs('AL', [1, 2]), ['a', 'b'])) == 2 + 4    # header + 4 figures
    # The means, medians and ratio are over the shared seeds too: 50 runs against their first 20.
    many, few = runs('AL', list(range(50))), runs('AL', list(range(20)))
    many['AL'].columns['position_mm'][:, 1] = np.r_[np.full(20, 1.0), np.full(30, 3.0)]
    row = compare(many, few, ['a', 'b'])[2].split(' | ')
    assert row[2:5] == ['1.000 (1.000)', '1.000 (1.000)', '1.00']
    # Repetition 0 of seed base 1000 is another robot than repetition 0 of seed base 0: pairs by seed.
    base0, base1000 = runs('AL', [0, 1]), runs('AL', [0, 1])
    base0['AL'].seeds, base1000['AL'].seeds = np.array([0, 1]), np.array([1000, 1001])
    with pytest.raises(ValueError, match='AL: no seed in both experiments'):
        compare(base0, base1000, ['a', 'b'])


@pytest.mark.slow
def test_experiment_compare_pairs_the_methods_both_ran(recorded_experiment: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    import csv

    from tools import experiment_compare

    # A copy whose AL ends 0.1 mm lower: the comparison sees it in its one shared repetition.
    rows = list(csv.DictReader((recorded_experiment / 'metrics.csv').open()))
    last = max(int(r['iteration']) for r in rows)
    for r in rows:
        if int(r['iteration']) == last:
            r['position_mm'] = str(float(r['position_mm']) - 0.1)
    with (tmp_path / 'metrics.csv').open('w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    assert experiment_compare.main([str(recorded_experiment), str(tmp_path), '--names', 'a', 'b']) == 0
    table = {r[1]: r for r in _rows(capsys.readouterr().out, '| method | figure |')}
    # One pair has no interval.
    assert table['position [mm]'][0] == 'AL' and table['position [mm]'][5:9] == ['-', '1', '-0.100', '1']
    assert table['orientation [deg]'][4] == '1.00' and table['orientation [deg]'][7] == '+0.000'
    assert experiment_compare.main([str(tmp_path / 'nothing'), str(tmp_path)]) == 2


def test_experiment_compare_says_whether_the_two_were_made_on_one_numeric_environment(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools.experiment_compare import main

    def experiment(name: str, final: float, environments: list | None) -> Path:
        d = tmp_path / name
        d.mkdir()
        rows = ['method,repetition,seed,iteration,position_mm,orientation_deg,movement_deg,discarded']
        rows += [f'AL,{r},{r},{i},{100.0 if i == 0 else final * (1 + r)},1.0,{10.0 * i},0' for r in range(3)
                 for i in (0, 1)]
        (d / 'metrics.csv').write_text('\n'.join(rows) + '\n')
        if environments is not None:
            (d / 'config.json').write_text(json.dumps({'environments': environments}))
        return d

    here = {'hosts': ['vm'], 'cpu': 'x', 'blas': 'SkylakeX'}
    a, b = experiment('a', 0.1, [here]), experiment('b', 0.2, [{**here, 'blas': 'Haswell'}])
    assert main([str(a), str(b)]) == 0
    assert 'b was made on another numeric environment than a (blas: SkylakeX -> Haswell)' in capsys.readouterr().out
    assert main([str(a), str(experiment('c', 0.2, [{**here, 'hosts': ['other']}]))]) == 0
    assert 'c and a were made on the same numeric environment' in capsys.readouterr().out     # hosts aside
    assert main([str(experiment('d', 0.1, None)), str(experiment('e', 0.1, None))]) == 0
    assert 'numeric environment' not in capsys.readouterr().out
