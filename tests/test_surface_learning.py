"""Where physics lets a model win: a transit 6 cm over the floor, in ground effect, below the fast layer's floor
margin (where it holds and measures nothing). A model learned in flight beside the layer owns the vertical there
and flies the cell with a far lower error than the layer alone; seed 0, 4 s of the bench's own cell."""

from __future__ import annotations

from cfknode.app.bench.learning import Job, run_job
from cfknode.app.bench.learning_cells import CELLS

CELL = next(c for c in CELLS if c.name == "surface h=6 cm v=0.5")


def test_online_learning_beside_the_layer_learns_the_ground_effect_the_held_layer_cannot(tmp_path):
    layer = run_job(Job(CELL, "layer", 0, str(tmp_path), 4.0))
    online = run_job(Job(CELL, "online+layer", 0, str(tmp_path), 4.0))
    for run in (layer, online):
        assert run.outcome.startswith("flight complete") and not run.fell and not run.tripped, run.outcome
    assert online.models_accepted >= 1
    # The layer holds near the floor: its height error is the ground effect it does not see.
    assert online.mse_z < 0.6 * layer.mse_z, (online.mse_z, layer.mse_z)
    assert online.mse < 0.75 * layer.mse, (online.mse, layer.mse)  # 25 % lower at least
