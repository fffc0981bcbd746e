"""The layering rule and the generated parameter tables (docs/architecture.md).

Who may import whom: ``body_schema`` imports no workspace package; ``calibration_interfaces`` only
``body_schema``; the node packages (``icub_sim_bridge``, ``marker_detector``, ``dh_estimator``,
``active_selector``) only those two, never each other or ``calibration_bringup``; the recorder and
player of ``calibration_bringup`` are node packages in this sense. The rest of
``calibration_bringup`` (graph assembly, experiment, report) is the top layer and may import
everything.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from calibration_interfaces.parameters import update_tables

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / 'ros2_ws' / 'src'
BOTTOM = {'body_schema', 'calibration_interfaces'}
NODES = {'icub_sim_bridge', 'marker_detector', 'dh_estimator', 'active_selector', 'calibration_viz'}
WORKSPACE = BOTTOM | NODES | {'calibration_bringup'}
#: calibration_bringup modules that run as (or inside) nodes, with the node packages' rule.
BRINGUP_RUNTIME = ('recorder_node', 'player_node', 'mcap_writer', 'node_settings', 'tf_recording')


#: Third-party modules body_schema may import in one module only (docs/architecture.md, section 1).
BODY_SCHEMA_ONLY_IN = {'cv2': {'markers.py'}, 'pinocchio': {'collision.py'}, 'coal': {'collision.py'},
                       'yourdfpy': {'urdf_model.py'}, 'xacro': {'urdf_model.py'}, 'rclpy': set()}


def _all_imports(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports, wherever the import stands."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name.split('.')[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split('.')[0])
    return out


def _imports(path: Path) -> set[str]:
    """Workspace packages a module imports (absolute imports; relative ones stay in the package)."""
    return _all_imports(path) & WORKSPACE


def _modules(package: str) -> list[Path]:
    return sorted((SRC / package / package).rglob('*.py'))


def _allowed(package: str) -> set[str]:
    if package == 'body_schema':
        return {'body_schema'}
    if package == 'calibration_interfaces':
        return BOTTOM
    return BOTTOM | {package}


@pytest.mark.parametrize('package', sorted(BOTTOM | NODES))
def test_packages_import_only_the_layers_below(package: str) -> None:
    modules = _modules(package)
    assert modules, f'no modules found for {package}'
    bad = {str(p.relative_to(SRC)): sorted(_imports(p) - _allowed(package)) for p in modules}
    assert not {k: v for k, v in bad.items() if v}


def test_body_schema_keeps_its_heavy_imports_in_their_one_module() -> None:
    bad = {str(p.relative_to(SRC)): sorted(m for m in _all_imports(p) & set(BODY_SCHEMA_ONLY_IN)
                                           if p.name not in BODY_SCHEMA_ONLY_IN[m])
           for p in _modules('body_schema')}
    assert not {k: v for k, v in bad.items() if v}


def test_bringup_runtime_modules_import_no_node_package() -> None:
    for name in BRINGUP_RUNTIME:
        path = SRC / 'calibration_bringup' / 'calibration_bringup' / f'{name}.py'
        assert not _imports(path) - BOTTOM - {'calibration_bringup'}, path


def test_the_checker_sees_a_forbidden_import(tmp_path: Path) -> None:
    bad = tmp_path / 'x.py'
    bad.write_text('import numpy\nfrom dh_estimator.estimator import OnlineEstimator\nfrom . import y\n')
    assert _imports(bad) == {'dh_estimator'}


@pytest.mark.parametrize('readme', ['README.md', *(str(p.relative_to(ROOT)) for p in sorted(SRC.glob('*/README.md'))),
                                    *(str(p.relative_to(ROOT)) for p in sorted((ROOT / 'docs').rglob('*.md')))])
def test_readme_parameter_tables_match_the_settings_dataclasses(readme: str) -> None:
    # README, the package READMEs and every docs page (the node pages hold the tables).
    text = (ROOT / readme).read_text()
    assert update_tables(text) == text, (f'{readme}: parameter tables are stale; run '
                                         f'`python -m calibration_interfaces.parameters {readme}`')
