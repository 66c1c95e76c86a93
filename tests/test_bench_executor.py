"""The bench executor: the same results on the local pool, in this process and on Ray; a task
whose worker process dies is run again; ``bench paper`` prints the same table on Ray."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.bench.executor import ExecutorSettings, run_ordered, run_tasks

# Spawned workers import this module for its task functions: the bench's heavy modules (torch,
# casadi) are imported inside the tests that need them.

TASKS = list(range(6))


def seeded_sum(seed: int) -> tuple[int, float]:
    """A deterministic task: the sum of a seeded normal draw."""
    return seed, float(np.random.default_rng(seed).standard_normal(1000).sum())


def die_once(seed: int, marker: str) -> tuple[int, float]:
    """Task 0 kills its worker process the first time it runs (the marker file remembers)."""
    if seed == 0 and not os.path.exists(marker):
        Path(marker).touch()
        os._exit(1)
    return seeded_sum(seed)


EXPECTED = [seeded_sum(s) for s in TASKS]


@pytest.fixture(scope="module")
def ray_cluster():
    """One two-CPU Ray shared by this module's tests; each run joins it by address."""
    if importlib.util.find_spec("ray") is None:
        pytest.skip("ray is not installed (pip install -e '.[test,ray]')")
    import ray.cloudpickle
    from ray.cluster_utils import Cluster

    # Ray's workers cannot import this test module: send its task functions by value.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2})
    yield cluster.address
    cluster.shutdown()


def test_local_pool_and_this_process_give_the_same_results_in_task_order():
    assert run_ordered(seeded_sum, TASKS, ExecutorSettings(jobs=2), progress=False) == EXPECTED
    assert run_ordered(seeded_sum, TASKS, ExecutorSettings(jobs=1), progress=False) == EXPECTED
    # run_tasks yields (index, result) pairs as they complete, each exactly once.
    assert sorted(run_tasks(seeded_sum, TASKS, ExecutorSettings(jobs=2), progress=False)) == list(enumerate(EXPECTED))


def test_ray_gives_the_local_results(ray_cluster):
    settings = ExecutorSettings(kind="ray", jobs=2, address=ray_cluster)
    assert run_ordered(seeded_sum, TASKS, settings, progress=False) == EXPECTED


def test_local_pool_reruns_the_tasks_of_a_dead_worker(tmp_path):
    marker = tmp_path / "died"
    out = run_ordered(partial(die_once, marker=str(marker)), TASKS, ExecutorSettings(jobs=2), progress=False)
    assert marker.exists() and out == EXPECTED


def test_local_pool_gives_up_after_max_retries(tmp_path):
    with pytest.raises(RuntimeError, match="lost its worker process"):
        run_ordered(partial(die_once, marker=str(tmp_path / "died")), TASKS, ExecutorSettings(jobs=2, max_retries=0),
                    progress=False)


def test_ray_reruns_the_task_of_a_dead_worker(ray_cluster, tmp_path):
    marker = tmp_path / "died"
    settings = ExecutorSettings(kind="ray", jobs=2, address=ray_cluster)
    assert run_ordered(partial(die_once, marker=str(marker)), TASKS, settings, progress=False) == EXPECTED
    assert marker.exists()


def test_executor_options_are_checked(monkeypatch, tmp_path, capsys):
    from cfknode.app.cli import main

    assert main(["bench", "paper", "--address", "127.0.0.1:6379", "--out", str(tmp_path)]) == 2
    assert "--address needs --executor ray" in capsys.readouterr().err
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real_find_spec(name, *a))
    for argv in (["paper", "--quick"], ["online", "--quick"]):
        assert main(["bench", *argv, "--executor", "ray", "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "pip install 'cfknode[ray]'" in err
    assert not (tmp_path / "x").exists()  # refused before anything was written


def _tiny_quick(formulations: tuple[str, ...], seed: int = 0):  # noqa: ANN202 - a BenchPlan
    from cfknode.app.bench.paper.protocol import MassEvent
    from cfknode.app.bench.paper.suite import BenchPlan, Cell

    # --quick takes minutes on a loaded two-core machine; this keeps every path of the plan
    # (an offline model, a run that waits for it, one that does not) at 1.5 s simulated.
    return BenchPlan(formulations=formulations, cells=(Cell(2.0, 0.8),), controllers=("geometric", "knode_offline"),
                     duration=1.5, events=(MassEvent(0.5, -0.015), MassEvent(1.0, 0.025)), seed=seed)


def _bench(out: Path, *flags: str) -> tuple[dict, list[str]]:
    from cfknode.app.cli import main

    argv = ["bench", "paper", "--quick", "--formulation", "paper", "--out", str(out), *flags]
    assert main(argv) == 0
    data = json.loads((out / "paper_full_quick.json").read_text())
    rows = [line for line in (out / "paper_full_quick.md").read_text().splitlines() if line.startswith("| ")]
    return data, rows


def test_bench_paper_prints_the_same_table_on_ray(ray_cluster, tmp_path, monkeypatch):
    from cfknode.app.bench.paper.suite import BenchPlan

    monkeypatch.setattr(BenchPlan, "quick", classmethod(lambda cls, forms, seed=0: _tiny_quick(forms, seed)))
    local, local_rows = _bench(tmp_path / "local", "--jobs", "2")
    monkeypatch.setenv("RAY_ADDRESS", ray_cluster)  # the cluster is found through the environment
    on_ray, ray_rows = _bench(tmp_path / "ray", "--executor", "ray")
    # The paper formulation is lockstep and seeded: every number is reproducible.
    assert [(r["controller"], r["mse"]) for r in on_ray["runs"]] == [(r["controller"], r["mse"]) for r in local["runs"]]
    assert [r["controller"] for r in on_ray["runs"]] == ["geometric", "knode_offline"]  # plan order
    assert ray_rows == local_rows and any("KNODE-MPC (offline)" in row for row in ray_rows)
    assert "--executor ray" in on_ray["command"] and on_ray["executor"].startswith("Ray at")
