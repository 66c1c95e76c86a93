"""`cfknode bench paper --mode hierarchical --quick` keeps working: one cell, every controller, the real stack.

The command runs as a user runs it, on a shorter flight than ``--quick``'s own: 2.5 s of pattern (the mass
steps at 0.6 s and 1.6 s into it, still several online rounds after each), a 1.5 s take-off, a 0.5 s settle and
a 1.5 s landing, where the bench's own are 4 s of pattern, 3 s, 1 s and 3 s; its offline model trains 50 epochs
instead of 400. The test checks what the bench wires together, not its numbers (docs/results.md has those).
"""

import json

import pytest

from cfknode.app.bench import hierarchical
from cfknode.app.bench.hierarchical import CONTROLLERS, CellResult, markdown
from cfknode.app.cli import main

SHORT = {"trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5, "trajectory.land_duration": 1.5,
         "training.epochs": 50}

pytest.importorskip("torch")


def test_markdown_marks_the_lowest_and_counts_wins():
    r = CellResult(2.0, 0.8, {"nominal": 0.03, "offline": 0.05, "geometric": 0.02, "online": 0.01},
                   {k: 0.0 for k in CONTROLLERS}, {k: "" for k in CONTROLLERS}, {}, 1.0)
    md = markdown([r], "cmd", "0")
    assert "**0.0100**" in md and "| online |" in md and "lowest MSE in 1 of 1 cells" in md
    assert "0.0660" in md  # the paper's published Online value for r=2, v=0.8


def test_quick_hierarchical_bench_runs_the_whole_stack(tmp_path, monkeypatch):
    cell_overrides = hierarchical.cell_overrides
    monkeypatch.setattr(hierarchical, "QUICK_DURATION_S", 2.5)
    monkeypatch.setattr(hierarchical, "cell_overrides", lambda *a: {**cell_overrides(*a), **SHORT})
    assert main(["bench", "paper", "--mode", "hierarchical", "--quick", "--jobs", "1", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "paper_hierarchical_quick.json").read_text())
    (cell,) = data["cells"]
    assert set(cell["mse"]) == set(CONTROLLERS)
    assert all(0.0 <= v < 1.0 for v in cell["mse"].values())
    assert all(o.startswith("flight complete") for o in cell["outcome"].values()), cell["outcome"]
    assert cell["online"]["models_trained"] >= 1
