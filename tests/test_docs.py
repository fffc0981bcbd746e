"""The documentation site builds strict, and its API reference covers every public name.

``make docs`` builds the site with ``mkdocs build --strict`` (mkdocs.yml): a broken link or
anchor, a page outside the nav, an unresolved cross-reference or a docstring mkdocstrings cannot
render fails it. The API reference pages (docs/api/) must document every name in the ``__all__``
of every module of ``body_schema`` and ``calibration_interfaces``; the built site's inventory
(``objects.inv``, one line per rendered object) is read to check it.
"""
from __future__ import annotations

import ast
import importlib
import os
import subprocess
import zlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / 'ros2_ws' / 'src'
PACKAGES = ('body_schema', 'calibration_interfaces')


def _public_names() -> dict[str, list[str]]:
    """``module -> __all__`` for every module of the two packages (read statically)."""
    out = {}
    for package in PACKAGES:
        for path in sorted((SRC / package / package).glob('*.py')):
            module = package if path.stem == '__init__' else f'{package}.{path.stem}'
            names = None
            for node in ast.parse(path.read_text()).body:
                targets = node.targets if isinstance(node, ast.Assign) else (
                    [node.target] if isinstance(node, ast.AnnAssign) else [])
                if any(getattr(t, 'id', None) == '__all__' for t in targets):
                    names = ast.literal_eval(node.value)
            out[module] = names
    return out


def _inventory(site: Path) -> set[str]:
    """Object names of a Sphinx-format ``objects.inv`` (four header lines, then zlib)."""
    data = (site / 'objects.inv').read_bytes()
    body = data.split(b'\n', 4)[4]
    return {line.split(' ', 1)[0] for line in zlib.decompress(body).decode().splitlines() if line}


@pytest.fixture(scope='module')
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('site')
    env = {**os.environ, 'NO_MKDOCS_2_WARNING': '1'}
    done = subprocess.run([str(ROOT / '.venv' / 'bin' / 'mkdocs'), 'build', '--strict', '--site-dir', str(out)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
    return out


def test_every_module_declares_its_public_names() -> None:
    assert {m: n for m, n in _public_names().items() if n is None} == {}


def test_the_site_builds_strict_with_every_page(site: Path) -> None:
    for page in ('index.html', 'getting-started.html', 'nodes/estimator.html', 'api/body_schema.html', 'changelog.html'):
        assert (site / page).is_file(), page
    # The parameter tables and the changelog are in the pages, not left as markers.
    assert '<code>change_count</code>' in (site / 'nodes' / 'estimator.html').read_text()
    assert 'Keep a Changelog' in (site / 'changelog.html').read_text()


def test_the_api_reference_covers_every_public_name(site: Path) -> None:
    documented = _inventory(site)
    missing = []
    for module, names in _public_names().items():
        for name in names or []:
            target = f'{module}.{name}'
            if module in PACKAGES:  # a package re-exports: its name is documented where it is defined
                target = f'{importlib.import_module(module).__dict__[name].__module__}.{name}'
            if target not in documented:
                missing.append(target)
    assert missing == []


def test_the_coverage_check_reads_an_inventory(tmp_path: Path) -> None:
    lines = 'body_schema.kinematics.forward_kinematics py:function 1 api/body_schema.html#$ -\n'
    (tmp_path / 'objects.inv').write_bytes(b'# Sphinx inventory version 2\n# Project: x\n# Version: 0\n'
                                           b'# The remainder of this file is compressed using zlib.\n'
                                           + zlib.compress(lines.encode()))
    assert _inventory(tmp_path) == {'body_schema.kinematics.forward_kinematics'}
