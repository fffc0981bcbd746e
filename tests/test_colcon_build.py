"""``colcon build`` of ros2_ws installs what ``ros2 run`` and the ament index expect.

The workspace is built once, with colcon-core and colcon-ros from PyPI, into a temporary
directory (build, install and log bases all outside the repository) with the default isolated
install layout. The expected executables come from each package's ``setup.py`` entry points, so
the test follows the packages as they gain executables.
"""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

pytest.importorskip('colcon_core', reason='colcon-core is not installed (requirements.txt pins it)')
pytest.importorskip('colcon_ros', reason='colcon-ros is not installed (requirements.txt pins it)')

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / 'ros2_ws' / 'src'
PACKAGES = sorted(p.parent.name for p in SRC.glob('*/package.xml'))
# Two shared cores and six packages built one after the other: ~6 s measured, 10 min allowed.
BUILD_TIMEOUT_S = 600.0


def console_scripts(setup_py: Path) -> dict[str, str]:
    """Console scripts declared by a package's ``setup.py``, without running it.

    Parameters
    ----------
    setup_py : Path
        The package's ``setup.py``.

    Returns
    -------
    dict[str, str]
        Executable name -> ``module:function``.
    """
    tree = ast.parse(setup_py.read_text(), filename=str(setup_py))
    # Module-level string constants (package_name = '...') may appear inside entry_points.
    names: dict[str, object] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 \
                and isinstance(node.targets[0], ast.Name):
            try:
                names[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'setup':
            for kw in node.keywords:
                if kw.arg == 'entry_points':
                    expr = ast.Expression(kw.value)
                    value = eval(compile(expr, str(setup_py), 'eval'), {'__builtins__': {}}, names)
                    scripts = {}
                    for spec in value.get('console_scripts', []):
                        name, _, target = spec.partition('=')
                        scripts[name.strip()] = target.strip()
                    return scripts
    return {}


def _pollution() -> set[Path]:
    """Build artefacts colcon or setuptools would leave in the repository if misdirected."""
    found = set()
    for base in [REPO, REPO / 'ros2_ws', *(SRC / p for p in PACKAGES)]:
        for name in ('build', 'install', 'log'):
            if (base / name).exists():
                found.add(base / name)
    return found


@dataclass
class Build:
    """One ``colcon build`` of the workspace."""

    install: Path  # the install base (isolated layout: install/<pkg>/...)
    seconds: float  # wall time of the build
    output: str  # colcon's console output
    new_pollution: set[Path]  # build artefacts that appeared in the repository


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> Build:
    """Run ``colcon build`` once for the module."""
    tmp = tmp_path_factory.mktemp('colcon')
    before = _pollution()
    env = dict(os.environ)
    env.update(
        COLCON_HOME=str(tmp / 'colcon_home'),  # no user defaults.yaml changes the build
        PYTHONDONTWRITEBYTECODE='1',  # no __pycache__ in the source tree
        PATH=f'{Path(sys.executable).parent}{os.pathsep}{env.get("PATH", "")}',
    )
    env.pop('COLCON_DEFAULTS_FILE', None)
    cmd = [
        sys.executable, '-c', 'import sys; from colcon_core.command import main; sys.exit(main())',
        '--log-base', str(tmp / 'log'),
        'build',
        '--base-paths', str(SRC),
        '--build-base', str(tmp / 'build'),
        '--install-base', str(tmp / 'install'),
        '--executor', 'sequential',
        '--event-handlers', 'console_direct-',
    ]
    start = time.monotonic()
    proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True,
                          timeout=BUILD_TIMEOUT_S)
    elapsed = time.monotonic() - start
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    return Build(install=tmp / 'install', seconds=elapsed, output=proc.stdout,
                 new_pollution=_pollution() - before)


def test_every_package_was_built(built: Build) -> None:
    install = built.install
    assert len(PACKAGES) >= 6
    for pkg in PACKAGES:
        assert f'Finished <<< {pkg}' in built.output, built.output
        assert (install / pkg).is_dir(), pkg


