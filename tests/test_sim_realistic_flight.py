"""A short closed-loop flight on the realistic plant (``sim.aero: realistic``): the default MPC and
fast layer take off through the ground effect, fly a fast circle in rotor drag, inflow and the
fast force, and land, inside the fence and without a fallback."""

from __future__ import annotations

import numpy as np

from cfknode.app.config import load_config
from cfknode.app.mission import run_flight

SHORT = {"sim.aero": "realistic", "trajectory.speed": 1.0, "trajectory.duration": 3.0,
         "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.3, "trajectory.land_duration": 1.5,
         "trajectory.ramp_duration": 0.5}


def test_a_realistic_fast_circle_stays_up_inside_the_fence_and_lands(tmp_path):
    result = run_flight(load_config(overrides={**SHORT, "log.dir": str(tmp_path)}), name_hint="realistic")
    s = result.summary
    assert result.outcome.message == "flight complete: landed"
    assert s.extra["fence_excursion_m"] == 0.0 and s.extra["fallback_ticks"] == 0
    assert s.window_samples > 1000
    # A 1 m/s circle entered in 0.5 s: the ideal plant's error is as large (about 0.1 m at the entry).
    assert s.max_error < 0.15, s.max_error
    assert s.mse < 5e-3, s.mse
    # On the pattern (after take-off and settle, before landing) it stays near its 1 m height.
    t, z = result.record.t, result.record.p[:, 2]
    on_pattern = (t > 2.0) & (t < 4.5)
    assert np.all(np.abs(z[on_pattern] - 1.0) < 0.05)
