"""`cfknode bench paper --mode hierarchical --quick` keeps working: one cell, four controllers, the real stack."""

import json

import pytest

from cfknode.app.bench.hierarchical import CONTROLLERS, CellResult, markdown
from cfknode.app.cli import main

pytest.importorskip("torch")


def test_markdown_marks_the_lowest_and_counts_wins():
    r = CellResult(2.0, 0.8, {"nominal": 0.03, "offline": 0.05, "geometric": 0.02, "online": 0.01},
                   {k: 0.0 for k in CONTROLLERS}, {k: "" for k in CONTROLLERS}, {}, 1.0)
    md = markdown([r], "cmd", "0")
    assert "**0.0100**" in md and "| online |" in md and "lowest MSE in 1 of 1 cells" in md
    assert "0.0660" in md  # the paper's published Online value for r=2, v=0.8


def test_quick_hierarchical_bench_runs_the_whole_stack(tmp_path):
    assert main(["bench", "paper", "--mode", "hierarchical", "--quick", "--jobs", "1", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "paper_hierarchical_quick.json").read_text())
    (cell,) = data["cells"]
    assert set(cell["mse"]) == set(CONTROLLERS)
    assert all(0.0 <= v < 1.0 for v in cell["mse"].values())
    assert all(o.startswith("flight complete") for o in cell["outcome"].values()), cell["outcome"]
    assert cell["online"]["models_trained"] >= 1
