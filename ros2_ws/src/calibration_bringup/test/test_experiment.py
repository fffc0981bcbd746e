"""Experiment runner: plan, seeds, per-method and per-system parameters, settings checks, files, CLI
(no ROS graph run; tests/test_experiment_run.py and test_experiment_ray.py run graphs)."""
from __future__ import annotations

import io
import itertools
import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

import pytest
from rclpy.parameter import Parameter

from calibration_bringup import experiment as ex


def test_every_method_of_a_repetition_shares_its_seeds() -> None:
    config = ex.ExperimentConfig(repetitions=3, iterations=7, seed_base=40)
    runs = ex.plan_runs(config)
    assert len(runs) == 3 * len(ex.METHODS)
    # Repetition-major: an interrupted experiment holds whole repetitions.
    assert [r.repetition for r in runs] == sorted(r.repetition for r in runs)
    for rep, group in itertools.groupby(runs, key=lambda r: r.repetition):
        group = list(group)
        assert [r.method for r in group] == list(ex.METHODS)
        assert {r.seed for r in group} == {40 + rep}
        assert {r.seeds for r in group} == {ex.derive_seeds(40 + rep)}
        assert {r.iterations for r in group} == {7}
        # Every method's nodes get the same robot, guess and selector seeds.
        params = [ex.node_parameters(r) for r in group]
        assert len({(p['sim']['perturb_seed'], p['estimator']['initial_seed'], p['selector']['seed'])
                    for p in params}) == 1


def test_seeds_are_spawned_independently_from_the_repetition_seed() -> None:
    seeds = [ex.derive_seeds(s) for s in range(200)]
    for s, d in enumerate(seeds):
        # The reference derivation, spelt out: SeedSequence(s).spawn(3), first word of each, mod 2**31 - 1.
        children = np.random.SeedSequence(s).spawn(3)
        assert (d.robot, d.guess, d.selector) == tuple(int(c.generate_state(1)[0]) % (2**31 - 1) for c in children)
        assert len({d.robot, d.guess, d.selector}) == 3
        assert all(0 <= v <= 2**31 - 2 for v in (d.robot, d.guess, d.selector))
    assert ex.derive_seeds(7) == ex.derive_seeds(7)
    # Not a shifted copy of each other (the old runner used one seed for all three draws):
    robot, guess = np.array([d.robot for d in seeds], float), np.array([d.guess for d in seeds], float)
    assert abs(np.corrcoef(robot, guess)[0, 1]) < 0.2
    assert len({d.robot for d in seeds}) == 200
    with pytest.raises(ValueError, match='-1'):
        ex.derive_seeds(-1)


@pytest.mark.parametrize('method', list(ex.METHODS))
def test_node_parameters_follow_the_method(method: str) -> None:
    spec = ex.RunSpec(method, 2, 17, 9)
    p = ex.node_parameters(spec)
    m = ex.METHODS[method]
    seeds = ex.derive_seeds(17)
    assert (p['sim']['perturb_seed'], p['estimator']['initial_seed'], p['selector']['seed']) == \
        (seeds.robot, seeds.guess, seeds.selector)
    assert p['selector']['strategy'] == m.strategy
    assert p['selector']['iterations'] == 9
    # Both eyes rendered, as the detector reads both (the parameter files' use_right_eye).
    assert p['sim']['cameras'] == ['left', 'right'] and p['sim']['real_time_factor'] == 0.0
    # CN: selector and estimator use the constant model; the detector keeps its default.
    expected = 'constant' if m.constant_noise else None
    assert p['selector'].get('noise_model') == expected
    assert p['estimator'].get('noise_model') == expected
    assert p['detector'] == ex.node_parameters(ex.RunSpec('AL', 0, 17, 9))['detector']


