"""FlightStatus: per-tick records, lazy statistics, the log tap and the pollers."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.app.ui.status import (
    FlightStatus,
    StatusTap,
    battery_poller,
    mocap_poller,
    radio_poller,
)


def _tick(t, compute_s=2e-4, solve_s=1e-4, missed=False, source="mpc", p=(0.0, 0.0, 1.0), ref=(0.0, 0.0, 1.0),
          skipped=0):
    est = None if p is None else SimpleNamespace(p=np.asarray(p, dtype=float))
    return SimpleNamespace(t=t, est=est, ref_p=np.asarray(ref, dtype=float), compute_s=compute_s, solve_s=solve_s,
                           missed=missed, source=source, model_version=0, skipped=skipped)


class RecordingLog:
    def __init__(self):
        self.written = []
        self.path = "flight.mcap"

    def write(self, topic, t, msg):
        self.written.append((topic, t, msg))


def test_statistics_cover_the_newest_window_only():
    status = FlightStatus(nominal_rate_hz=400.0, window=100)
    compute = np.linspace(1e-4, 5e-4, 250)
    for k, c in enumerate(compute):
        # 400 Hz on the flight clock, 2000 ticks per wall second: 5x real time.
        status.record_tick(k / 400, 10.0 + k / 2000, c, c / 2, False, "mpc", (0, 0, 0), (0, 0, 0))
    stats = status.tick_stats(wall_now=10.0 + 249 / 2000 + 0.25)
    newest_ms = compute[-100:] * 1e3
    assert stats.window == 100
    assert stats.compute_median_ms == pytest.approx(np.percentile(newest_ms, 50))
    assert stats.compute_p99_ms == pytest.approx(np.percentile(newest_ms, 99))
    assert stats.solve_p99_ms == pytest.approx(np.percentile(newest_ms / 2, 99))
    assert stats.loop_rate_hz == pytest.approx(400.0)
    assert stats.wall_rate_hz == pytest.approx(2000.0)
    assert stats.speed_factor == pytest.approx(5.0)
    assert stats.since_last_tick_s == pytest.approx(0.25)


def test_no_ticks_gives_nan_statistics():
    stats = FlightStatus().tick_stats(wall_now=1.0)
    assert stats.window == 0
    assert all(math.isnan(v) for v in (stats.compute_p99_ms, stats.loop_rate_hz, stats.speed_factor))


def test_solve_statistics_skip_ticks_without_a_solve():
    status = FlightStatus(window=10)
    for k in range(10):
        status.record_tick(k / 400, k / 400, 1e-3, 2e-3 if k % 2 else 0.0, False, "mpc", (0, 0, 0), (0, 0, 0))
    assert status.tick_stats(1.0).solve_median_ms == pytest.approx(2.0)


def test_on_tick_counts_missed_and_fallback_ticks_and_keeps_the_newest_state():
    status = FlightStatus()
    status.on_tick(_tick(0.0, p=None, source="no_state"))
    assert np.all(np.isnan(status.error()))
    status.on_tick(_tick(0.0025, missed=True, source="fallback", p=(0.1, 0.2, 1.0), ref=(0.1, 0.25, 1.0)))
    status.on_tick(_tick(0.0050, source="fallback", p=(0.1, 0.2, 1.0), ref=(0.1, 0.21, 0.9)))
    assert (status.ticks, status.missed_deadlines, status.fallbacks) == (3, 1, 2)
    assert status.t == 0.0050 and status.command_source == "fallback"
    np.testing.assert_allclose(status.error(), [0.0, -0.01, 0.1])


def test_slots_passed_over_count_as_missed_deadlines():
    status = FlightStatus()
    status.on_tick(_tick(0.0025))
    status.on_tick(_tick(0.0100, skipped=2))  # two slots had no tick at all
    status.on_tick(_tick(0.0125, missed=True))
    assert (status.ticks, status.missed_deadlines) == (3, 3)


def test_tap_passes_messages_through_and_reads_supervisor_and_model_channels():
    log = RecordingLog()
    status = FlightStatus()
    tap = StatusTap(log, status)
    tap.write("/tick", 0.1, {"compute_s": 1e-4})
    tap.write("/safety", 0.2, {"state": "TRACK", "fence_margin_m": 0.42, "battery_v": None})
    tap.write("/events", 0.3, {"level": "warning", "text": "TRACK -> LAND: mocap lost", "source": "supervisor",
                               "state": "LAND"})
    tap.write("/model", 1.0, {"version": 1, "event": "swap", "val_error": 0.03, "queue": [1]})
    tap.write("/model", 2.0, {"version": 2, "event": "swap", "val_error": 0.02, "queue": [1, 2]})
    tap.write("/model", 2.5, {"version": 3, "event": "reject", "reason": "validation error worse"})
    tap.write("/model", 3.0, {"version": 1, "event": "rollback", "reason": "solver failed", "queue": [1]})
    assert [w[0] for w in log.written] == ["/tick", "/safety", "/events", "/model", "/model", "/model", "/model"]
    assert tap.path == "flight.mcap"  # a stand-in for the log it wraps
    assert status.supervisor_state == "LAND"
    assert status.geofence_margin_m == 0.42 and math.isnan(status.battery_v)
    assert (status.model_swaps, status.model_rejects, status.model_rollbacks) == (2, 1, 1)
    assert (status.windows_accepted, status.windows_rejected) == (2, 1)
    assert [(m.version, m.created_t, m.weight, m.val_error) for m in status.models] == [(1, 1.0, 1.0, 0.03)]
    texts = [e.text for e in status.events]
    assert texts == ["TRACK -> LAND: mocap lost", "model 3 reject: validation error worse",
                     "model 1 rollback: solver failed"]


def test_tap_queue_weights_are_the_forgetting_weights():
    status = FlightStatus()
    tap = StatusTap(RecordingLog(), status)
    for v in (1, 2, 3):
        tap.write("/model", float(v), {"version": v, "event": "swap", "queue": list(range(1, v + 1))})
    assert [m.version for m in status.models] == [1, 2, 3]
    np.testing.assert_allclose([m.weight for m in status.models], np.exp([-2.0, -1.0, 0.0]))


def test_tap_reads_the_trainer_from_training_rounds_and_process_events():
    status = FlightStatus()
    tap = StatusTap(RecordingLog(), status)
    tap.write("/training", 1.0, {"round": 1, "version": 1, "window": [0.5, 0.65], "ok": True, "loss": 0.004})
    assert status.trainer_state == "running" and status.trainer_last_loss == 0.004
    tap.write("/training", 1.2, {"round": 2, "version": 2, "window": [0.65, 0.8], "ok": False, "error": "no data"})
    assert status.windows_rejected == 1 and status.trainer_last_loss == 0.004
    tap.write("/model", 1.3, {"version": 1, "event": "crash", "reason": "exit code 70"})
    assert status.trainer_state == "crashed" and status.events[-1].text == "model 1 crash: exit code 70"
    tap.write("/model", 1.4, {"version": 1, "event": "restart"})
    assert status.trainer_state == "restarting"


def test_tap_over_a_real_flight_log_keeps_the_log_complete(tmp_path):
    status = FlightStatus()
    with FlightLog.create(tmp_path, {"a": 1}, "test") as log:
        tap = StatusTap(log, status)
        tap.write("/safety", 0.5, {"state": "TAKEOFF", "fence_margin_m": 1.0})
        tap.write("/events", 0.6, {"level": "info", "text": "hello"})
    data = read_log(log.path)
    assert data.topic("/safety")[0]["state"] == "TAKEOFF" and data.topic("/events")[0]["text"] == "hello"
    assert status.supervisor_state == "TAKEOFF"


def test_pollers_copy_sources_and_a_failing_one_is_reported_not_raised():
    status = FlightStatus()
    mocap = SimpleNamespace(stats=lambda: SimpleNamespace(frames=120, dropouts=3, rate_hz=99.5))
    plain_radio = SimpleNamespace(stats=lambda: SimpleNamespace(setpoints_sent=50, send_errors=1, link_lost=None))
    status.add_poller(mocap_poller(mocap))
    status.add_poller(radio_poller(plain_radio))
    status.add_poller(battery_poller(lambda: 3.91))
    status.poll()
    assert (status.mocap_frames, status.mocap_dropouts, status.mocap_rate_hz) == (120, 3, 99.5)
    assert (status.setpoints_sent, status.radio_errors) == (50, 1)
    assert math.isnan(status.radio_latency_ms) and math.isnan(status.radio_ack_rate)
    assert status.battery_v == 3.91 and status.poll_error is None

    rich_radio = SimpleNamespace(stats=lambda: SimpleNamespace(setpoints_sent=7, send_errors=0, link_lost="gone",
                                                               latency_ms=4.5, ack_rate=0.98))
    status.add_poller(radio_poller(rich_radio))

    def broken(_status):
        raise RuntimeError("no telemetry")

    status.add_poller(broken)
    status.poll()
    assert (status.radio_latency_ms, status.radio_ack_rate, status.link_lost) == (4.5, 0.98, "gone")
    assert status.poll_error == "broken: RuntimeError: no telemetry"
