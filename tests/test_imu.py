"""The accelerometer through the real log path: simulated acc.x/y/z, the radio's 100 Hz block, the loop, log and replay."""

from __future__ import annotations

import itertools
import logging
import math
import time
from pathlib import Path
from typing import Any, Iterator
from unittest import mock

import numpy as np
import pytest

from cfknode.app.backends.imu_log import FirmwareClockMap
from cfknode.app.backends.radio import CflibRadio
from cfknode.app.config import ConfigError, load_config
from cfknode.app.logs.writer import read_log
from cfknode.app.mission import run_flight
from cfknode.app.replay import _logged_imu, logged_config, replay_log
from cfknode.flight.controller import Controller
from cfknode.kernel.clock import WallClock
from cfknode.kernel.imu import FIRMWARE_G, ImuSample
from cfknode.models.quadrotor import quat_to_rotation
from cfknode.sim_backend import link_driver
from cfknode.sim_backend.accelerometer import specific_force
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
from cfknode.sim_backend.realtime import RealtimeStepper
from cfknode.sim_backend.sim_toc import LOG_ITEMS, _toc_crc

_uris = itertools.count(9900)
G = 9.81
STEP_T = 2.0
# A short hover with a 0.5x mass step: take-off 1 s, settle 0.2 s, 1.5 s of hover, land.
HOVER = {
    "trajectory.kind": "hover",
    "trajectory.duration": 1.5,
    "trajectory.takeoff_duration": 1.0,
    "trajectory.settle_duration": 0.2,
    "trajectory.land_duration": 1.0,
}
STEP = {**HOVER, "sim.mass_changes": [{"t": STEP_T, "factor": 0.5}]}


class StepSpy:
    """Records the IMU sample the controller was given at each tick (patched over ``Controller.step``)."""

    def __init__(self) -> None:
        self.seen: dict[float, ImuSample | None] = {}
        self._step = Controller.step

    def __enter__(self) -> "StepSpy":
        spy = self

        def step(controller: Any, t: float, state: Any, reference: Any, **kw: Any) -> Any:
            spy.seen[t] = getattr(state, "imu", None)
            return spy._step(controller, t, state, reference, **kw)

        self._patch = mock.patch.object(Controller, "step", step)
        self._patch.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._patch.stop()


def fly(tmp: Path, **overrides: Any) -> Any:
    cfg = load_config(overrides={**overrides, "log.dir": str(tmp)})
    return run_flight(cfg, name_hint="imu")