def test_the_paper_system_overrides_estimator_and_selector_only() -> None:
    spec = ex.RunSpec('UCSAL', 0, 3, 9)
    ours, paper = ex.node_parameters(spec, system='ours'), ex.node_parameters(spec, system='paper')
    e = paper['estimator']
    assert (e['estimator'], e['iterations'], e['gate_probability']) == ('ekf', 1, 0.0)     # no gate
    assert e['q_length'] > 0 and e['q_angle'] > 0                                          # P + Q
    s = paper['selector']
    assert (s['occlusion_mode'], s['criterion'], s['optimizer'], s['algorithm'], s['max_evals']) == \
        ('paper', 'a_optimal', 'direct', 'DIRECT', 1000)
    assert (s['occlusion_prior'], s['repeat_tolerance']) == ('flat', 0.0)
    assert (s['q_length'], s['q_angle']) == (e['q_length'], e['q_angle'])    # the cost sees the same Q
    # One law, R = sigma^2 I: the same coefficients for both blocks in the detector and the selector.
    for node in ('detector', 'selector'):
        p = paper[node]
        assert p['pdn_a_pos'] == p['pdn_a_rot'] and p['pdn_b_pos'] == p['pdn_b_rot']
        assert p['pdn_floor_pos'] == p['pdn_floor_rot'] == 0.0
    # 'ours' is the parameter files as they are (not the paper's choices).
    assert (ours['estimator']['estimator'], ours['selector']['optimizer']) != ('ekf', 'direct')
    changed = {(node, k) for node in ours for k in set(ours[node]) | set(paper[node])
               if ours[node].get(k) != paper[node].get(k)}
    # The simulator renders the eyes the detector reads: both for ours, the left for the paper's.
    assert (ours['sim']['cameras'], paper['sim']['cameras']) == (['left', 'right'], ['left'])
    assert changed - {('sim', 'cameras')} <= {(node, k) for node, over in ex.SYSTEMS['paper'].items() for k in over}
    assert {('estimator', 'estimator'), ('selector', 'optimizer'), ('selector', 'criterion')} <= changed
    # Same robots (the start is the paper's random one).
    assert {k: v for k, v in paper['sim'].items() if k not in ('random_start', 'cameras')} == \
        {k: v for k, v in ours['sim'].items() if k != 'cameras'}
    with pytest.raises(ValueError, match='quantum'):
        ex.ExperimentConfig(system='quantum')


@pytest.mark.parametrize('system', list(ex.SYSTEMS))
def test_node_parameters_are_declared_by_the_nodes(ros, system: str) -> None:
    """A misspelt override would be silently ignored by rclpy: every one must exist and apply."""
    from active_selector.selector_node import SelectorNode
    from dh_estimator.estimator_node import EstimatorNode
    from icub_sim_bridge.sim_node import SimNode
    from marker_detector.detector_node import DetectorNode

    params = ex.node_parameters(ex.RunSpec('CCSAL-CN', 0, 5, 3), system=system)
    classes = {'sim': SimNode, 'detector': DetectorNode, 'estimator': EstimatorNode, 'selector': SelectorNode}
    for key, cls in classes.items():
        node = ros.add(cls(context=ros.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params[key].items()]))
        for name, value in params[key].items():
            assert node.has_parameter(name), f'{cls.__name__} does not declare {name!r}'
            assert node.get_parameter(name).value == value, (key, name)


@pytest.mark.parametrize('kwargs, word', [
    ({'methods': ('AL', 'XX')}, 'XX'), ({'methods': ()}, 'methods'), ({'repetitions': 0}, 'repetitions'),
    ({'iterations': -1}, 'iterations'), ({'jobs': 0}, 'jobs'), ({'seed_base': -3}, '-3'),
    ({'domain_base': 240}, '240')])
def test_config_errors_name_the_bad_value(kwargs: dict, word: str) -> None:
    with pytest.raises(ValueError, match=word):
        ex.ExperimentConfig(**kwargs)


