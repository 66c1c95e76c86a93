"""``cfknode bench paper --quick``: the whole benchmark path (parallel workers, both formulations,
every controller, markdown, JSON and the plot) on one short cell.

The command runs as a user runs it, on a plan shorter than ``--quick``'s own: 1.5 s with the two mass
events at 0.4 s and 0.9 s (still several online rounds after each), and cfknode's online rounds
taking a fixed 0.1 s of flight time instead of the measured training wall time, so the rounds it
counts do not depend on the machine's load. What ``--quick`` itself plans is checked on its own.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from cfknode.app.bench.paper.protocol import MassEvent
from cfknode.app.bench.paper.suite import BenchPlan, Cell
from cfknode.app.cli import main

QUICK = BenchPlan.quick  # the command's own, before the fixture shortens it
SHORT = {"duration": 1.5, "events": (MassEvent(0.4, -0.015), MassEvent(0.9, 0.025)), "fixed_latency": 0.1}


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(BenchPlan, "quick", classmethod(lambda cls, forms, seed=0: replace(QUICK(forms, seed), **SHORT)))
        assert main(["bench", "paper", "--mode", "full", "--quick", "--jobs", "2", "--out", str(out)]) == 0
    return out


def test_quick_plans_one_cell_with_both_events_in_3_5_s():
    plan = QUICK(("paper", "default"), 3)
    assert plan.cells == (Cell(2.0, 0.8),) and plan.duration == 3.5 and plan.seed == 3
    assert plan.events == (MassEvent(1.0, -0.015), MassEvent(2.0, 0.025)) and plan.fixed_latency is None
    assert len(plan.tasks()) == 12  # per formulation: the offline model and five controllers


def test_quick_bench_writes_table_json_and_plots(quick_bench):
    md = (quick_bench / "paper_full_quick.md").read_text()
    for label in ("formulation: paper", "formulation: default", "MPC (nominal)", "KNODE-MPC (offline)", "Geometric",
                  "KNODE-MPC-Online", "Oracle (true mass)", "this Online / Oracle"):
        assert label in md
    assert "paper: MPC" not in md  # a shortened protocol is not compared with Table 1
    for name in ("paper", "default"):
        png = quick_bench / f"paper_full_quick_fig2_{name}.png"
        assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_quick_bench_json_holds_every_run(quick_bench):
    data = json.loads((quick_bench / "paper_full_quick.json").read_text())
    assert data["plan"]["duration_s"] == SHORT["duration"] and data["jobs"] == 2
    runs = {(r["formulation"], r["controller"]): r for r in data["runs"]}
    assert set(runs) == {(f, c) for f in ("paper", "default") for c in ("mpc", "knode_offline", "geometric", "knode_online", "oracle")}
    for r in runs.values():
        assert math.isfinite(r["mse"]) and r["mse"] > 0 and r["failed_solves"] == 0
        assert r["mse"] == pytest.approx(sum(r["mse_per_axis"]) / 3, rel=1e-9)
    # The paper's loop trains after every window from the first event on (7 windows of 0.15 s on this plan), and
    # swaps each in; cfknode's gates its swaps.
    paper_rounds = runs[("paper", "knode_online")]["rounds"]
    assert len(paper_rounds) >= 5 and all(r["accepted"] for r in paper_rounds)
    ends = np.array([r["window_end"] for r in paper_rounds])
    window = float(np.median(np.diff(ends)))
    assert np.all(np.abs(np.diff(ends) - window) < 0.01)  # no window skipped
    assert ends[0] - SHORT["events"][0].time < window + 0.01 and SHORT["duration"] - ends[-1] < window + 0.01
    default_rounds = runs[("default", "knode_online")]["rounds"]
    assert any(not r["accepted"] for r in default_rounds) and any(r["swap"] is not None for r in default_rounds)
    # Preview: cfknode's nominal MPC tracks far better than the paper's constant-point MPC.
    assert runs[("default", "mpc")]["mse"] < 0.1 * runs[("paper", "mpc")]["mse"]
    assert len(data["offline_models"]) == 2


def test_bench_rejects_bad_arguments(tmp_path, capsys):
    assert main(["bench", "paper", "--jobs", "0", "--out", str(tmp_path)]) == 2
    assert "--jobs must be >= 1" in capsys.readouterr().err
    not_dir = tmp_path / "file"
    not_dir.write_text("x")
    assert main(["bench", "paper", "--out", str(not_dir)]) == 2
