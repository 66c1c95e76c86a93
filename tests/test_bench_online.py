"""The online-learning acceptance protocol on the paper's cell, flown by the whole stack,
and `cfknode bench online`'s report."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cfknode.app.bench.online import PAPER, CellReport, Run, markdown, run_cell
from cfknode.app.cli import main

pytest.importorskip("torch")


def report(mse: dict[str, list[float]]) -> CellReport:
    runs = tuple(Run(c, seed, m, m, "flight complete: landed", {"models_dropped": 1} if c == "online" else {})
                 for c, values in mse.items() for seed, m in enumerate(values))
    return CellReport(PAPER, runs, 1.0)


def test_the_report_takes_medians_and_ratios_seed_by_seed() -> None:
    rep = report({"nominal": [0.06, 0.07, 0.08], "offline": [0.2, 0.2, 0.2], "online": [0.03, 0.09, 0.04]})
    assert rep.met  # median 0.04 below 0.07 and 0.2
    np.testing.assert_allclose(rep.ratios("nominal"), [0.5, 0.09 / 0.07, 0.5])
    md = markdown([rep], "cmd", "0")
    assert "0.07 [0.06, 0.08]" in md and "(wins 2/3)" in md and "| yes |" in md
    assert not report({"nominal": [0.06], "offline": [0.2], "online": [0.07]}).met


def test_bad_seed_count_is_a_usage_error(capsys) -> None:
    assert main(["bench", "online", "--seeds", "0"]) == 2
    assert "--seeds must be >= 1" in capsys.readouterr().err


def test_online_beats_nominal_and_offline_on_the_paper_cell(tmp_path) -> None:
    # r = 2 m, 0.8 m/s, 8 s; mass 0.5x at 2 s and 1.33x at 5 s; offline trained on the first change only.
    # The three controllers compared here, not the cell's references: each flight is seeded on its own,
    # so they fly as they do beside the others.
    rep = run_cell(replace(PAPER, controllers=("nominal", "offline", "online")), (0,), tmp_path)
    mse = {r.controller: r.mse for r in rep.runs}
    assert set(mse) == {"nominal", "offline", "online"}
    assert all(r.outcome == "flight complete: landed" for r in rep.runs), [r.outcome for r in rep.runs]
    assert mse["online"] < mse["nominal"] and mse["online"] < mse["offline"], mse
    online = next(r for r in rep.runs if r.controller == "online").online
    assert online["models_dropped"] >= 1  # the half-mass model is dropped after the 1.33x step
    assert online["models_accepted"] >= 5
    out = json.loads(json.dumps(online))  # the bench's JSON holds these fields as they are
    assert out["swap_max_ms"] is not None and out["train_wall_median_s"] is not None