def test_cli_quick_preset_and_overrides(tmp_path: Path) -> None:
    c = ex.config_from_args(['--quick'])
    assert (c.repetitions, c.iterations, c.jobs, c.record, c.system) == (3, 20, 2, True, 'ours')
    assert c.methods == tuple(ex.METHODS) and c.output == Path('results/experiment-ours-quick')
    assert (c.address, c.shared, c.force_new) == (None, False, False)
    assert ex.config_from_args(['--quick', '--output', str(tmp_path)]).output == tmp_path
    c = ex.config_from_args(['--quick', '--iterations', '5', '--methods', 'AL', 'R', 'AL', '--no-record',
                             '--jobs', '1', '--seed-base', '100'])
    assert (c.repetitions, c.iterations, c.methods, c.record, c.jobs, c.seed_base) == \
        (3, 5, ('AL', 'R'), False, 1, 100)
    g = ex.config_from_args(['--image-rate', '2.5', '--image-size', '640', '480', '--joint-speed', '45']).graph
    assert (g.image_rate, g.image_width, g.image_height, g.max_joint_speed_deg) == (2.5, 640, 480, 45.0)
    full = ex.config_from_args([])
    assert (full.repetitions, full.iterations, full.output) == (50, 50, Path('results/experiment-ours'))
    paper = ex.config_from_args(['--system', 'paper'])
    assert (paper.system, paper.output) == ('paper', Path('results/experiment-paper'))
    c = ex.config_from_args(['--address', 'ray://head:10001', '--shared-output', str(tmp_path), '--force-new'])
    assert (c.address, c.output, c.shared, c.force_new) == ('ray://head:10001', tmp_path, True, True)
    with pytest.raises(SystemExit):
        ex.config_from_args(['--output', 'a', '--shared-output', 'b'])
    with pytest.raises(SystemExit):
        ex.config_from_args(['--methods', 'ALX'])
    with pytest.raises(SystemExit):
        ex.config_from_args(['--system', 'theirs'])
    assert ex.main(['--repetitions', '0']) == 2


def test_rows_are_written_atomically_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / 'runs' / 'AL' / 'rep03.csv'
    rows = [{c: 0 for c in ex.COLUMNS} | {'method': 'AL', 'iteration': i, 'position_mm': 1.0 / 3}
            for i in range(3)]
    ex.write_rows(path, rows)
    assert [p.name for p in path.parent.iterdir()] == ['rep03.csv']    # no temporary left behind
    back = ex.read_rows(path)
    assert [r['iteration'] for r in back] == ['0', '1', '2']
    assert list(back[0]) == list(ex.COLUMNS)
    assert float(back[1]['position_mm']) == pytest.approx(1.0 / 3, rel=1e-5)


def _finish(spec: ex.RunSpec, root: Path, run_hash: str) -> None:
    """A finished run's CSV, as the driver writes it."""
    ex.write_rows(spec.path(root, '.csv'), [{'method': spec.method, 'repetition': spec.repetition,
                                              'seed': spec.seed, 'iteration': i, 'settings_hash': run_hash}
                                             for i in range(spec.iterations + 1)])


def test_a_finished_run_of_another_configuration_is_refused(tmp_path: Path) -> None:
    spec = ex.RunSpec('AL', 1, 11, 20)
    assert not ex.is_finished(spec, tmp_path, 'h1')
    _finish(spec, tmp_path, 'h1')
    assert ex.is_finished(spec, tmp_path, 'h1')
    with pytest.raises(ValueError, match='holds 20 iterations.*asks for 50'):
        ex.is_finished(ex.RunSpec('AL', 1, 11, 50), tmp_path, 'h1')
    with pytest.raises(ValueError, match='seed 12'):
        ex.is_finished(ex.RunSpec('AL', 1, 12, 20), tmp_path, 'h1')
    with pytest.raises(ValueError, match=r"settings hash \['h1'\].*has h2"):
        ex.is_finished(spec, tmp_path, 'h2')


