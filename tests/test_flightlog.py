"""Flight log: MCAP round trip of every channel, truncation tolerance, crash safety, naming."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.logs.writer import (
    CHANNELS,
    Chunks,
    FlightLog,
    LogError,
    channels_markdown,
    check_message,
    read_log,
)

CONFIG = {"backend": "sim", "vehicle": {"mass": 0.029, "inertia": [1.66e-5, 1.67e-5, 2.93e-5]}, "log": {"dir": "x"}}
VERSION = "9.8.7-test"
STARTED = datetime(2025, 3, 4, 5, 6, 7)

# One representative message per channel, as the flight loop writes them (numpy included).
SAMPLES: dict[str, dict] = {
    "/config": {"software_version": "other", "config": {"a": 1}},
    "/state": {"p": np.array([0.1, -0.2, 1.0]), "v": np.array([0.5, 0.0, -0.1]), "q": np.array([1.0, 0.0, 0.0, 0.0]),
               "p_true": np.array([0.11, -0.19, 1.01]), "v_true": np.array([0.49, 0.01, -0.1])},
    "/reference": {"p": np.array([0.0, 0.0, 1.0]), "v": np.zeros(3), "a": np.array([0.0, 0.0, 0.0]),
                   "yaw": np.float64(0.3)},
    "/command": {"acc": np.array([0.2, -0.1, 0.05]), "roll_deg": 1.5, "pitch_deg": np.float32(-2.0),
                 "yawrate_deg": 0.0, "thrust": np.uint16(41000), "source": "mpc"},
    "/tick": {"compute_s": 0.00041, "solve_s": 0.00032, "missed": np.bool_(False), "mpc_ok": True, "status": "ok"},
    "/mocap": {"p": np.array([0.1, -0.2, 1.0]), "q": np.array([0.9998, 0.0, 0.0, 0.02]), "received": True,
               "stamp": 1.2475},
    "/events": {"level": "warning", "text": "mocap frame late by 12 ms", "source": "mocap"},
    "/safety": {"state": "TRACK", "reason": "", "pose_age_s": 0.012, "fence_margin_m": 0.9, "tracking_error_m": 0.004,
                "battery_v": 3.82, "link_silence_s": 0.0, "fallback_ticks": 0},
    "/adaptation": {"offset": np.array([0.1, -0.2, 0.3]), "thrust_scale": 1.3, "axis_gain": np.array([1.0, 1.0]),
                    "frozen": False, "saturated": True, "f_max": 11.4, "mode": "dob"},
    "/model": {"version": np.int64(3), "event": "swap", "val_error": 0.021, "swap_ms": 0.31, "queue": [1, 2, 3],
               "round": 3, "window": [6.1, 6.6], "val_error_current": 0.034, "val_error_nominal": 0.05,
               "max_residual": 4.2, "val_pairs": 44, "train_wall_s": 0.11, "latency_s": 0.12, "install_ms": 0.6,
               "slice_ms": 0.2, "control_gain": [0.7, 1.1], "velocity_gain": -0.2},
    "/training": {"round": 3, "version": 3, "window": [6.1, 6.6], "ok": True, "base_version": 2, "pairs": 200,
                  "loss": 1.7, "val_rmse_model": 0.012, "val_rmse_nominal": 0.031,
                  "max_abs_residual": 4.2, "train_wall_s": 0.11, "train_cpu_s": 0.1, "latency_s": 0.12, "t_col": 0.5,
                  "error": ""},
    "/summary": {"mse": 0.0012, "window": [2.0, 10.0], "log_path": None},
}


def plain(msg: dict) -> dict:
    """What a sample looks like after JSON: numpy becomes lists and Python scalars."""
    return json.loads(json.dumps(msg, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else o.item()))


def make_log(tmp_path: Path, **kwargs) -> FlightLog:
    return FlightLog.create(tmp_path, CONFIG, VERSION, "test", started=STARTED, **kwargs)


def test_every_registered_channel_has_a_sample() -> None:
    assert {c.topic for c in CHANNELS} == set(SAMPLES)


def test_round_trip_of_every_channel(tmp_path: Path) -> None:
    with make_log(tmp_path) as log:
        for i, topic in enumerate(SAMPLES):
            log.write(topic, 1.0 + 0.0025 * i, SAMPLES[topic])
    data = read_log(log.path)
    assert not data.truncated and data.note == ""
    assert data.config == CONFIG
    assert data.software_version == VERSION
    assert data.metadata["cfknode"]["started"] == "2025-03-04T05:06:07"
    for i, topic in enumerate(SAMPLES):
        msgs = data.topic(topic)
        if topic == "/config":  # the first one is written by create()
            assert msgs[0] == {"t": 0.0, "software_version": VERSION, "config": CONFIG}
            msgs = msgs[1:]
        assert msgs == [{"t": 1.0 + 0.0025 * i, **plain(SAMPLES[topic])}]
        assert check_message(topic, msgs[0]) == []
        schema = data.schemas[topic]
        assert schema["type"] == "object" and "t" in schema["required"]
        assert set(schema["required"]) <= set(schema["properties"])


def test_check_message_finds_problems() -> None:
    bad = {"t": 0.0, "p": [1.0, 2.0], "v": [0, 0, 0], "q": [1, 0, 0, "x"]}
    problems = check_message("/state", bad)
    assert any("'p'" in p for p in problems) and any("'q'" in p for p in problems)
    assert check_message("/nope", {}) == ["unknown topic '/nope'"]


def test_log_time_is_flight_time_in_ns(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    with make_log(tmp_path) as log:
        log.write("/tick", 2.0025, SAMPLES["/tick"])
    with open(log.path, "rb") as f:  # the stock reader also reads our file, summary and all
        reader = make_reader(f)
        times = [m.log_time for _, c, m in reader.iter_messages(topics=["/tick"])]
        assert {c.topic for c in reader.get_summary().channels.values()} == set(SAMPLES)
    assert times == [2_002_500_000]


def test_numpy_and_non_finite_values(tmp_path: Path) -> None:
    with make_log(tmp_path) as log:
        log.write("/command", 0.5, {**SAMPLES["/command"], "acc": np.array([np.nan, 1.0, np.inf])})
        log.write("/events", 0.6, {"level": "error", "text": "NaN in the MPC solution"})
    data = read_log(log.path)
    assert data.topic("/command")[0]["acc"] == [None, 1.0, None]
    assert data.topic("/events")[0]["text"] == "NaN in the MPC solution"
    acc = data.array("/command", "acc")
    assert acc.shape == (1, 3) and np.isnan(acc[0, 0]) and acc[0, 1] == 1.0


def test_write_rejects_bad_input(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    with pytest.raises(ValueError, match="unknown flight-log topic '/nope'"):
        log.write("/nope", 0.0, {})
    with pytest.raises(ValueError, match="must not contain 't'"):
        log.write("/tick", 0.0, {"t": 1.0})
    with pytest.raises(ValueError, match=">= 0"):
        log.write("/tick", -0.1, SAMPLES["/tick"])
    with pytest.raises(ValueError, match=">= 0"):
        log.write("/tick", float("nan"), SAMPLES["/tick"])
    with pytest.raises(TypeError, match="object"):
        log.write("/events", 0.0, {"level": "info", "text": object()})
    log.close()
    log.close()  # idempotent
    assert log.closed
    with pytest.raises(ValueError, match="closed"):
        log.write("/tick", 1.0, SAMPLES["/tick"])
    assert not read_log(log.path).truncated


def test_unique_file_names_never_overwrite(tmp_path: Path) -> None:
    directory = tmp_path / "a" / "b"  # created on demand
    directory.mkdir(parents=True)
    taken = directory / "20250304-050607-circle_r_2.mcap"
    taken.write_bytes(b"keep me")
    paths = []
    for _ in range(3):
        with FlightLog.create(directory, CONFIG, VERSION, "circle r=2/", started=STARTED) as log:
            paths.append(log.path)
    assert [p.name for p in paths] == [f"20250304-050607-circle_r_2-{k}.mcap" for k in (1, 2, 3)]
    assert taken.read_bytes() == b"keep me"
    assert all(not read_log(p).truncated for p in paths)


def test_directory_is_created_and_default_name(tmp_path: Path) -> None:
    with FlightLog.create(tmp_path / "new" / "dir", CONFIG, VERSION, "") as log:
        pass
    assert log.path.parent == tmp_path / "new" / "dir"
    assert log.path.name.endswith("-flight.mcap")
    datetime.strptime(log.path.name[:15], "%Y%m%d-%H%M%S")


def _write_flight(log: FlightLog, ticks: int) -> None:
    for k in range(ticks):
        t = k / 400
        log.write("/state", t, SAMPLES["/state"])
        log.write("/tick", t, SAMPLES["/tick"])
        if k % 100 == 0:
            log.write("/events", t, {"level": "info", "text": f"tick {k}"})
            log.flush()


def test_truncated_file_reads_up_to_where_it_ends(tmp_path: Path) -> None:
    with make_log(tmp_path, chunks=Chunks(4096)) as log:
        _write_flight(log, 600)
    full = read_log(log.path)
    raw = log.path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    seen_counts = set()
    for cut in [9, 20, 100, *np.linspace(200, len(raw) - 1, 60).astype(int)]:
        cut_path.write_bytes(raw[:cut])
        part = read_log(cut_path)  # never raises
        assert part.truncated and part.note
        for topic, msgs in part.messages.items():
            assert msgs == full.topic(topic)[: len(msgs)]  # a prefix of the real thing
        if cut > 2000:
            assert part.config == CONFIG and part.software_version == VERSION
        seen_counts.add(len(part.topic("/state")))
    assert len(seen_counts) > 10  # cuts really landed at many depths
    assert full.array("/state", "p").shape == (600, 3)


def test_reading_a_file_that_is_still_open(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    _write_flight(log, 201)  # ends with a flush after tick 200
    data = read_log(log.path)
    assert data.truncated
    assert len(data.topic("/state")) == 201 and data.config == CONFIG
    log.write("/events", 0.6, {"level": "critical", "text": "e-stop"})  # events reach disk at once
    assert read_log(log.path).topic("/events")[-1]["text"] == "e-stop"
    log.close()
    assert not read_log(log.path).truncated


def test_idle_log_is_flushed_by_the_background_thread(tmp_path: Path) -> None:
    log = make_log(tmp_path, flush_interval=0.05)
    log.write("/tick", 0.0, SAMPLES["/tick"])  # not a flush channel, and no further writes
    deadline = time.monotonic() + 10.0
    while not read_log(log.path).topic("/tick") and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(read_log(log.path).topic("/tick")) == 1
    log.close()


def test_a_crash_loses_at_most_the_last_second(tmp_path: Path) -> None:
    # A child writes 400 Hz ticks stamped with its wall clock, then dies without closing.
    script = textwrap.dedent(f"""
        import os, sys, time
        from datetime import datetime
        from cfknode.app.logs.writer import FlightLog
        log = FlightLog.create({str(tmp_path)!r}, {{"a": 1}}, "v", "crash")
        start = time.time(); k = 0
        while time.time() - start < 1.6:  # flight time is wall time, as in a real-time flight
            log.write("/tick", time.time() - start, {{"compute_s": 0.0, "solve_s": 0.0, "missed": False,
                                                     "mpc_ok": True, "status": repr(time.time())}})
            k += 1
            time.sleep(0.0005)
        print(repr(time.time()), flush=True)
        os._exit(1)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stderr
    died_at = float(proc.stdout.strip())
    (path,) = tmp_path.glob("*-crash.mcap")
    data = read_log(path)
    assert data.truncated and data.config == {"a": 1}
    ticks = data.topic("/tick")
    assert ticks, "nothing reached the disk"
    t = [m["t"] for m in ticks]
    assert t == sorted(t) and len(set(t)) == len(t)  # every tick up to the loss, in order
    assert died_at - float(ticks[-1]["status"]) < 1.0


