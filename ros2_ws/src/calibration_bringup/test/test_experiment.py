"""Experiment runner: plan, per-method parameters, files, progress bar, CLI (no ROS graph run)."""
from __future__ import annotations

import io
import itertools
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from calibration_bringup import experiment as ex


def test_every_method_of_a_repetition_shares_its_seed() -> None:
    config = ex.ExperimentConfig(repetitions=3, iterations=7, seed_base=40)
    runs = ex.plan_runs(config)
    assert len(runs) == 3 * len(ex.METHODS)
    # Repetition-major: an interrupted experiment holds whole repetitions.
    assert [r.repetition for r in runs] == sorted(r.repetition for r in runs)
    for rep, group in itertools.groupby(runs, key=lambda r: r.repetition):
        group = list(group)
        assert [r.method for r in group] == list(ex.METHODS)
        assert {r.seed for r in group} == {40 + rep}
        assert {r.iterations for r in group} == {7}


@pytest.mark.parametrize('method', list(ex.METHODS))
def test_node_parameters_follow_the_method(method: str) -> None:
    spec = ex.RunSpec(method, 2, 17, 9)
    p = ex.node_parameters(spec)
    m = ex.METHODS[method]
    assert p['sim']['perturb_seed'] == p['estimator']['initial_seed'] == p['selector']['seed'] == 17
    assert p['selector']['strategy'] == m.strategy
    assert p['selector']['iterations'] == 9
    assert p['sim']['cameras'] == ['left'] and p['sim']['real_time_factor'] == 0.0
    # CN: selector and estimator use the constant model; the detector keeps its default.
    expected = 'constant' if m.constant_noise else None
    assert p['selector'].get('noise_model') == expected
    assert p['estimator'].get('noise_model') == expected
    assert p['detector'] == ex.node_parameters(ex.RunSpec('AL', 0, 17, 9))['detector']


def test_node_parameters_are_declared_by_the_nodes(ros) -> None:
    """A misspelt override would be silently ignored by rclpy: every one must exist and apply."""
    from active_selector.selector_node import SelectorNode
    from dh_estimator.estimator_node import EstimatorNode
    from icub_sim_bridge.sim_node import SimNode
    from marker_detector.detector_node import DetectorNode

    params = ex.node_parameters(ex.RunSpec('CCSAL-CN', 0, 5, 3))
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
    assert (c.repetitions, c.iterations, c.jobs, c.record) == (3, 20, 2, True)
    assert c.methods == tuple(ex.METHODS) and c.output == Path('results/experiment-quick')
    assert ex.config_from_args(['--quick', '--output', str(tmp_path)]).output == tmp_path
    c = ex.config_from_args(['--quick', '--iterations', '5', '--methods', 'AL', 'R', 'AL', '--no-record',
                             '--jobs', '1', '--seed-base', '100'])
    assert (c.repetitions, c.iterations, c.methods, c.record, c.jobs, c.seed_base) == \
        (3, 5, ('AL', 'R'), False, 1, 100)
    g = ex.config_from_args(['--image-rate', '2.5', '--image-size', '640', '480', '--joint-speed', '45']).graph
    assert (g.image_rate, g.image_width, g.image_height, g.max_joint_speed_deg) == (2.5, 640, 480, 45.0)
    full = ex.config_from_args([])
    assert (full.repetitions, full.iterations, full.output) == (50, 50, Path('results/experiment'))
    with pytest.raises(SystemExit):
        ex.config_from_args(['--methods', 'ALX'])
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


def test_a_finished_run_of_another_configuration_is_refused(tmp_path: Path) -> None:
    spec = ex.RunSpec('AL', 1, 11, 20)
    assert not ex.is_finished(spec, tmp_path)
    ex.write_rows(spec.path(tmp_path, '.csv'), [{'method': 'AL', 'seed': 11, 'iteration': i} for i in range(21)])
    assert ex.is_finished(spec, tmp_path)
    with pytest.raises(ValueError, match='holds 20 iterations.*asks for 50'):
        ex.is_finished(ex.RunSpec('AL', 1, 11, 50), tmp_path)
    with pytest.raises(ValueError, match='seed 12'):
        ex.is_finished(ex.RunSpec('AL', 1, 12, 20), tmp_path)
    config = ex.ExperimentConfig(repetitions=2, iterations=50, methods=('AL',), output=tmp_path, seed_base=10)
    assert ex.main(['--repetitions', '2', '--methods', 'AL', '--seed-base', '10', '--output', str(tmp_path)]) == 2
    assert ex.plan_runs(config)[1] == ex.RunSpec('AL', 1, 11, 50)


def test_combine_takes_only_finished_planned_runs(tmp_path: Path) -> None:
    runs = ex.plan_runs(ex.ExperimentConfig(repetitions=2, iterations=1, methods=('AL', 'R')))
    for spec in runs[:3]:
        ex.write_rows(spec.path(tmp_path, '.csv'), [{'method': spec.method, 'repetition': spec.repetition}])
    ex.write_rows(tmp_path / 'runs' / 'AL' / 'rep09.csv', [{'method': 'AL', 'repetition': 9}])  # not planned
    n = ex.combine_runs(tmp_path, runs, tmp_path / 'metrics.csv')
    assert n == 3
    assert [(r['method'], r['repetition']) for r in ex.read_rows(tmp_path / 'metrics.csv')] == \
        [('AL', '0'), ('R', '0'), ('AL', '1')]


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_progress_without_a_terminal_prints_one_line_per_run_with_eta() -> None:
    out, clock = io.StringIO(), _Clock()
    p = ex.Progress(runs=4, iterations_per_run=10, stream=out, tty=False, clock=clock)
    for i in range(1, 11):
        clock.t += 0.5
        p.iteration('AL rep 0', i)
    assert out.getvalue() == ''                       # no per-iteration output in a log
    p.run_finished('AL rep 0', note='5 s')
    line = out.getvalue()
    assert line.count('\n') == 1 and '\r' not in line
    assert 'AL rep 0: done 5 s' in line and '1/4 runs' in line and '10/40 iterations' in line
    assert '2.00 it/s' in line and 'ETA 0:15' in line           # 30 iterations left at 2 it/s
    clock.t += 5
    p.run_finished('R rep 0', ok=False, note='RunError: stuck')
    assert 'FAILED' in out.getvalue() and '1 failed' in out.getvalue()


def test_progress_on_a_terminal_redraws_in_place() -> None:
    out, clock = io.StringIO(), _Clock()
    p = ex.Progress(runs=1, iterations_per_run=4, stream=out, tty=True, clock=clock)
    clock.t += 1
    p.iteration('AL rep 0', 1)
    clock.t += 1
    p.iteration('AL rep 0', 2)
    assert out.getvalue().count('\r') == 2 and '\n' not in out.getvalue()
    assert '2/4 iterations' in out.getvalue().split('\r')[-1]
    p.run_finished('AL rep 0')
    p.close()
    assert out.getvalue().endswith('\n') and '1/1 runs' in out.getvalue()


def test_domain_ids_are_distinct_and_valid() -> None:
    ids = ex._domain_ids(ex.ExperimentConfig(jobs=3))
    assert len(set(ids)) == 3 and all(215 <= d <= 232 for d in ids)
    assert ex._domain_ids(ex.ExperimentConfig(jobs=2, domain_base=40)) == [40, 41]
