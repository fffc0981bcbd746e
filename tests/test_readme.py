"""The front page cannot rot: its commands run, its links resolve, it stays short and current.

Every fenced ``bash`` block of README.md is run (``text`` blocks are output, ``bibtex`` a
citation): each command line with the small settings of ``SMALL`` (a 3-iteration demo, a
2-iteration experiment of one method and repetition for each system, the site built into a temporary
directory), paths under ``results/`` and the user's ``my_arm.yaml`` moved into a temporary
directory and ``--iterations 50`` cut to 2. A command no rule shrinks runs as written. ``make
test`` is not run here (it is this suite: CI's ``.ci/run`` runs it); the test checks that make
knows the target and that ``.ci/run`` calls it.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
DOCS = ROOT / 'docs'

#: README command (after the generic substitutions) -> the command the test runs ({tmp}: a temporary directory).
SMALL = {
    'make demo': 'make demo DEMO_ARGS="--iterations 3 --output {tmp}/demo"',
    'make experiment': (
        'make experiment EXPERIMENT_ARGS="--repetitions 1 --iterations 2 --methods AL '
        '--jobs 1 --no-record --output {tmp}/experiment"'),
    'make experiment-paper': (
        'make experiment-paper EXPERIMENT_ARGS="--repetitions 1 --iterations 2 --methods AL '
        '--jobs 1 --no-record --output {tmp}/experiment-paper"'),
    "make experiment EXPERIMENT_ARGS='--repetitions 20'": (
        'make experiment EXPERIMENT_ARGS="--repetitions 1 --iterations 2 --methods AL '
        '--jobs 1 --no-record --output {tmp}/experiment"'),
    "make experiment-paper EXPERIMENT_ARGS='--repetitions 20'": (
        'make experiment-paper EXPERIMENT_ARGS="--repetitions 1 --iterations 2 --methods AL '
        '--jobs 1 --no-record --output {tmp}/experiment-paper"'),
    "make experiment-ablation EXPERIMENT_ARGS='--repetitions 20'": (
        'make experiment-ablation EXPERIMENT_ARGS="--repetitions 1 --iterations 2 --methods R --jobs 1 '
        '--output {tmp}/ablation --paper-output {tmp}/paper --ours-output {tmp}/ours"'),
    'make docs': 'make docs SITE={tmp}/site',
}
#: Run by CI, not from inside the suite it starts.
RUN_BY_CI = {'make test'}
#: Sentences that compare the code with an earlier release belong in CHANGELOG.md.
RELEASE_TALK = re.compile(r'\b(last|previous|earlier|prior) release|release before|the one before|'
                          r'\bformer (default|behaviour)|no longer|(until|since) this release', re.I)


def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf'^```{lang}\n(.*?)^```', text, re.M | re.S)


def _commands(block: str) -> list[str]:
    """The block's command lines, comments stripped, backslash continuations joined."""
    out = []
    for line in block.replace('\\\n', ' ').splitlines():
        line = re.sub(r'\s+#.*$', '', line).strip()
        if line and not line.startswith('#'):
            out.append(line)
    return out


def _small(command: str, tmp: Path) -> str:
    command = command.replace('--iterations 50', '--iterations 2')
    command = re.sub(r'(?<![\w/])results/', f'{tmp}/results/', command)
    command = re.sub(r'(?<![\w/])my_arm\.yaml', f'{tmp}/my_arm.yaml', command)
    return SMALL.get(command, command).format(tmp=tmp)


README_BLOCKS = [_commands(b) for b in _blocks(README.read_text(), 'bash')]
README_COMMANDS = [c for b in README_BLOCKS for c in b]


def test_the_readme_is_a_front_page() -> None:
    text = README.read_text()
    assert len(text.splitlines()) <= 250
    assert not RELEASE_TALK.search(text), RELEASE_TALK.search(text)


def test_the_docs_describe_the_code_as_it_is() -> None:
    # Measurement write-ups (docs/results/<study>/) name the commits they were made at; the
    # pages do not compare with earlier releases (that is the changelog's job).
    pages = [p for p in DOCS.rglob('*.md') if p.parent.parent != DOCS / 'results' and p.name != 'changelog.md']
    found = {str(p.relative_to(ROOT)): m.group(0) for p in pages if (m := RELEASE_TALK.search(p.read_text()))}
    assert not found


def test_the_release_talk_check_sees_a_comparison() -> None:
    assert RELEASE_TALK.search('0.47 mm at the last release')
    assert not RELEASE_TALK.search('seeds that were not used to choose any setting')


def test_the_readme_shows_the_two_commands() -> None:
    assert README_COMMANDS[:2] == ['make demo', 'make test']


@pytest.mark.parametrize('target', ['README.md', 'CHANGELOG.md', *sorted(
    str(p.relative_to(ROOT)) for p in (ROOT / 'ros2_ws' / 'src').glob('*/README.md'))])
def test_every_relative_link_resolves(target: str) -> None:
    path = ROOT / target
    text = re.sub(r'^```.*?^```', '', path.read_text(), flags=re.M | re.S)
    missing = []
    for link in re.findall(r'\]\(([^)\s]+)\)', text):
        if re.match(r'[a-z]+://|#|mailto:', link):
            continue
        if not (path.parent / link.split('#')[0]).exists():
            missing.append(link)
    assert not missing


def test_make_test_is_what_ci_runs() -> None:
    assert 'make test' in RUN_BY_CI
    assert re.search(r'^make test$', (ROOT / '.ci' / 'run').read_text(), re.M)
    subprocess.run(['make', '-n', 'test'], cwd=ROOT, check=True, capture_output=True)


@pytest.mark.slow
@pytest.mark.parametrize('block', [b for b in README_BLOCKS if set(b) - RUN_BY_CI], ids=lambda b: ' && '.join(b)[:60])
def test_every_readme_command_runs(block: list[str], tmp_path: Path) -> None:
    # One block's commands run in order in one shell, sharing one temporary directory.
    small = 'set -euo pipefail\n' + '\n'.join(_small(c, tmp_path) for c in block if c not in RUN_BY_CI)
    env = {**os.environ, 'AMENT_PREFIX_PATH': str(ROOT / '.venv'), 'PATH': f"{ROOT / '.venv' / 'bin'}:{os.environ['PATH']}"}
    done = subprocess.run(['bash', '-c', small], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (shlex.quote(small), done.stdout[-3000:], done.stderr[-3000:])


def test_the_small_settings_shrink_what_they_should(tmp_path: Path) -> None:
    assert _small('make demo', tmp_path) == f'make demo DEMO_ARGS="--iterations 3 --output {tmp_path}/demo"'
    cmd = _small('scripts/run_calibration.sh --robot my_arm.yaml --iterations 50 --output results/my_arm', tmp_path)
    assert cmd == (f'scripts/run_calibration.sh --robot {tmp_path}/my_arm.yaml --iterations 2 '
                   f'--output {tmp_path}/results/my_arm')
    assert _small('cp a/b/ur5e.yaml my_arm.yaml', tmp_path) == f'cp a/b/ur5e.yaml {tmp_path}/my_arm.yaml'