def test_a_full_disk_never_stops_the_flight(tmp_path: Path) -> None:
    # The file-size limit makes writes fail with EFBIG, as a full disk fails them with ENOSPC.
    script = textwrap.dedent(f"""
        import resource, signal
        from cfknode.app.logs.writer import Chunks, FlightLog
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, resource.RLIM_INFINITY))
        log = FlightLog.create({str(tmp_path)!r}, {{"a": 1}}, "v", "full", chunks=Chunks(2048, "none"))
        for k in range(2000):
            log.write("/tick", k / 400, {{"compute_s": 0.0, "solve_s": 0.0, "missed": False, "mpc_ok": True}})
        log.flush()
        log.close()
        print(log.failure is not None, log.messages_dropped, log.messages_written)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    failed, dropped, written = proc.stdout.split()
    assert failed == "True" and int(dropped) > 0 and int(dropped) + int(written) == 2001  # + /config
    assert "flight log stopped writing" in proc.stderr and "full.mcap" in proc.stderr
    (path,) = tmp_path.glob("*-full.mcap")
    data = read_log(path)
    assert data.truncated and 0 < len(data.topic("/tick")) < 2000


def test_not_mcap_is_a_clear_error(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("this is not a flight log\n")
    with pytest.raises(LogError) as info:
        read_log(text)
    message = str(info.value)
    assert str(text) in message and "not an MCAP" in message and "\n" not in message
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(LogError, match="empty"):
        read_log(empty)
    with pytest.raises(LogError, match="missing.mcap"):
        read_log(tmp_path / "missing.mcap")


def test_array_helper(tmp_path: Path) -> None:
    with make_log(tmp_path) as log:
        log.write("/state", 0.0, SAMPLES["/state"])
        log.write("/state", 0.1, {k: v for k, v in SAMPLES["/state"].items() if k != "p_true"})
        log.write("/tick", 0.0, SAMPLES["/tick"])
    data = read_log(log.path)
    p_true = data.array("/state", "p_true")
    assert p_true.shape == (2, 3) and np.allclose(p_true[0], [0.11, -0.19, 1.01]) and np.isnan(p_true[1]).all()
    assert np.array_equal(data.times("/state"), [0.0, 0.1])
    assert data.array("/tick", "missed").dtype == bool
    assert data.array("/tick", "compute_s").shape == (1,)
    assert list(data.array("/tick", "status")) == ["ok"]
    with pytest.raises(KeyError, match="nothing"):
        data.array("/state", "nothing")
    assert data.array("/mocap", "p").shape == (0,)


def test_channels_markdown_lists_every_topic() -> None:
    table = channels_markdown()
    for spec in CHANNELS:
        assert f"`{spec.topic}`" in table

