"""The timing bench's parts measure what they claim (values are not asserted: numbers go in notes)."""

import dataclasses
import math

import numpy as np
import pytest

from cfknode.app.bench.timing import (
    Timing, layer_tick, lockstep_flight, mpc_closed_loop, over_nominal, swap_latency, synthetic_queue,
)
from cfknode.app.config import load_config
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc


def test_timing_statistics():
    t = Timing.of("x", np.linspace(0.001, 0.002, 101))
    assert t.median_ms == 1.5 and t.max_ms == 2.0 and 1.98 < t.p99_ms < 2.0 and t.samples == 101


def test_closed_loop_rows_for_nominal_and_knode():
    cfg = load_config()
    ctrl = dataclasses.replace(cfg.controller, codegen=False)
    mpc = TranslationalMpc(ctrl, cfg.vehicle)
    solve, total, after = mpc_closed_loop(cfg, mpc, None, seconds=0.1)
    assert solve.samples == 40 and solve.name == "MPC solve, rti-qrqp-vm"
    assert after.samples == 40 and after.name == "after the send, rti-qrqp-vm"
    slot = ModelSlot(synthetic_queue(cfg.knode.hidden, 3), version=1)
    solve_k, total_k, after_k = mpc_closed_loop(cfg, mpc, slot, seconds=0.1)
    assert "KNODE x3" in solve_k.name and "KNODE x3" in after_k.name
    # The step holds the solve; linearising the queue has a row of its own, after the send, as in flight.
    assert total_k.median_ms >= solve_k.median_ms and after_k.samples == 40


def test_swap_rows():
    row = swap_latency(load_config(), repeats=50)
    assert row.samples == 50 and np.isfinite(row.max_ms)


def test_the_fast_layer_has_its_own_row_timing_every_call_of_a_tick():
    cfg = load_config()
    mpc = TranslationalMpc(dataclasses.replace(cfg.controller, codegen=False), cfg.vehicle)
    row = layer_tick(cfg, mpc, seconds=0.1)
    assert row.samples == 40 and row.name.startswith("fast layer")
    assert 0.0 < row.median_ms <= row.max_ms


def test_a_lockstep_flight_splits_its_ticks_by_the_accelerometer_s_samples():
    """The budget over plain MPC is read by kind of tick: the log's 100 Hz samples fall on one tick in four."""
    f = lockstep_flight(load_config(), None, 1.0, "dob")
    assert all(math.isfinite(f[k]) and f[k] > 0.0 for k in ("sample_tick_median_ms", "other_tick_median_ms"))
    assert 0.2 < f["sample_ticks"] / (f["sample_ticks"] + f["other_ticks"]) < 0.3


def test_each_flight_is_stated_over_the_nominal_one_in_ms_by_kind_of_tick():
    keys = ("tick_median_ms", "sample_tick_median_ms", "other_tick_median_ms")
    flights = {"nominal": dict(zip(keys, (0.35, 0.38, 0.33))), "layer": dict(zip(keys, (0.42, 0.45, 0.40)))}
    over = over_nominal(flights)
    assert set(over) == {"layer"}
    assert over["layer"] == pytest.approx(dict(zip(keys, (0.07, 0.07, 0.07))))