def test_console_scripts_land_in_lib_pkg(built: Build) -> None:
    install = built.install
    total = 0
    for pkg in PACKAGES:
        scripts = console_scripts(SRC / pkg / 'setup.py')
        for exe in scripts:
            path = install / pkg / 'lib' / pkg / exe
            assert path.is_file(), f'{pkg}: {exe} missing at {path}'
            assert os.access(path, os.X_OK), f'{path} is not executable'
            # setuptools' generated launcher names the distribution and the entry point.
            assert f"'console_scripts', '{exe}'" in path.read_text(), path
            # ros2 run lists lib/<pkg>; nothing should land in bin/ instead.
            assert not (install / pkg / 'bin' / exe).exists(), f'{exe} also installed to bin/'
        total += len(scripts)
    assert total >= 1, 'no package declares a console script: the parser is broken'


def test_entry_point_parser_reads_known_script() -> None:
    scripts = console_scripts(SRC / 'icub_sim_bridge' / 'setup.py')
    assert scripts.get('sim_node') == 'icub_sim_bridge.sim_node:main'


def test_ament_index_marker_package_xml_and_config(built: Build) -> None:
    install = built.install
    for pkg in PACKAGES:
        share = install / pkg / 'share'
        assert (share / 'ament_index' / 'resource_index' / 'packages' / pkg).is_file(), pkg
        assert (share / pkg / 'package.xml').read_text() == (SRC / pkg / 'package.xml').read_text()
        for cfg in sorted((SRC / pkg / 'config').glob('*')):
            if cfg.is_file():
                installed = share / pkg / 'config' / cfg.name
                assert installed.is_file(), f'{pkg}: config {cfg.name} not installed'
                assert installed.read_bytes() == cfg.read_bytes()
        for launch in sorted((SRC / pkg / 'launch').glob('*.launch.py')):
            installed = share / pkg / 'launch' / launch.name
            assert installed.is_file(), f'{pkg}: launch file {launch.name} not installed'


def test_sourced_install_resolves_to_the_install(built: Build) -> None:
    """After sourcing ``install/setup.sh``, the ament index and every entry point resolve into
    the install prefix (not to the editable sources in the venv), as ``ros2 run`` would."""
    install = built.install
    expected = {pkg: console_scripts(SRC / pkg / 'setup.py') for pkg in PACKAGES}
    probe = textwrap.dedent(f'''
        import json, importlib.metadata as md
        from ament_index_python.packages import get_package_prefix, get_package_share_directory
        out = {{}}
        for pkg, scripts in json.loads({json.dumps(json.dumps(expected))}).items():
            out[pkg] = {{'prefix': get_package_prefix(pkg),
                         'share': get_package_share_directory(pkg), 'scripts': {{}}}}
            eps = md.distribution(pkg).entry_points
            for exe in scripts:
                (ep,) = [e for e in eps if e.group == 'console_scripts' and e.name == exe]
                func = ep.load()
                import sys
                out[pkg]['scripts'][exe] = [ep.value, sys.modules[func.__module__].__file__]
        print(json.dumps(out))
    ''')
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'AMENT_PREFIX_PATH')}
    env['PYTHONDONTWRITEBYTECODE'] = '1'
    proc = subprocess.run(
        ['sh', '-c', f'. "{install}/setup.sh" && exec "{sys.executable}" -c "$0"', probe],
        env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    for pkg, scripts in expected.items():
        assert result[pkg]['prefix'] == str(install / pkg)
        assert result[pkg]['share'] == str(install / pkg / 'share' / pkg)
        for exe, target in scripts.items():
            value, module_file = result[pkg]['scripts'][exe]
            assert value.replace(' ', '') == target.replace(' ', '')
            assert Path(module_file).is_relative_to(install / pkg), (exe, module_file)


def test_build_is_fast_and_leaves_the_repository_clean(built: Build) -> None:
    assert not built.new_pollution, f'build artefacts in the repository: {built.new_pollution}'
    assert built.seconds < 120.0, f'colcon build took {built.seconds:.1f} s'
