"""CflibRadio over a stock cflib Crazyflie and the sim:// link: slots, TX rate, threads, shutdown."""

from __future__ import annotations

import itertools
import threading
from typing import Any, Iterator

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.app.backends.radio import CflibRadio, HardwareRadio, LinkSafety, RadioError
from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
from fakes import RecordingFirmware, serve_sim

_uris = itertools.count(9300)


class FakeSim:
    dt = 0.002
    battery_voltage = 4.0

    def __init__(self) -> None:
        self.t = 0.0
        self.lock = threading.RLock()
        self.firmware = RecordingFirmware(note=threading.get_ident)

    def add_step_observer(self, cb: Any) -> None:
        pass

    def step_to(self, t_target: float) -> None:
        self.t = max(self.t, t_target)


@pytest.fixture
def sim_uri() -> Iterator[tuple[FakeSim, str]]:
    yield from serve_sim(FakeSim(), next(_uris))


def wait_for(predicate: Any, timeout: float = 2.0) -> bool:
    event = threading.Event()
    for _ in range(int(timeout / 0.005)):
        if predicate():
            return True
        event.wait(0.005)
    return predicate()


def test_connect_sends_the_unlock_first(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(uri, lockstep=True, clock=lambda: sim.t)
    radio.connect(timeout=2.0)
    try:
        assert sim.firmware.calls == [("rpyt", 0.0, 0.0, -0.0, 0.0, 0)]
        assert radio.stats().setpoints_sent == 1
        with pytest.raises(RadioError, match="already connected"):
            radio.connect()
    finally:
        radio.shutdown()


def test_connect_failure_is_one_clear_line() -> None:
    radio = CflibRadio("sim://9299", lockstep=True)
    with pytest.raises(RadioError) as info:
        radio.connect(timeout=2.0)
    message = str(info.value)
    assert "\n" not in message
    assert "sim://9299" in message and "no simulator registered" in message
    radio.shutdown()  # nothing to hand back: a no-op
    radio.shutdown()


def test_lockstep_pump_sends_newest_setpoint_at_tx_rate(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(uri, tx_rate_hz=100.0, lockstep=True, clock=lambda: sim.t)
    radio.connect(timeout=2.0)
    try:
        period = 1.0 / 400.0
        sent_at_tick: list[int] = []
        for k in range(40):  # 0.1 s of 400 Hz ticks, a new setpoint every tick
            sim.t = k * period
            n_before = len(sim.firmware.named("rpyt"))
            radio.set_setpoint(AttitudeSetpoint(float(k), -0.5 * k, 2.0 * k, 20000 + k))
            radio.pump(sim.t)
            if len(sim.firmware.named("rpyt")) > n_before:
                sent_at_tick.append(k)
        rpyt = sim.firmware.named("rpyt")[1:]  # after the unlock
        assert sent_at_tick == list(range(0, 40, 4))  # 100 Hz out of 400 Hz ticks
        for (_, t, roll, wire_pitch, yawrate, thrust), k in zip(rpyt, sent_at_tick):
            # The newest value of that tick, at that tick's sim time, pitch negated by cflib.
            assert (t, roll, wire_pitch, yawrate, thrust) == (k * period, k, 0.5 * k, 2.0 * k, 20000 + k)
        assert radio.stats().setpoints_sent == 11
        assert radio.stats().last_send_time == pytest.approx(36 * period)
        assert all(tid == threading.get_ident() for tid in sim.firmware.notes)  # no thread sends
    finally:
        radio.shutdown()


def test_lockstep_extpose_forwarded_once_in_xyzw_order(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(uri, tx_rate_hz=100.0, lockstep=True, clock=lambda: sim.t)
    radio.connect(timeout=2.0)
    try:
        q_wxyz = np.array([0.5, 0.5, -0.5, 0.5])
        for k in range(12):
            sim.t = k * 0.0025
            if k % 4 == 0:  # a 100 Hz mocap frame every 4th tick
                radio.set_extpose(np.array([0.25 * k, -1.0, 1.5]), q_wxyz)
            radio.pump(sim.t)
        extposes = sim.firmware.named("extpose")
        assert [c[1] for c in extposes] == [0.0, 0.01, 0.02]
        assert [c[2] for c in extposes] == [(0.0, -1.0, 1.5), (1.0, -1.0, 1.5), (2.0, -1.0, 1.5)]
        assert all(c[3] == (0.5, -0.5, 0.5, 0.5) for c in extposes)  # x, y, z, w
        assert radio.stats().extposes_sent == 3
    finally:
        radio.shutdown()


def test_threaded_mode_sends_from_its_own_thread(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(uri, tx_rate_hz=200.0, lockstep=False)
    radio.connect(timeout=2.0)
    caller = threading.get_ident()
    try:
        n_unlock = len(sim.firmware.calls)
        radio.set_setpoint(AttitudeSetpoint(1.0, 2.0, 3.0, 12000))
        radio.pump(0.0)  # a no-op in threaded mode
        radio.set_extpose(np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, 0.0, 0.0]))
        assert wait_for(lambda: len(sim.firmware.named("rpyt")) >= 4 and sim.firmware.named("extpose"))
        radio.set_setpoint(AttitudeSetpoint(-1.0, -2.0, -3.0, 13000))
        assert wait_for(lambda: sim.firmware.named("rpyt")[-1][2:] == (-1.0, 2.0, -3.0, 13000))
        sent_threads = set(sim.firmware.notes[n_unlock:])
        assert caller not in sent_threads and len(sent_threads) == 1
        extpose = sim.firmware.named("extpose")
        assert len(extpose) == 1  # one pose, forwarded once
        assert extpose[0][2:] == ((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))
    finally:
        radio.shutdown()
    tx_thread = sim.firmware.notes[-1]
    assert tx_thread != caller  # the hand-back ran on the TX thread too
    assert sim.firmware.calls[-2:] == [("notify_stop", 0.0), ("hl_stop", 0.0)]


@pytest.mark.parametrize("lockstep", [True, False])
def test_shutdown_order_and_idempotence(sim_uri: tuple[FakeSim, str], lockstep: bool) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(
        uri, tx_rate_hz=100.0, lockstep=lockstep, safety=LinkSafety(zero_stream_s=0.05), clock=lambda: sim.t, advance=sim.step_to
    )
    radio.connect(timeout=2.0)
    radio.set_setpoint(AttitudeSetpoint(5.0, 5.0, 5.0, 30000))
    radio.pump(0.0)
    if not lockstep:
        assert wait_for(lambda: len(sim.firmware.named("rpyt")) >= 2)
    cf = radio.cf
    radio.shutdown()
    calls = sim.firmware.calls
    tail = calls[-7:]
    # Five zero setpoints (0.05 s at 100 Hz), then hand the commander to the stopped HL planner.
    assert [c[0] for c in tail] == ["rpyt"] * 5 + ["notify_stop", "hl_stop"]
    assert all(c[2:] == (0.0, -0.0, 0.0, 0) for c in tail[:5])
    if lockstep:
        # The zero stream spans simulated time: one TX period apart.
        assert [c[1] for c in tail[:5]] == pytest.approx([0.0, 0.01, 0.02, 0.03, 0.04])
    # Nothing after the HL stop: cflib's close_link() zero setpoint would re-take the commander.
    assert cf.link is None and not cf.is_connected()
    n = len(calls)
    radio.shutdown()
    radio.set_setpoint(AttitudeSetpoint(1.0, 1.0, 1.0, 20000))
    radio.pump(1.0)
    assert len(sim.firmware.calls) == n
    stats = radio.stats()
    assert stats.setpoints_sent == len(sim.firmware.named("rpyt"))
    assert stats.send_errors == 0 and stats.link_lost is None


def test_send_errors_are_counted_not_raised(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    with CflibRadio(uri, lockstep=True, clock=lambda: sim.t) as radio:
        radio.connect(timeout=2.0)
        radio.set_setpoint(AttitudeSetpoint(0.0, 0.0, 0.0, 70000))  # cflib rejects > 0xFFFF
        radio.pump(0.0)
        stats = radio.stats()
        assert stats.send_errors == 1 and "ValueError" in stats.last_error
        assert stats.setpoints_sent == 1  # only the unlock
    assert sim.firmware.calls[-1][0] == "hl_stop"  # the context manager shut it down


def test_link_lost_is_reported(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    radio = CflibRadio(uri, lockstep=True, clock=lambda: sim.t)
    radio.connect(timeout=2.0)
    unregister_simulator(uri)
    assert wait_for(lambda: radio.stats().link_lost is not None)
    assert "unregistered" in radio.stats().link_lost
    radio.set_setpoint(AttitudeSetpoint(1.0, 1.0, 1.0, 20000))
    radio.pump(0.0)
    assert radio.stats().setpoints_sent == 1  # nothing counted once the link is gone
    radio.shutdown()
    register_simulator(uri, sim)  # for the fixture's teardown


def test_from_config_uses_radio_section() -> None:
    cfg = load_config(overrides={"radio.tx_rate_hz": 150.0, "radio.uri": "sim://7"})
    radio = CflibRadio(cfg.radio.uri, tx_rate_hz=cfg.radio.tx_rate_hz, lockstep=True)
    assert radio.uri == "sim://7"
    assert radio.tx_rate_hz == 150.0 and radio.lockstep


def test_flies_the_real_simulator_and_hands_it_back_unlocked() -> None:
    from cfknode.sim_backend.crazyflie import SimCrazyflie

    cfg = load_config()
    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    uri = f"sim://{next(_uris)}"
    register_simulator(uri, sim)
    radio = CflibRadio(cfg.radio.uri, tx_rate_hz=cfg.radio.tx_rate_hz, lockstep=True, clock=lambda: sim.t, advance=sim.step_to)
    radio.uri = uri
    try:
        radio.connect(timeout=2.0)
        fw = sim.firmware
        assert not fw.thrust_locked  # the unlock arrived
        # Climb with +pitch and +roll: cflib's pitch is right-handed (nose down -> +x) and
        # +roll is right side down (-> -y) (docs/hardware.md#rpyt-setpoint), through cflib, the wire and the firmware.
        period = 1.0 / cfg.controller.rate_hz
        for k in range(int(round(0.8 / period))):
            t = k * period
            if k % 4 == 0:
                s = sim.state
                radio.set_extpose(s[:3].copy(), s[6:10].copy())
            radio.set_setpoint(AttitudeSetpoint(4.0, 4.0, 0.0, 48000))
            radio.pump(t)
            sim.step_to(t + period)
        assert fw.supervisor_state == "flying"
        assert fw.last_setpoint.thrust == 48000
        assert fw.setpoints_received == radio.stats().setpoints_sent == 81  # unlock + 80 at 100 Hz
        assert fw.extposes_received == radio.stats().extposes_sent == 80
        state = sim.state
        assert state[2] > 0.05  # climbed
        assert state[3] > 0.05 and state[4] < -0.05  # +pitch -> +x, +roll -> -y
        radio.shutdown()
        sim.step_to(sim.t + 3.0)
        # Handed to the stopped HL planner: the watchdog is satisfied and the drone lands, not locks.
        assert fw.supervisor_state == "landed"
    finally:
        radio.shutdown()
        unregister_simulator(uri)


# --- the hardware radio ------------------------------------------------------------------------

PARAMS = {"stabilizer.estimator": 2, "stabilizer.controller": 1, "locSrv.extPosStdDev": 1e-3,
          "locSrv.extQuatStdDev": 0.05}


@pytest.fixture
def real_sim(tmp_path: Any) -> Iterator[tuple[Any, str]]:
    from cfknode.sim_backend.crazyflie import SimCrazyflie

    sim, uri = SimCrazyflie(load_config().vehicle, load_config().sim), f"sim://{next(_uris)}"
    register_simulator(uri, sim)
    yield sim, uri
    unregister_simulator(uri)


def hardware_radio(sim: Any, uri: str, tmp_path: Any, **kwargs: Any) -> HardwareRadio:
    options: dict[str, Any] = dict(params=PARAMS, safety=LinkSafety(heartbeat_hz=5.0), lockstep=True, clock=lambda: sim.t,
                                   advance=sim.step_to, rw_cache=str(tmp_path))
    options.update(kwargs)
    return HardwareRadio(uri, **options)


def fly_lockstep(radio: CflibRadio, sim: Any, seconds: float, sp: AttitudeSetpoint) -> None:
    """400 Hz ticks: set the setpoint, pump, step the simulator."""
    period = 1.0 / 400.0
    t0 = sim.t
    for k in range(int(round(seconds / period))):
        radio.set_setpoint(sp)
        radio.pump(t0 + k * period)
        sim.step_to(t0 + (k + 1) * period)


def test_hardware_radio_sets_parameters_and_resets_the_estimator(real_sim: tuple[Any, str], tmp_path: Any) -> None:
    from cfknode.sim_backend.link_driver import PARAM_TOC, _registry

    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path, params={**PARAMS, "pm.lowVoltage": 3.3})
    radio.connect(timeout=5.0)
    try:
        values = dict(zip((f"{p.group}.{p.name}" for p in PARAM_TOC), _registry[uri].param_values))
        assert values["stabilizer.estimator"] == 2 and values["stabilizer.controller"] == 1
        assert values["locSrv.extPosStdDev"] == pytest.approx(1e-3) and values["locSrv.extQuatStdDev"] == pytest.approx(0.05)
        assert values["pm.lowVoltage"] == pytest.approx(3.3)
        assert radio.protocol_version == 12 and radio.heartbeat_enabled
        radio.reset_estimator()
        assert values["kalman.resetEstimation"] == 0
        assert dict(zip((f"{p.group}.{p.name}" for p in PARAM_TOC), _registry[uri].param_values))[
            "kalman.resetEstimation"] == 0  # set to 1, then back to 0, each confirmed
        assert not sim.firmware.thrust_locked  # the unlock went out after the parameters
    finally:
        radio.shutdown()


def test_a_parameter_the_firmware_lacks_is_one_line_and_leaves_nothing_open(real_sim: tuple[Any, str], tmp_path: Any) -> None:
    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path, params={"stabilizer.estimatr": 2}, lockstep=False)
    with pytest.raises(RadioError) as info:
        radio.connect(timeout=5.0)
    assert str(info.value) == f"{uri} has no parameter 'stabilizer.estimatr' (firmware too old, or a typo?)"
    assert radio.cf is None and sim.firmware.setpoints_received == 0  # never unlocked
    assert not any(t.name.startswith("radio-tx") for t in threading.enumerate())
    radio.shutdown()  # a no-op


def test_telemetry_and_link_statistics_snapshots(real_sim: tuple[Any, str], tmp_path: Any) -> None:
    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path, telemetry_hz=20.0)
    radio.connect(timeout=5.0)
    try:
        assert radio.telemetry() is None
        fly_lockstep(radio, sim, 0.5, AttitudeSetpoint(0.0, 0.0, 0.0, 0))
        assert wait_for(lambda: radio.telemetry() is not None and radio.telemetry().samples >= 10)
        tel = radio.telemetry()
        assert tel.vbat == pytest.approx(sim.battery_voltage, abs=0.02)
        assert tel.pm_state == 0 and tel.rssi > 0
        assert tel.supervisor_info & 0b1000  # can fly
        assert tel.firmware_ms == pytest.approx(500, abs=50)
        assert wait_for(lambda: radio.link_statistics().latency_ms is not None)
        link = radio.link_statistics()
        assert link.link_quality == 100.0 and link.uplink_rate > 90.0 and link.downlink_rate > 15.0
        assert radio.stats().latency_ms == link.latency_ms  # what the safety layer's link watchdog reads
        assert link.packets_sent == radio.stats().setpoints_sent + radio.stats().heartbeats_sent
    finally:
        radio.shutdown()


def test_heartbeat_at_its_rate_in_lockstep(real_sim: tuple[Any, str], tmp_path: Any) -> None:
    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path, reboot_after_heartbeat=False)
    radio.connect(timeout=5.0)
    fly_lockstep(radio, sim, 1.0, AttitudeSetpoint(0.0, 0.0, 0.0, 0))
    assert radio.stats().heartbeats_sent == 5  # 5 Hz over 1 s of pumps
    assert sim.firmware.estop_watchdog_notifications == 5
    radio.shutdown()
    # The armed watchdog stops and locks the drone 1 s after the last heartbeat, landed or not.
    assert radio.handback_note.startswith("the emergency-stop watchdog is armed")
    sim.step_to(sim.t + 0.5)
    assert sim.firmware.supervisor_state == "idle"
    sim.step_to(sim.t + 1.0)
    assert sim.firmware.supervisor_state == "locked"
    assert sim.firmware.lock_reason == "emergency_stop_watchdog"