def test_run_settings_cover_what_changes_results_and_nothing_else() -> None:
    base = ex.ExperimentConfig(repetitions=2, iterations=10, methods=('AL', 'R'), seed_base=3)
    s = ex.run_settings(base, 'AL')
    assert s['selector.strategy'] == 'al' and s['iterations'] == 10 and s['seed_base'] == 3
    assert 'system' not in s and s['sim.image_rate'] == base.graph.image_rate
    # Per-repetition seeds are not settings (they follow from seed_base).
    assert not {'sim.perturb_seed', 'estimator.initial_seed', 'selector.seed'} & set(s)
    h = ex.settings_hash(s)
    assert len(h) == 16 and h == ex.settings_hash(dict(reversed(list(s.items()))))
    # How many runs, where and how fast: same hash.
    for same in (replace(base, repetitions=50), replace(base, methods=('AL',)), replace(base, jobs=1),
                 replace(base, record=False), replace(base, address='auto'),
                 replace(base, graph=replace(base.graph, run_timeout=99.0))):
        assert ex.settings_hash(ex.run_settings(same, 'AL')) == h
    # What a run computes: another hash.
    for other in (replace(base, iterations=11), replace(base, seed_base=4), replace(base, system='paper'),
                  replace(base, graph=replace(base.graph, image_rate=5.0))):
        assert ex.settings_hash(ex.run_settings(other, 'AL')) != h
    assert ex.settings_hash(ex.run_settings(base, 'R')) != h
    assert ex.settings_difference(s, {**s, 'iterations': 11, 'extra': 1}) == ["extra: '<unset>' -> 1",
                                                                               'iterations: 10 -> 11']


def _fake_session(config: ex.ExperimentConfig) -> None:
    """What a finished session leaves (config.json, every run's CSV), without running graphs."""
    root = Path(config.output)
    settings = {m: ex.run_settings(config, m) for m in config.methods}
    ex._write_config(root, config, settings)
    for spec in ex.plan_runs(config):
        _finish(spec, root, ex.settings_hash(settings[spec.method]))


def test_resume_with_other_settings_is_refused_naming_them(tmp_path: Path) -> None:
    config = ex.ExperimentConfig(repetitions=2, iterations=3, methods=('AL', 'R'), output=tmp_path,
                                 seed_base=5, figures=False)
    _fake_session(config)
    recorded = json.loads((tmp_path / 'config.json').read_text())
    assert recorded['seeds'] == [{'repetition': r, 'seed': 5 + r, **asdict(ex.derive_seeds(5 + r))} for r in range(2)]
    assert recorded['settings_hash'] == {m: ex.settings_hash(ex.run_settings(config, m)) for m in ('AL', 'R')}
    # Same settings (more repetitions are fine): nothing to redo for the finished runs.
    log = io.StringIO()
    with pytest.raises(ValueError, match='other settings') as err:
        ex.run_experiment(replace(config, system='paper'), stream=log)
    message = str(err.value)
    for key in ("selector.optimizer: 'batch' -> 'direct'", "estimator.estimator: 'map' -> 'ekf'",
                'AL:', 'R:', '--force-new'):
        assert key in message, message
    assert ' iterations: ' not in message and 'seed_base' not in message     # only what differs
    with pytest.raises(ValueError, match="iterations: 3 -> 4"):
        ex.run_experiment(replace(config, iterations=4, methods=('R',)), stream=log)
    assert ex.main(['--iterations', '4', '--repetitions', '2', '--methods', 'AL', '--seed-base', '5',
                    '--output', str(tmp_path), '--no-figures']) == 2
    # The refused attempts changed nothing on disk.
    assert json.loads((tmp_path / 'config.json').read_text()) == recorded
    # A method with no finished runs may be added with the same settings; it needs no Ray here
    # because its runs are finished too.
    _fake_session(replace(config, methods=('CCSAL',)))
    out = ex.run_experiment(replace(config, methods=('AL', 'R', 'CCSAL')), stream=log)
    assert out.failures == [] and out.results == []
    assert '6 already finished, 0 to run' in log.getvalue()
    assert len(ex.read_rows(tmp_path / 'metrics.csv')) == 6 * 4


