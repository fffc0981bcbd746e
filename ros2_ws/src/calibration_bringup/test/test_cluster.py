"""What the experiment's tasks carry to their nodes and when the driver stops early (pure parts of
:mod:`calibration_bringup.cluster`; the real processes are in test_experiment_cluster_processes.py)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from calibration_bringup import cluster

exceptions = pytest.importorskip('ray.exceptions')

IMPORT_FAILURE = (
    "The remote function failed to import on the worker. This may be because needed library dependencies "
    "are not installed in the worker environment or cannot be found from sys.path ['/x']:\n\n"
    'Traceback (most recent call last):\n'
    '  File "/v/ray/_private/function_manager.py", line 314, in fetch_and_register_remote_function\n'
    '    function = pickle.loads(serialized_function)\n'
    "ModuleNotFoundError: No module named 'calibration_bringup'\n")


def _ament_prefix(root: Path) -> Path:
    marker = root / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'calibration_bringup'
    marker.parent.mkdir(parents=True)
    marker.touch()
    return root


def _task_error(cause: BaseException) -> BaseException:
    """What ``ray.get`` raises for a task that failed with ``cause`` on a worker."""
    return exceptions.RayTaskError('execute_run', 'Traceback ...', cause, proctitle='ray::execute_run',
                                   pid=7, ip='10.0.0.2').as_instanceof_cause()


def test_the_driver_hands_its_ament_index_and_middleware_settings_to_the_tasks(tmp_path: Path) -> None:
    env = {'AMENT_PREFIX_PATH': '/opt/ros/jazzy:/ws/.venv', 'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp',
           'FASTRTPS_DEFAULT_PROFILES_FILE': '', 'HOME': '/root', 'PYTHONPATH': '/elsewhere'}
    assert cluster.run_environment(env, prefix=str(_ament_prefix(tmp_path / 'venv'))) == \
        {'AMENT_PREFIX_PATH': '/opt/ros/jazzy:/ws/.venv', 'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'}


def test_without_an_ament_path_the_drivers_own_workspace_prefix_is_handed_on(tmp_path: Path) -> None:
    venv = _ament_prefix(tmp_path / 'venv')
    assert cluster.run_environment({'PATH': '/usr/bin'}, prefix=str(venv)) == {'AMENT_PREFIX_PATH': str(venv)}
    # A Python without the workspace's index: nothing to hand on (no made-up path).
    assert cluster.run_environment({}, prefix=str(tmp_path)) == {}


def test_the_task_options_carry_this_venvs_index_with_nothing_exported(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in cluster.RUN_ENV_VARS:
        monkeypatch.delenv(name, raising=False)
    assert cluster.is_ament_prefix(sys.prefix), 'make setup installs the workspace into the venv'
    assert cluster.task_options() == {'runtime_env': {'env_vars': {'AMENT_PREFIX_PATH': sys.prefix}}}


@pytest.mark.parametrize('error, cause', [
    ("OSError: Environment variable 'AMENT_PREFIX_PATH' is not set or empty",
     "OSError: Environment variable 'AMENT_PREFIX_PATH' is not set or empty"),
    ("ModuleNotFoundError: No module named 'pybullet'", "ModuleNotFoundError: No module named 'pybullet'"),
    ('ImportError: libGL.so.1: cannot open shared object file\nmore',
     'ImportError: libGL.so.1: cannot open shared object file'),
    ("DefinitionNotFoundError: package 'std_msgs' is not in the ament index (AMENT_PREFIX_PATH)",
     "DefinitionNotFoundError: package 'std_msgs' is not in the ament index (AMENT_PREFIX_PATH)"),
    ("ament_index_python.packages.PackageNotFoundError: package 'x' not found",
     "ament_index_python.packages.PackageNotFoundError: package 'x' not found"),
    ('RuntimeEnvSetupError: Failed to set up runtime environment.',
     'RuntimeEnvSetupError: Failed to set up runtime environment.'),
    # A run's own failures: never a reason to stop the others.
    ('RunError: R rep 0 (seed 0): only 3 of 20 iterations within 660 s (selector phase: moving)', None),
    ('GraphTimeout: the estimator did not start within 30 s', None),
    ('TimeoutError: timed out', None),
    ("WorkerCrashedError: The worker died unexpectedly while executing this task.", None),
    ("ValueError: bad DH table", None),
    ('', None), (None, None),
])
def test_environmental_causes_are_told_from_a_runs_own_failures(error: str | None, cause: str | None) -> None:
    assert cluster.environmental_cause(error) == cause


def test_root_cause_unwraps_what_ray_raises_for_a_task() -> None:
    # The function could not be unpickled on the worker: the cause is the traceback's last line.
    assert cluster.root_cause(_task_error(RuntimeError(IMPORT_FAILURE))) == \
        "ModuleNotFoundError: No module named 'calibration_bringup'"
    # The arguments could not be: a system error around the import error.
    system = exceptions.RaySystemError(ModuleNotFoundError("No module named 'calibration_bringup'"), 'tb')
    assert cluster.root_cause(_task_error(system)) == "ModuleNotFoundError: No module named 'calibration_bringup'"
    assert cluster.root_cause(_task_error(OSError("Environment variable 'X' is not set or empty"))) == \
        "OSError: Environment variable 'X' is not set or empty"
    assert cluster.root_cause(exceptions.RuntimeEnvSetupError('agent down')) == \
        'RuntimeEnvSetupError: Failed to set up runtime environment.'
    assert cluster.root_cause(exceptions.WorkerCrashedError()).startswith('WorkerCrashedError: ')


def test_fail_fast_stops_at_the_limit_of_one_cause_on_one_node() -> None:
    ff = cluster.FailFast(limit=3)
    missing = "OSError: Environment variable 'AMENT_PREFIX_PATH' is not set or empty"
    assert ff.record('node-a', 'host-a', missing) is None
    # Other nodes, other causes and a run's own failures count apart (or not at all).
    assert ff.record('node-b', 'host-b', missing) is None
    assert ff.record('node-a', 'host-a', "ModuleNotFoundError: No module named 'pybullet'") is None
    for _ in range(5):
        assert ff.record('node-a', 'host-a', 'RunError: stuck') is None
    assert ff.record('node-a', 'host-a', missing) is None
    stop = ff.record('node-a', 'host-a', missing)
    assert isinstance(stop, cluster.NodeEnvironmentError)
    assert stop.runs == 3 and stop.problems == (cluster.NodeProblem('node-a', 'host-a', missing),)
    text = str(stop)
    assert 'node node-a (host-a)' in text and missing in text and '3 runs failed' in text
    assert text.count('\n') == 2, 'one message: what happened, the node and cause, what to do'


def test_a_failure_on_no_known_node_still_stops_and_says_so() -> None:
    ff = cluster.FailFast(limit=2)
    cause = "ModuleNotFoundError: No module named 'calibration_bringup'"
    assert ff.record('', '', cause) is None
    stop = ff.record('', '', cause)
    assert stop is not None and 'a node the driver cannot name' in str(stop)
    with pytest.raises(ValueError, match='limit must be >= 1, got 0'):
        cluster.FailFast(limit=0)


def test_the_node_check_passes_here_and_names_what_a_run_would_miss(monkeypatch: pytest.MonkeyPatch) -> None:
    info = cluster.check_node(record=True)
    assert info.python == sys.executable and info.node_id == ''     # outside Ray
    # The recorder's message definitions come from the ament index, as in the failure.
    from calibration_bringup import mcap_writer

    mcap_writer._schema_cached.cache_clear()
    monkeypatch.delenv('AMENT_PREFIX_PATH')
    try:
        with pytest.raises(OSError, match='AMENT_PREFIX_PATH'):
            cluster.check_node(record=True)
        cluster.check_node(record=False)       # an unrecorded run does not read the index
    finally:
        mcap_writer._schema_cached.cache_clear()


def test_the_node_check_describes_the_numeric_environment_runs_there_compute_with() -> None:
    info = cluster.check_node(record=False)
    assert info.numeric['numpy'] and 'openblas' in info.numeric['blas'], info.numeric
    # A kernel pinned on the driver is pinned on every node: the variables travel with the tasks.
    assert set(cluster.run_environment({'OPENBLAS_CORETYPE': 'Haswell', 'NPY_DISABLE_CPU_FEATURES': 'X86_V4'},
                                       prefix='/nonexistent')) == {'OPENBLAS_CORETYPE', 'NPY_DISABLE_CPU_FEATURES'}