def test_flight_then_hand_back_with_reboot_leaves_the_drone_unlocked(real_sim: tuple[Any, str], tmp_path: Any) -> None:
    """Acceptance: fly on the heartbeat, land, shut down: the firmware is neither locked by the
    commander watchdog (hand-back to the stopped HL planner) nor by the emergency-stop
    watchdog (the reboot through the nRF51 clears it)."""
    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path)
    radio.connect(timeout=5.0)
    fly_lockstep(radio, sim, 0.6, AttitudeSetpoint(0.0, 0.0, 0.0, 46000))
    assert sim.firmware.supervisor_state == "flying" and sim.state[2] > 0.02
    fly_lockstep(radio, sim, 1.0, AttitudeSetpoint(0.0, 0.0, 0.0, 0))  # motors off: it falls and lands
    assert radio.stats().heartbeats_sent == 8
    radio.shutdown()
    assert radio.handback_note is None and radio.stats().send_errors == 0
    fw = sim.firmware
    assert fw.boots == 2 and fw.powered
    sim.step_to(sim.t + 3.0)
    assert fw.supervisor_state == "idle" and fw.lock_reason is None
    assert not fw.estop_watchdog_active


def test_no_heartbeat_below_protocol_12(real_sim: tuple[Any, str], tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    import cfknode.sim_backend.link_driver as link_driver

    monkeypatch.setattr(link_driver, "PROTOCOL_VERSION", 11)
    sim, uri = real_sim
    radio = hardware_radio(sim, uri, tmp_path)
    radio.connect(timeout=5.0)
    assert radio.protocol_version == 11 and not radio.heartbeat_enabled
    fly_lockstep(radio, sim, 0.5, AttitudeSetpoint(0.0, 0.0, 0.0, 0))
    radio.shutdown()
    assert radio.stats().heartbeats_sent == 0 and sim.firmware.estop_watchdog_notifications == 0
    assert sim.firmware.boots == 1  # nothing armed, nothing to reboot


def test_threaded_heartbeat_and_extposes_fed_from_the_mocap_thread(sim_uri: tuple[FakeSim, str], tmp_path: Any) -> None:
    sim, uri = sim_uri
    radio = HardwareRadio(uri, params={}, safety=LinkSafety(heartbeat_hz=20.0), lockstep=False, rw_cache=str(tmp_path),
                          reboot_after_heartbeat=False)
    radio.connect(timeout=2.0)
    caller = threading.get_ident()
    try:
        assert wait_for(lambda: len(sim.firmware.named("heartbeat")) >= 3)
        radio.set_extpose(np.array([9.0, 9.0, 9.0]), np.array([1.0, 0.0, 0.0, 0.0]))  # the loop's copy
        assert wait_for(lambda: len(sim.firmware.named("extpose")) == 1)
        feeder = threading.Thread(target=radio.feed_extpose, args=(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0])))
        feeder.start()
        feeder.join()
        assert wait_for(lambda: len(sim.firmware.named("extpose")) == 2)
        radio.set_extpose(np.array([9.0, 9.0, 9.0]), np.array([1.0, 0.0, 0.0, 0.0]))  # now redundant
        threading.Event().wait(0.05)
        assert len(sim.firmware.named("extpose")) == 2
        assert sim.firmware.named("extpose")[1][2:] == ((1.0, 2.0, 3.0), (0.0, 0.0, 1.0, 0.0))
    finally:
        radio.shutdown()
    heartbeat_threads = {tid for (name, *_), tid in zip(sim.firmware.calls, sim.firmware.notes) if name == "heartbeat"}
    assert caller not in heartbeat_threads and len(heartbeat_threads) == 1  # the TX thread
