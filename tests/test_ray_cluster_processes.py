"""The experiment on a Ray cluster of real ``ray start`` processes, started as the README says, from a
clean environment (only ``PATH`` and ``HOME``: nothing sourced or exported).

A head and a second node from this venv run ``experiment --quick --address 127.0.0.1:PORT`` (two
methods x two repetitions x three iterations, recorded): every run finishes and the runs' logs show
both nodes. Then a node whose Python has Ray but not this workspace joins (a venv whose ``.pth``
puts this venv's third-party packages on its path, not the workspace's editable installs: a
machine where Ray was installed without ``make setup``): the same command stops before any run with
one message naming that node and ``No module named 'calibration_bringup'``.

Isolation on a shared machine: free loopback ports for the head and every fixed-port service (the
client server, the dashboard and its agents), a temporary directory per node (short: Ray's unix
sockets live there), a temporary ``HOME``; each ``ray start`` in a session of its own, and teardown
ends exactly the processes of those sessions (``ray stop`` would end every Ray on the machine).
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
import tempfile
import time
import venv
from pathlib import Path
from typing import Iterator

import pytest

pytest.importorskip('ray')

VENV_BIN = Path(sys.executable).parent
# Domains 200..213 (see ros2_ws/src/calibration_bringup/test/test_experiment_run.py), offset from the others.
DOMAIN_BASE = 200 + 2 * ((os.getpid() + 5) % 7)
NODE_ID = re.compile(r'Ray node ([0-9a-f]{56})')


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _session_pids(sid: int) -> list[int]:
    """Live (not zombie) processes of session ``sid``."""
    pids = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            if os.getsid(int(entry)) != sid:
                continue
            state = Path(f'/proc/{entry}/stat').read_text().rsplit(')', 1)[1].split()[0]
        except (OSError, IndexError):     # gone meanwhile
            continue
        if state != 'Z':
            pids.append(int(entry))
    return pids


def _node_id(temp_dir: Path) -> str:
    """The Ray node id of the node started with ``--temp-dir temp_dir`` (its session's port files)."""
    ids = {p.name.rsplit('_', 1)[1] for p in (temp_dir / 'session_latest').glob('*_port_*')}
    assert len(ids) == 1, ids
    return ids.pop()


class Cluster:
    """``ray start`` processes, each in its own session; :meth:`stop` ends exactly those sessions."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.home = root / 'home'
        self.home.mkdir()
        self.port = _free_port()
        self.address = f'127.0.0.1:{self.port}'
        self.sessions: list[int] = []

    def env(self, bin_dir: Path = VENV_BIN) -> dict[str, str]:
        return {'PATH': f'{bin_dir}:/usr/bin:/bin', 'HOME': str(self.home)}

    def start(self, name: str, args: list[str], bin_dir: Path = VENV_BIN) -> Path:
        """Run ``<bin_dir>/ray start <args>`` (it returns once the node is up) with isolation flags;
        returns the node's temp dir."""
        temp = self.root / name
        isolation = ['--temp-dir', str(temp), '--dashboard-agent-listen-port', str(_free_port())]
        if '--head' in args:
            isolation += ['--ray-client-server-port', str(_free_port()), '--dashboard-port', str(_free_port())]
        proc = subprocess.Popen([str(bin_dir / 'ray'), 'start', *args, *isolation], env=self.env(bin_dir),
                                cwd=self.root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
        self.sessions.append(proc.pid)
        out, _ = proc.communicate(timeout=180)
        assert proc.returncode == 0, out
        return temp

    def stop(self) -> None:
        for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 10.0)):
            for sid in self.sessions:
                for pid in _session_pids(sid):
                    try:
                        os.kill(pid, sig)
                    except ProcessLookupError:
                        pass
            deadline = time.monotonic() + wait
            while any(_session_pids(s) for s in self.sessions) and time.monotonic() < deadline:
                time.sleep(0.2)
        left = {s: _session_pids(s) for s in self.sessions}
        assert not any(left.values()), f'processes left running: {left}'


