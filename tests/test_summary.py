"""Flight summary: the paper's MSE on the pattern window, timing percentiles, JSON and table output."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.app.ui.summary import (
    FlightSummary,
    TickSeries,
    brief_rows,
    compute_summary,
    drone_row,
    render,
    render_brief,
    render_summary,
    summary_from_dict,
    summary_from_log,
    summary_to_json,
    tracking_error,
)

RATE = 400.0


def circle(t: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(t), np.sin(t), 1.0 + 0.0 * t], axis=1)


def flight(n: int = 4001, offset=(0.1, -0.2, 0.3), **kwargs) -> FlightSummary:
    t = np.arange(n) / RATE
    ref = circle(t)
    args = dict(
        t=t, p=ref + np.asarray(offset), p_ref=ref,
        compute_s=np.full(n, 4e-4), solve_s=np.full(n, 3e-4), missed=np.zeros(n, dtype=bool),
        window=(2.0, 8.0), wall_time=2.5, log_path="x.mcap",
    )
    args.update(kwargs)
    ticks = TickSeries(**{k: args.pop(k) for k in ("t", "p", "p_ref", "compute_s", "solve_s", "missed", "skipped")
                          if k in args})
    return compute_summary(ticks, **args)


def test_constant_offset_gives_known_mse() -> None:
    s = flight()
    assert (s.mse_x, s.mse_y, s.mse_z) == pytest.approx((0.01, 0.04, 0.09), rel=1e-12)
    assert s.mse == pytest.approx(0.14 / 3, rel=1e-12)
    assert s.rms_error == pytest.approx(math.sqrt(0.14), rel=1e-12)
    assert s.max_error == pytest.approx(math.sqrt(0.14), rel=1e-12)
    assert s.flight_mse == pytest.approx(0.14 / 3, rel=1e-12)
    assert s.window_samples == 6 * 400 + 1  # both ends included: 2.0 and 8.0 are tick times


def test_window_selects_the_pattern_samples() -> None:
    n = 4001
    t = np.arange(n) / RATE
    ref = circle(t)
    inside = (t >= 2.0) & (t <= 8.0)
    err = np.where(inside[:, None], [0.1, 0.0, 0.0], [1.0, 0.0, 0.0])  # take-off/landing much worse
    s = flight(p=ref + err)
    assert s.mse_x == pytest.approx(0.01) and s.mse_y == 0.0 and s.mse_z == 0.0
    assert s.mse == pytest.approx(0.01 / 3)
    assert s.max_error == pytest.approx(0.1)
    n_in = int(inside.sum())
    assert s.flight_mse == pytest.approx((n_in * 0.01 + (n - n_in) * 1.0) / n / 3)
    assert s.flight_max_error == pytest.approx(1.0)
    assert s.window == (2.0, 8.0)


def test_varying_error_matches_the_definition() -> None:
    rng = np.random.default_rng(4)
    p, p_ref = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    e = tracking_error(p, p_ref)
    expected = [np.mean((p[:, i] - p_ref[:, i]) ** 2) for i in range(3)]
    assert e.mse_xyz == pytest.approx(expected) and e.mse == pytest.approx(np.mean(expected))
    assert e.max == pytest.approx(np.max(np.linalg.norm(p - p_ref, axis=1)))
    assert e.rms == pytest.approx(np.sqrt(np.mean(np.sum((p - p_ref) ** 2, axis=1))))


def test_rows_without_a_state_are_skipped() -> None:
    n = 4001
    t = np.arange(n) / RATE
    p = circle(t) + [0.1, 0.0, 0.0]
    p[:100] = np.nan  # no estimate yet at the start
    s = flight(p=p, window=(0.0, 1.0))
    assert s.window_samples == 401 - 100
    assert s.mse == pytest.approx(0.01 / 3)


def test_empty_window_gives_nan_and_null() -> None:
    s = flight(window=(20.0, 30.0))
    assert s.window_samples == 0 and math.isnan(s.mse) and math.isnan(s.max_error)
    assert s.flight_mse == pytest.approx(0.14 / 3)
    assert json.loads(summary_to_json(s))["mse"] is None


def test_timing_percentiles() -> None:
    n = 101
    compute = np.linspace(0.0, 0.1, n)  # 0..100 ms: median 50, p99 99, max 100
    s = flight(n=n, compute_s=compute, solve_s=compute, missed=compute > 0.0955, window=(0.0, 1.0))
    assert s.compute_median_ms == pytest.approx(50.0)
    assert s.compute_p99_ms == pytest.approx(99.0)
    assert s.compute_max_ms == pytest.approx(100.0)
    assert s.solve_median_ms == pytest.approx(50.5)  # the 0 ms tick ran no solve
    assert s.missed_deadlines == 5 and s.ticks == 101  # 96..100 ms


def test_slots_passed_over_are_missed_deadlines_beside_the_late_ticks() -> None:
    n = 101
    missed, skipped = np.zeros(n, dtype=bool), np.zeros(n, dtype=int)
    missed[[10, 50]] = True
    skipped[[11, 51, 80]] = [1, 2, 1]  # after each late tick, and once after a tick on time whose bookkeeping ran over
    s = flight(n=n, missed=missed, skipped=skipped, window=(0.0, 1.0))
    assert (s.ticks, s.skipped_slots, s.missed_deadlines) == (101, 4, 6)
    assert flight(n=n, window=(0.0, 1.0)).skipped_slots == 0  # lockstep: no record of any
    assert "6 of 105 deadlines" in "\n".join(brief_rows(s))  # of the slots: the ticks and those passed over
    with pytest.raises(ValueError, match="skipped"):
        flight(n=n, skipped=np.zeros(n - 1, dtype=int))


def test_p99_is_linear_interpolation_of_order_statistics() -> None:
    rng = np.random.default_rng(7)
    compute = rng.lognormal(mean=-7.5, sigma=0.4, size=2345)
    s = flight(n=2345, compute_s=compute)
    x = np.sort(compute) * 1e3
    h = (len(x) - 1) * 0.99
    lo = int(math.floor(h))
    assert s.compute_p99_ms == pytest.approx(x[lo] + (h - lo) * (x[lo + 1] - x[lo]), rel=1e-12)
    assert s.compute_median_ms == pytest.approx(x[1172], rel=1e-12)  # odd count: the middle one


def test_solve_stats_ignore_ticks_without_a_solve() -> None:
    n = 1000
    solve = np.full(n, 2e-3)
    solve[::10] = np.nan  # fallback ticks
    s = flight(n=n, solve_s=solve)
    assert s.solve_median_ms == pytest.approx(2.0) and s.solve_p99_ms == pytest.approx(2.0)


def test_duration_wall_time_and_speed() -> None:
    s = flight()  # 4001 ticks at 400 Hz: 10 s
    assert s.duration_s == pytest.approx(10.0)
    assert s.wall_time_s == 2.5 and s.speed_factor == pytest.approx(4.0)
    assert flight(duration=12.5).speed_factor == pytest.approx(5.0)
    assert math.isnan(flight(wall_time=0.0).speed_factor)


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="same length"):
        flight(p_ref=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="missed"):
        flight(missed=np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="before its start"):
        flight(window=(5.0, 1.0))


def test_json_output_parses_and_round_trips() -> None:
    s = flight(extra={"controller": "mpc", "fallback_ticks": np.int64(3), "lockstep": True})
    text = summary_to_json(s)
    assert "\n" not in text
    d = json.loads(text)
    assert d["mse"] == pytest.approx(0.14 / 3) and d["window"] == [2.0, 8.0]
    assert d["missed_deadlines"] == 0 and d["log_path"] == "x.mcap"
    assert d["extra"] == {"controller": "mpc", "fallback_ticks": 3, "lockstep": True}
    back = summary_from_dict(d)
    assert back.to_dict() == s.to_dict()
    with pytest.raises(ValueError, match="unknown"):
        summary_from_dict({**d, "bogus": 1})


def test_render_summary_shows_the_numbers() -> None:
    console = Console(record=True, width=140, color_system=None)
    render_summary(flight(missed=np.arange(4001) % 1000 == 0, extra={"controller": "mpc"}), console)
    out = console.export_text()
    for text in ("Flight summary", "0.04667", "0.01 / 0.04 / 0.09", "5 / 4001", "0.400", "4", "x.mcap", "controller"):
        assert text in out, text


def test_brief_rows_carry_what_a_person_checks_within_80_columns() -> None:
    s = flight(missed=np.arange(4001) % 1000 == 0,
               extra={"lockstep": True, "adaptation": "dob", "adaptation_thrust_scale_end": 1.2987,
                      "models_accepted": 3, "models_trained": 5, "fallback_ticks": 7})
    rows = brief_rows(s)
    assert len(rows) <= 11 and all(len(row) <= 80 for row in rows)
    text = "\n".join(rows)
    for fragment in ("MSE 4.667e-02 m^2", "max error 374.2 mm", "median 0.400 ms, p99 0.400 ms",
                     "5 of 4001 deadlines", "x real time, lockstep", "3 accepted of 5 trained",
                     "1.299 x nominal (fast layer, dob)", "7 fallback ticks", "x.mcap"):
        assert fragment in text, fragment
    # Internals stay in --json and --verbose.
    assert "fallback_reasons" not in text and "MSE x / y / z" not in text


def test_brief_rows_name_the_learned_model_kept_beside_the_log() -> None:
    kept = flight(extra={"models_accepted": 2, "models_trained": 4,
                         "learned_model": "/flights/20261206-080340-circle.learned.safetensors"})
    rows = brief_rows(kept)
    assert "  learned model  kept as 20261206-080340-circle.learned.safetensors" in rows
    assert all(len(row) <= 80 for row in rows)
    lost = brief_rows(flight(extra={"learned_model_error": "the learned model was not written: disk full"}))
    assert any("attention" in row and "the learned model was not kept" in row for row in lost)


def test_brief_rows_leave_out_what_a_flight_did_not_have() -> None:
    rows = brief_rows(flight())
    assert [row.split()[0] for row in rows[1:]] == ["tracking", "tick", "missed", "speed", "log"]


def test_brief_rows_fit_every_mass_step_in_one_row() -> None:
    steps = [(float(t), 1.3) for t in (3.0, 4.0, 5.0, 6.0)]
    rows = brief_rows(flight(steps=steps))
    (row,) = [row for row in rows if "mass steps" in row]
    assert len(row) <= 80 and "(+2 more)" in row


def test_render_brief_prints_the_rows_as_lines() -> None:
    console = Console(record=True, width=80, color_system=None)
    s = flight()
    render_brief(s, console)
    assert console.export_text().splitlines() == brief_rows(s)


def test_verbose_prints_every_row_and_the_default_the_brief_ones() -> None:
    s = flight(extra={"adaptation_resets": 2, "fallback_reasons": {}})
    brief, full = Console(record=True, width=80, color_system=None), Console(record=True, width=160, color_system=None)
    render(s, brief)
    render(s, full, verbose=True)
    assert brief.export_text().splitlines() == brief_rows(s)
    every = full.export_text()
    for text in ("MSE x / y / z", "whole flight", "MPC solve median / p99", "adaptation_resets", "fallback_reasons"):
        assert text in every, text


def test_a_fleet_drone_is_one_row() -> None:
    row = drone_row("cf1", flight(extra={"models_accepted": 2}), "flight complete: landed")
    assert row == "cf1: MSE 4.67e-02 m^2, tick 0.40/0.40 ms, 2 models, flight complete: landed"
    wake = drone_row("cf1", flight(extra={"models_accepted": 2, "online_wake_only": True}), "flight complete: landed")
    assert wake == "cf1: MSE 4.67e-02 m^2, tick 0.40/0.40 ms, 2 wake models, flight complete: landed"


def test_summary_from_log_matches_the_arrays(tmp_path: Path) -> None:
    n = 1601
    t = np.arange(n) / RATE
    ref = circle(t)
    p_true = ref + [0.05, 0.0, -0.02]
    est = ref + [0.5, 0.5, 0.5]
    compute = np.linspace(1e-4, 9e-4, n)
    missed = np.arange(n) % 400 == 0
    expected = compute_summary(TickSeries(t, p_true, ref, compute, compute / 2, missed), (1.0, 3.0), 0.8)
    with FlightLog.create(tmp_path, {"a": 1}, "v", "s") as log:
        for k in range(n):
            log.write("/state", t[k], {"p": est[k], "v": np.zeros(3), "q": [1.0, 0, 0, 0], "p_true": p_true[k]})
            log.write("/reference", t[k], {"p": ref[k], "v": np.zeros(3), "a": np.zeros(3), "yaw": 0.0})
            log.write("/tick", t[k], {"compute_s": compute[k], "solve_s": compute[k] / 2, "missed": missed[k],
                                      "mpc_ok": True})
        log.write("/summary", t[-1], expected.to_dict())
    got = summary_from_log(read_log(log.path))
    for name in ("mse_x", "mse_y", "mse_z", "mse", "flight_mse", "max_error", "compute_p99_ms", "solve_median_ms",
                 "missed_deadlines", "ticks", "duration_s", "wall_time_s", "window"):
        assert getattr(got, name) == pytest.approx(getattr(expected, name)), name
    from_estimate = summary_from_log(read_log(log.path), window=(0.0, 4.0), use_true=False)
    assert from_estimate.mse == pytest.approx(0.25) and from_estimate.window == (0.0, 4.0)
    assert summary_from_dict(read_log(log.path).topic("/summary")[0]).mse == pytest.approx(expected.mse)