def imu_columns(log: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tick times, the IMU sample times and forces each tick saw (NaN where none)."""
    states = log.topic("/state")
    t = np.array([m["t"] for m in states])
    imu_t = np.array([math.nan if m.get("imu_t") is None else m["imu_t"] for m in states])
    imu_f = np.array([[math.nan if v is None else v for v in m.get("imu_f") or (None,) * 3] for m in states])
    return t, imu_t, imu_f


@pytest.fixture(scope="module")
def step_flights(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any, dict[float, ImuSample | None]]:
    with StepSpy() as spy:
        first = fly(tmp_path_factory.mktemp("a"), **STEP)
    second = fly(tmp_path_factory.mktemp("b"), **STEP)
    return first, second, spy.seen


# --- the simulated accelerometer ----------------------------------------------------------------

def test_specific_force_is_gravity_reaction_plus_acceleration_in_the_body_frame() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        acc = rng.standard_normal(3) * 5.0
        state = [0.0] * 6 + list(q) + [0.0] * 7
        expected = quat_to_rotation(q).T @ (acc + np.array([0.0, 0.0, G]))
        assert np.allclose(specific_force(state, acc, G), expected, atol=1e-12)
    level = [0.0] * 6 + [1.0, 0.0, 0.0, 0.0]
    assert specific_force(level, (0.0, 0.0, 0.0), G) == (0.0, 0.0, G)  # hover: +1 g up the body z axis


def test_hover_reads_one_g_and_a_half_mass_step_about_two(step_flights: Any) -> None:
    res = step_flights[0]
    assert res.outcome.message.startswith("flight complete")
    assert res.summary.extra["imu_late"] == 0 and res.summary.extra["imu_samples"] > 300
    t, imu_t, imu_f = imu_columns(read_log(res.summary.log_path))
    assert not np.isnan(imu_t[t > 0.05]).any()  # a sample on every tick from the first 10 ms on
    # Every tick sees the newest sample: measured at or before the tick, less than one 10 ms period old.
    age = t - imu_t
    assert np.nanmin(age) >= -1e-9 and np.nanmax(age) < 0.010 - 1e-9
    window = (imu_t > 1.6 - 1e-9) & (imu_t < STEP_T - 1e-9)
    f = imu_f[window][np.unique(imu_t[window], return_index=True)[1]]
    assert len(f) == 40  # 100 Hz
    assert np.allclose(f.mean(axis=0), [0.0, 0.0, G], atol=0.25)  # (0, 0, 1) g ...
    assert 0.15 < f[:, 0].std() < 0.5 and 0.15 < f[:, 1].std() < 0.5  # ... with the 0.3 m/s^2 noise
    # At the hover thrust, half the mass doubles the specific force: the first sample after the step.
    after = imu_f[np.argmax(imu_t > STEP_T + 1e-9)]
    assert 1.8 * G < after[2] < 2.2 * G


def test_two_lockstep_flights_with_a_mass_step_are_bit_identical(step_flights: Any) -> None:
    a, b = (read_log(r.summary.log_path) for r in step_flights[:2])
    for name in ("imu_t", "imu_f", "p", "v", "p_true"):
        x, y = a.array("/state", name), b.array("/state", name)
        assert x.shape == y.shape and x.shape[0] > 1000
        assert np.array_equal(x, y, equal_nan=True), name
    assert np.array_equal(a.array("/command", "thrust"), b.array("/command", "thrust"))


def test_replay_feeds_the_controller_the_sample_it_saw_in_flight(step_flights: Any) -> None:
    res, _, flown = step_flights
    log = read_log(res.summary.log_path)
    cfg, _ = logged_config(log)
    with StepSpy() as spy:
        result = replay_log(log, cfg)
    assert max(result.max_abs().values()) == 0.0  # the flight replays exactly
    replayed = spy.seen
    assert len(replayed) == result.ticks > 1000
    seen = [flown[t] for t in replayed]
    assert sum(s is not None for s in seen) > 0.95 * len(seen)
    for t, sample in replayed.items():
        want = flown[t]
        assert (sample is None) == (want is None), t
        if want is not None:
            assert sample.t == want.t and np.array_equal(sample.specific_force, want.specific_force), t


def test_a_log_without_imu_fields_replays_with_none() -> None:
    assert _logged_imu({"p": [0, 0, 0]}) is None  # a log from before the field
    assert _logged_imu({"imu_t": None, "imu_f": [None, None, None]}) is None  # no sample yet
    sample = _logged_imu({"imu_t": 1.25, "imu_f": [0.1, -0.2, 9.8]})
    assert sample is not None and sample.t == 1.25 and sample.specific_force.tolist() == [0.1, -0.2, 9.8]


# --- the radio's block ------------------------------------------------------------------------------

@pytest.fixture
def sim(tmp_path: Path) -> Iterator[tuple[SimCrazyflie, str]]:
    cfg = load_config(overrides={"sim.imu_noise": 0.0})
    sim, uri = SimCrazyflie(cfg.vehicle, cfg.sim), f"sim://{next(_uris)}"
    register_simulator(uri, sim)
    yield sim, uri
    unregister_simulator(uri)


def test_lockstep_radio_delivers_every_100_hz_sample_by_its_tick(sim: tuple[SimCrazyflie, str], tmp_path: Path) -> None:
    s, uri = sim
    radio = CflibRadio(uri, lockstep=True, clock=lambda: s.t, advance=s.step_to, rw_cache=str(tmp_path), imu_log=True)
    try:
        radio.connect(timeout=5.0)
        assert radio.imu is not None and radio.imu_note is None
        stamps = []
        for k in range(1, 401):  # 1 s of 400 Hz ticks
            s.step_to(k * 0.0025)
            sample = radio.latest_imu(s.t)
            # No race with cflib's receive thread: the sample of the newest 10 ms mark, every time.
            assert sample is not None and sample.t == math.floor(k * 0.25 + 1e-9) / 100.0 or k < 4, k
            if sample is not None:
                stamps.append(sample.t)
                # On the ground, motors off, no noise: 1 g exactly (a float32 1.0 from the firmware).
                assert sample.specific_force.tolist() == [0.0, 0.0, FIRMWARE_G]
        assert len(set(stamps)) == 100
        stats = radio.stats()
        assert stats.imu_samples == 100 and stats.imu_late == 0
    finally:
        radio.shutdown()


def test_wall_clock_radio_stamps_samples_on_the_flight_clock(sim: tuple[SimCrazyflie, str], tmp_path: Path) -> None:
    s, uri = sim
    clock = WallClock()
    radio = CflibRadio(uri, lockstep=False, clock=clock.now, rw_cache=str(tmp_path), imu_log=True)
    stepper = RealtimeStepper(s, clock.now)
    try:
        radio.connect(timeout=5.0)
        stepper.start()
        seen = []
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            now = clock.now()
            sample = radio.latest_imu(now)
            if sample is not None:
                assert sample.t <= now + 5e-4  # never from the future
                seen.append(sample.t)
            time.sleep(0.003)
        assert len(set(seen)) >= 10 and np.all(np.diff(seen) >= 0)
        offset = radio.imu.stats().offset_s
        # The simulator's clock is the wall clock, stepped up to one plant step ahead of it.
        assert offset is not None and -s.dt - 1e-9 <= offset < 0.1
    finally:
        radio.shutdown()
        stepper.stop()


def test_firmware_clock_map_offset_floor_wrap_and_drift() -> None:
    exact = FirmwareClockMap(exact=True)
    assert exact.stamp(1234, received=99.0) == 1.234 and exact.offset == 0.0
    m = FirmwareClockMap(exact=False)
    delays = [0.006, 0.002, 0.009, 0.004]
    for k in range(40):
        fw_ms = 5000 + 10 * k
        t = m.stamp(fw_ms, received=100.0 + fw_ms / 1000.0 + delays[k % 4])
    assert m.offset == pytest.approx(100.002) and t == pytest.approx(100.0 + 5.39 + 0.002)
    # The 24-bit timestamp wraps every 4.66 h; the map keeps counting.
    w = FirmwareClockMap(exact=True)
    assert w.stamp((1 << 24) - 10, 0.0) == pytest.approx(16777.206)
    assert w.stamp(0, 0.0) == pytest.approx(16777.216)
    # A host clock running 100 ppm fast: the window's minimum follows it.
    d = FirmwareClockMap(exact=False, window=50)
    for k in range(2000):
        fw = k * 0.01
        d.stamp(k * 10, received=fw * (1 + 1e-4) + 0.003)
    assert d.offset == pytest.approx(19.99 * 1e-4 + 0.003, abs=1e-4)
    with pytest.raises(ValueError):
        FirmwareClockMap(exact=False, window=0)


def test_a_firmware_without_the_accelerometer_flies_with_a_warning_and_no_imu(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    old = LOG_ITEMS[:4]  # the TOC before acc.x/y/z
    with mock.patch.object(link_driver, "LOG_ITEMS", old), mock.patch.object(link_driver, "LOG_CRC", _toc_crc(old)):
        with caplog.at_level(logging.WARNING):
            res = fly(tmp_path, **HOVER)
    assert res.outcome.message.startswith("flight complete")
    assert any("accelerometer" in r.getMessage() and "\n" not in r.getMessage() for r in caplog.records)
    log = read_log(res.summary.log_path)
    assert any(e["level"] == "warning" and "acc.x" in e["text"] for e in log.topic("/events"))
    assert all("imu_t" not in m for m in log.topic("/state"))  # no IMU: nothing logged for it


def test_imu_log_off_flies_without_it(tmp_path: Path) -> None:
    cfg = load_config(overrides={"radio.imu_log": False})
    s = SimCrazyflie(cfg.vehicle, cfg.sim)
    uri = f"sim://{next(_uris)}"
    register_simulator(uri, s)
    radio = CflibRadio(uri, lockstep=True, clock=lambda: s.t, advance=s.step_to, rw_cache=str(tmp_path),
                       imu_log=cfg.radio.imu_log)
    try:
        radio.connect(timeout=5.0)
        s.step_to(0.1)
        assert radio.imu is None and radio.latest_imu(s.t) is None and radio.stats().imu_samples == 0
    finally:
        radio.shutdown()
        unregister_simulator(uri)


@pytest.mark.parametrize("value", [-0.1, 6.0])
def test_a_bad_imu_noise_is_one_clear_line(value: float) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(overrides={"sim.imu_noise": value})
    message = str(err.value)
    assert "sim.imu_noise" in message and "m/s^2" in message and "\n" not in message