@pytest.fixture
def cluster() -> Iterator[Cluster]:
    # Short and outside pytest's tmp_path: Ray's unix socket paths must stay under ~107 characters.
    root = Path(tempfile.mkdtemp(prefix='rayc-', dir='/tmp'))
    c = Cluster(root)
    try:
        yield c
    finally:
        c.stop()
        shutil.rmtree(root, ignore_errors=True)


def _experiment(cluster: Cluster, output: Path) -> subprocess.CompletedProcess[str]:
    cmd = [str(VENV_BIN / 'python'), '-m', 'calibration_bringup.experiment', '--quick', '--address', cluster.address,
           '--methods', 'R', 'AL', '--repetitions', '2', '--iterations', '3', '--jobs', '2',
           '--domain-base', str(DOMAIN_BASE), '--no-figures', '--output', str(output)]
    return subprocess.run(cmd, env=cluster.env(), cwd=cluster.root, capture_output=True, text=True, timeout=600)


def _workspace_less_python(root: Path) -> Path:
    """A venv with this venv's Ray (and every other third-party package) but not the workspace."""
    venv.EnvBuilder(with_pip=False).create(root)
    site = root / 'lib' / f'python{sys.version_info.major}.{sys.version_info.minor}' / 'site-packages'
    # A plain path entry: the .pth files there (the workspace's editable installs) are not processed.
    (site / 'this_venvs_packages.pth').write_text(sysconfig.get_paths()['purelib'] + '\n')
    ray = root / 'bin' / 'ray'
    ray.write_text(f'#!{root / "bin" / "python"}\nimport sys\nfrom ray.scripts.scripts import main\nsys.exit(main())\n')
    ray.chmod(0o755)
    return root / 'bin'


@pytest.mark.slow
def test_runs_on_ray_start_nodes_with_nothing_exported_and_a_broken_node_stops_it_at_once(cluster: Cluster) -> None:
    head = cluster.start('head', ['--head', '--port', str(cluster.port), '--num-cpus', '1',
                                  '--include-dashboard', 'false', '--disable-usage-stats'])
    second = cluster.start('n2', ['--address', cluster.address, '--num-cpus', '1', '--disable-usage-stats'])

    done = _experiment(cluster, cluster.root / 'out')
    assert done.returncode == 0, done.stderr
    runs = cluster.root / 'out' / 'runs'
    assert len(list(runs.glob('*/rep*.csv'))) == 4, done.stderr
    assert len(list(runs.glob('*/rep*.mcap'))) == 4        # recorded: the ament index reached the workers
    nodes = {NODE_ID.search(p.read_text()).group(1) for p in runs.glob('*/rep*.log')}
    assert nodes == {_node_id(head), _node_id(second)}

    bin_dir = _workspace_less_python(cluster.root / 'bv')
    broken = cluster.start('n3', ['--address', cluster.address, '--num-cpus', '1', '--disable-usage-stats'],
                           bin_dir=bin_dir)
    t0 = time.monotonic()
    stopped = _experiment(cluster, cluster.root / 'out-broken')
    seconds = time.monotonic() - t0
    assert stopped.returncode == 1, stopped.stderr
    named = [line for line in stopped.stderr.splitlines() if line.startswith('  node ')]
    assert len(named) == 1, stopped.stderr      # the two good nodes passed the check
    assert named[0].startswith(f'  node {_node_id(broken)} ({socket.gethostname()}, ')
    assert named[0].endswith("): ModuleNotFoundError: No module named 'calibration_bringup'"), stopped.stderr
    assert 'no run was started' in stopped.stderr and 'FAILED' not in stopped.stderr, stopped.stderr
    assert not list((cluster.root / 'out-broken').glob('runs/*/*')), 'no run may have been queued'
    print(f'broken node reported {seconds:.1f} s after the command started')