def test_force_new_moves_the_old_results_aside(tmp_path: Path) -> None:
    config = ex.ExperimentConfig(repetitions=1, iterations=3, methods=('AL',), output=tmp_path, figures=False)
    _fake_session(config)
    (tmp_path / 'metrics.csv').write_text('old\n')
    old_csv = ex.plan_runs(config)[0].path(tmp_path, '.csv').read_text()
    paper = replace(config, system='paper', repetitions=1, force_new=True)
    # No graph runs here: stop where the runs would be submitted to Ray, as Ctrl-C would.
    log = io.StringIO()
    with pytest.MonkeyPatch.context() as mp:
        def interrupted(*args: object, **kwargs: object) -> None:
            raise KeyboardInterrupt
        mp.setattr(ex, 'ray_runtime', interrupted)
        with pytest.raises(KeyboardInterrupt):
            ex.run_experiment(paper, stream=log)
    aside = sorted(tmp_path.glob('previous-*'))
    assert len(aside) == 1 and f'moved to {aside[0]}' in log.getvalue()
    assert (aside[0] / 'runs' / 'AL' / 'rep00.csv').read_text() == old_csv
    assert (aside[0] / 'metrics.csv').read_text() == 'old\n'
    assert not (tmp_path / 'runs').exists()
    assert json.loads((tmp_path / 'config.json').read_text())['system'] == 'paper'


def test_combine_takes_only_finished_planned_runs(tmp_path: Path) -> None:
    runs = ex.plan_runs(ex.ExperimentConfig(repetitions=2, iterations=1, methods=('AL', 'R')))
    for spec in runs[:3]:
        ex.write_rows(spec.path(tmp_path, '.csv'), [{'method': spec.method, 'repetition': spec.repetition}])
    ex.write_rows(tmp_path / 'runs' / 'AL' / 'rep09.csv', [{'method': 'AL', 'repetition': 9}])  # not planned
    n = ex.combine_runs(tmp_path, runs, tmp_path / 'metrics.csv')
    assert n == 3
    assert [(r['method'], r['repetition']) for r in ex.read_rows(tmp_path / 'metrics.csv')] == \
        [('AL', '0'), ('R', '0'), ('AL', '1')]


def test_a_run_that_never_used_an_observation_is_cautioned() -> None:
    """Issue 31's seed 30 (per-eye occlusion models): 50 attempts, none seen, and nothing said."""
    def result(method: str, outcomes: list[str]) -> ex.RunResult:
        spec = ex.RunSpec(method, 30, 30, len(outcomes))
        rows = [{'outcome': o} for o in ['initial', *outcomes]]
        return ex.RunResult(spec, rows, None, None, None, '', '', 215, 1.0)

    results = [result('AL', ['failed'] * 50), result('R', ['failed'] * 49 + ['outlier']),
               result('CCSAL', ['accepted', 'failed']),
               ex.RunResult(ex.RunSpec('UCSAL', 30, 30, 50), None, 'RunError: x', None, None, '', '', 216, 1.0)]
    assert ex.run_cautions(results) == ['AL rep 30 (seed 30): no observation reached the estimate in its 50 '
                                        "iterations; its final error is the initial guess's"]


def test_domain_ids_are_distinct_and_valid() -> None:
    ids = ex.domain_ids(ex.ExperimentConfig(jobs=3))
    assert len(set(ids)) == 3 and all(215 <= d <= 232 for d in ids)
    assert ex.domain_ids(ex.ExperimentConfig(jobs=2, domain_base=40)) == [40, 41]
    with pytest.raises(ValueError, match='20'):
        ex.domain_ids(ex.ExperimentConfig(jobs=20))


