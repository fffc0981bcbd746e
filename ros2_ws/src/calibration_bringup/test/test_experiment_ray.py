"""The experiment on a two-node Ray cluster on this machine (``ray.cluster_utils.Cluster``: a head and
a second node, one CPU each), submitted through ``address`` as ``--address`` does: the runs spread
over both nodes and their rows equal those of the same experiment on a local runtime."""
from __future__ import annotations

import io
import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from calibration_bringup import experiment as ex

ray = pytest.importorskip('ray')
from ray.cluster_utils import Cluster  # noqa: E402 (after the skip when Ray is missing)

# Domains 200..213, clear of the suite's others (see test_experiment_run.py), offset from that test's.
DOMAIN_BASE = 200 + 2 * ((os.getpid() + 3) % 7)
NODE_MEMORY = {'num_cpus': 1, 'object_store_memory': 100 * 1024**2}


def _rows(outcome: ex.ExperimentOutcome) -> dict[tuple[str, int], list[dict[str, Any]]]:
    assert all(r.rows is not None for r in outcome.results), outcome.failures
    return {(r.spec.method, r.spec.repetition): r.rows for r in outcome.results}


@ray.remote(num_cpus=1)
def _python() -> str:
    return sys.executable


@pytest.mark.slow
def test_runs_spread_over_two_nodes_and_equal_a_local_run(tmp_path: Path) -> None:
    config = ex.ExperimentConfig(repetitions=2, iterations=2, methods=('AL', 'R'), jobs=2, record=False,
                                 figures=False, seed_base=5, domain_base=DOMAIN_BASE)
    log = io.StringIO()
    cluster = Cluster(initialize_head=True, head_node_args={**NODE_MEMORY, 'include_dashboard': False})
    try:
        cluster.add_node(**NODE_MEMORY)
        cluster.wait_for_nodes()
        nodes = {n.node_id for n in cluster.list_all_nodes()}
        on_cluster = ex.run_experiment(replace(config, output=tmp_path / 'cluster', address=cluster.address),
                                       stream=log)
        assert not ray.is_initialized()         # the runner disconnected what it connected
        # The cluster's workers run this venv's Python (the nodes inherit it from this process).
        ray.init(address=cluster.address, logging_level='ERROR', log_to_driver=False)
        assert set(ray.get([_python.remote() for _ in range(2)])) == {sys.executable}
    finally:
        ray.shutdown()
        cluster.shutdown()
    assert on_cluster.failures == [], log.getvalue()
    assert len(on_cluster.results) == 4
    assert {r.node_id for r in on_cluster.results} == nodes and len(nodes) == 2

    local = ex.run_experiment(replace(config, output=tmp_path / 'local'), stream=log)
    assert local.failures == [], log.getvalue()
    assert len({r.node_id for r in local.results}) == 1

    remote_rows, local_rows = _rows(on_cluster), _rows(local)
    assert remote_rows.keys() == local_rows.keys() == {(m, r) for m in config.methods for r in range(2)}
    for key, rows in remote_rows.items():
        assert len(rows) == len(local_rows[key]) == config.iterations + 1
        for a, b in zip(rows, local_rows[key]):
            assert (a['iteration'], a['outcome'], a['detected'], a['discarded'], a['robot_seed']) == \
                (b['iteration'], b['outcome'], b['detected'], b['discarded'], b['robot_seed']), key
            for column in ('position_mm', 'orientation_deg', 'movement_deg'):
                assert a[column] == pytest.approx(b[column], abs=1e-9), (key, a['iteration'], column)
    # The driver wrote both experiments' files the same way.
    for name in ('cluster', 'local'):
        assert len(ex.read_rows(tmp_path / name / 'metrics.csv')) == 4 * (config.iterations + 1)
