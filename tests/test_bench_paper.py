"""``cfknode bench paper --quick``: the whole benchmark path (parallel workers, both formulations,
every controller, markdown, JSON and the plot) on one short cell."""

from __future__ import annotations

import json
import math

import pytest

from cfknode.app.cli import main


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "paper", "--mode", "full", "--quick", "--jobs", "2", "--out", str(out)]) == 0
    return out


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
    assert data["plan"]["duration_s"] == 3.5 and data["jobs"] == 2
    runs = {(r["formulation"], r["controller"]): r for r in data["runs"]}
    assert set(runs) == {(f, c) for f in ("paper", "default") for c in ("mpc", "knode_offline", "geometric", "knode_online", "oracle")}
    for r in runs.values():
        assert math.isfinite(r["mse"]) and r["mse"] > 0 and r["failed_solves"] == 0
        assert r["mse"] == pytest.approx(sum(r["mse_per_axis"]) / 3, rel=1e-9)
    # The paper's loop trains after every window from the first event on; cfknode's gates its swaps.
    paper_rounds = runs[("paper", "knode_online")]["rounds"]
    assert len(paper_rounds) >= 10 and all(r["accepted"] for r in paper_rounds)
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