@pytest.mark.parametrize('text, expected', [
    ('estimator.q_length=1e-6', ('estimator', 'q_length', 1e-6)),
    ('estimator.gate_probability=0.0', ('estimator', 'gate_probability', 0.0)),
    ('selector.max_evals=200', ('selector', 'max_evals', 200)),
    ('sim.random_start=true', ('sim', 'random_start', True)),
    ('selector.algorithm=DIRECT', ('selector', 'algorithm', 'DIRECT')),
    ('sim.initial_positions_deg=[1.0, 2.5]', ('sim', 'initial_positions_deg', [1.0, 2.5]))])
def test_set_values_are_typed_as_ros_parameters(text: str, expected: tuple) -> None:
    node, name, value = ex.parse_override(text)
    assert (node, name, value) == expected and type(value) is type(expected[2])


@pytest.mark.parametrize('text, word', [('q_length=1', 'NODE.PARAMETER'), ('estimator.q_length', 'NODE'),
                                        ('planner.gamma=1.0', "'planner'")])
def test_bad_set_is_refused_naming_it(text: str, word: str) -> None:
    with pytest.raises(ValueError, match=word):
        ex.parse_override(text)
    assert ex.main(['--set', text, '--repetitions', '1']) == 2


def test_set_overrides_the_system_and_the_same_parameters_share_finished_runs() -> None:
    c = ex.config_from_args(['--set', 'estimator.q_length=1e-6', '--set', 'selector.gamma=0.5'])
    assert c.overrides == {'estimator': {'q_length': 1e-6}, 'selector': {'gamma': 0.5}}
    p = ex.node_parameters(ex.RunSpec('UCSAL', 0, 1, 5), c.graph, c.system, c.overrides)
    assert (p['estimator']['q_length'], p['selector']['gamma']) == (1e-6, 0.5)
    assert p['selector']['strategy'] == 'ucsal'                      # the method still wins
    # The paper's system reached through --set on ours is the same runs as --system paper.
    from calibration_bringup.systems import PAPER
    via_set = ex.ExperimentConfig(system='ours', overrides=PAPER)
    assert ex.run_settings(via_set, 'AL') == ex.run_settings(ex.ExperimentConfig(system='paper'), 'AL')
    with pytest.raises(ValueError, match='planner'):
        ex.ExperimentConfig(overrides={'planner': {'gamma': 1.0}})


def test_the_numeric_environments_of_the_runs_are_kept_across_sessions_and_a_new_one_is_cautioned(
        tmp_path: Path) -> None:
    config = ex.ExperimentConfig(repetitions=1, iterations=3, methods=('AL',), output=tmp_path, figures=False)
    _fake_session(config)
    assert ex.read_environments(tmp_path) == []          # made before environments were recorded
    here = {'cpu': 'x', 'blas': 'openblas SkylakeX x1'}
    assert ex._record_environments(tmp_path, {'vm': here}) == []
    assert ex._record_environments(tmp_path, {'other-host': dict(here)}) == []      # the same one: no caution
    recorded = json.loads((tmp_path / 'config.json').read_text())['environments']
    assert recorded == [{'hosts': ['other-host', 'vm'], **here}]
    # A later session (its config written again) keeps them; another environment is a caution naming it.
    ex._write_config(tmp_path, config, {m: ex.run_settings(config, m) for m in config.methods})
    assert ex.read_environments(tmp_path) == [here]
    haswell = {**here, 'blas': 'openblas Haswell x1', 'OPENBLAS_CORETYPE': 'Haswell'}
    (caution,) = ex._record_environments(tmp_path, {'vm': haswell})
    assert 'another numeric environment (vm: OPENBLAS_CORETYPE: unset -> Haswell; blas: ' in caution
    assert ex.read_environments(tmp_path) == [here, haswell]
