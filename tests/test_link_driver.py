"""The sim:// link driver under the stock cflib Crazyflie: handshake, decoding, logs, params."""

from __future__ import annotations

import itertools
import struct
import threading
from typing import Any, Iterator

import cflib.crtp
import numpy as np
import pytest
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie
from cflib.crtp.crtpstack import CRTPPacket
from cflib.crtp.exceptions import WrongUriType

from cfknode.sim_backend.link_driver import (
    PROTOCOL_VERSION,
    SimLinkDriver,
    SimLinkError,
    register_simulator,
    supervisor_bitfield,
    unregister_simulator,
)
from fakes import RecordingFirmware, serve_sim

_uris = itertools.count(9100)


class FakeSim:
    """The SimCrazyflie surface the driver uses, with a clock the test steps by hand."""

    dt = 0.002

    def __init__(self) -> None:
        self.t = 0.0
        self.lock = threading.Lock()
        self.firmware = RecordingFirmware(note=self.lock.locked)
        self.battery_voltage = 3.95
        self._observers: list = []

    def add_step_observer(self, cb: Any) -> None:
        self._observers.append(cb)

    def step_to(self, t_target: float) -> None:
        while self.t < t_target - 1e-12:
            with self.lock:
                self.t += self.dt
                for cb in self._observers:
                    cb(self.t, None)


@pytest.fixture
def sim_uri() -> Iterator[tuple[FakeSim, str]]:
    yield from serve_sim(FakeSim(), next(_uris))


@pytest.fixture
def connected(sim_uri: tuple[FakeSim, str]) -> Iterator[tuple[FakeSim, Crazyflie]]:
    sim, uri = sim_uri
    with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
        yield sim, scf.cf


def f32(x: float) -> float:
    return float(np.float32(x))


def test_stock_cflib_connects_within_a_second(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    cf = Crazyflie()
    connected, fully = threading.Event(), threading.Event()
    cf.connected.add_callback(lambda u: connected.set())
    cf.fully_connected.add_callback(lambda u: fully.set())
    cf.open_link(uri)
    try:
        assert connected.wait(1.0)
        assert fully.wait(1.0)  # the param TOC's values arrived too
        assert cf.platform.get_protocol_version() == PROTOCOL_VERSION
        assert isinstance(cf.link, SimLinkDriver) and cf.link.needs_resending is False
        assert sim.firmware.calls == []  # the handshake never reaches the commander
    finally:
        cf.close_link()


def test_driver_is_installed_once_in_front(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    register_simulator(uri, sim)  # again: harmless
    other = f"sim://{next(_uris)}"
    register_simulator(other, FakeSim())
    unregister_simulator(other)
    assert cflib.crtp.CLASSES[0] is SimLinkDriver
    assert cflib.crtp.CLASSES.count(SimLinkDriver) == 1
    assert len(cflib.crtp.CLASSES) > 1  # cflib's own drivers are still behind it
    with pytest.raises(SimLinkError, match="already registered"):
        register_simulator(uri, FakeSim())


def test_foreign_and_unregistered_uris() -> None:
    with pytest.raises(WrongUriType):
        SimLinkDriver().connect("radio://0/80/2M/E7E7E7E7E7", None, None)
    with pytest.raises(SimLinkError, match="no simulator registered at sim://9099"):
        SimLinkDriver().connect("sim://9099", None, None)
    with pytest.raises(SimLinkError, match="malformed"):
        SimLinkDriver().connect("sim://zero", None, None)

    cf = Crazyflie()
    failed: list[str] = []
    done = threading.Event()
    cf.connection_failed.add_callback(lambda uri, msg: (failed.append(msg), done.set()))
    cf.open_link("sim://9099")
    assert done.wait(1.0)
    cf.close_link()
    assert "no simulator registered at sim://9099" in failed[0]


@pytest.mark.parametrize(
    "roll, pitch, yawrate, thrust",
    [(3.5, 7.25, -20.0, 36000), (-12.3, -4.1, 45.6, 65535), (0.0, 0.0, 0.0, 0), (1e-3, -2e-3, 3e-3, 999)],
)
def test_rpyt_reaches_firmware_as_on_the_wire(
    connected: tuple[FakeSim, Crazyflie], roll: float, pitch: float, yawrate: float, thrust: int
) -> None:
    sim, cf = connected
    sim.t = 1.25
    cf.commander.send_setpoint(roll, pitch, yawrate, thrust)
    # cflib negates pitch; yaw rate and thrust travel as given (the firmware clamps, not cflib).
    assert sim.firmware.calls == [("rpyt", 1.25, f32(roll), f32(-pitch), f32(yawrate), thrust)]
    assert sim.firmware.notes == [True]
    assert cf.link.setpoints == 1


def test_extpose_quaternion_is_xyzw_on_the_wire(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    sim.t = 0.5
    q = np.array([0.1, -0.2, 0.3, 0.0])
    q[3] = np.sqrt(1.0 - np.sum(q[:3] ** 2))  # qw
    cf.extpos.send_extpose(1.5, -2.25, 0.75, *q)
    ((name, t, pos, quat),) = sim.firmware.calls
    assert (name, t) == ("extpose", 0.5)
    assert pos == (1.5, -2.25, 0.75)
    assert quat == tuple(f32(v) for v in q)
    assert sim.firmware.notes == [True]
    assert cf.link.extposes == 1


def test_stop_notify_and_hl_stop_decoded(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    sim.t = 2.0
    cf.commander.send_stop_setpoint()
    sim.t = 2.01
    cf.commander.send_notify_setpoint_stop()
    sim.t = 2.02
    cf.high_level_commander.stop()
    assert sim.firmware.calls == [("stop", 2.0), ("notify_stop", 2.01), ("hl_stop", 2.02)]
    assert all(sim.firmware.notes)


def test_unknown_and_malformed_packets_are_counted_not_fatal(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    before = cf.link.unknown_packets
    cf.send_packet(CRTPPacket(0x00, b"hello console"))  # console port: not served
    cf.send_packet(CRTPPacket(0x30, b"\x01\x02"))  # RPYT, too short
    cf.high_level_commander.takeoff(1.0, 2.0)  # needs the onboard planner: not modelled
    cf.commander.send_position_setpoint(0.0, 0.0, 1.0, 0.0)  # generic type 7
    cf.extpos.send_extpos(1.0, 2.0, 3.0)  # port 6 ch 0: position only
    cf.send_packet(CRTPPacket(0x71, b""))  # empty meta command
    assert cf.link.unknown_packets - before == 6
    assert sim.firmware.calls == []
    cf.commander.send_setpoint(1.0, 2.0, 3.0, 4000)  # the link still works
    assert sim.firmware.calls == [("rpyt", 0.0, 1.0, -2.0, 3.0, 4000)]


def test_ping_is_echoed(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    latency = threading.Event()
    cf.link_statistics.latency.latency_updated.add_callback(lambda ms: latency.set())
    cf.link_statistics.latency.ping()
    assert latency.wait(1.0)

    echoed: list[bytes] = []
    got = threading.Event()

    def on_packet(pk: CRTPPacket) -> None:
        if pk.port == 15 and pk.channel == 0 and pk.data[0] == 0x42:
            echoed.append(bytes(pk.data))
            got.set()

    cf.packet_received.add_callback(on_packet)
    cf.send_packet(CRTPPacket(0xF0, b"\x42payload"))
    assert got.wait(1.0)
    assert echoed == [b"\x42payload"]


def test_receive_packet_wait_semantics(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    driver = SimLinkDriver()
    driver.connect(uri, None, None)
    assert driver.receive_packet(0) is None  # poll: nothing queued
    assert driver.receive_packet(0.01) is None  # timeout: nothing arrives
    driver.send_packet(CRTPPacket(0xF0, b"\x01abc"))
    pk = driver.receive_packet(0)
    assert (pk.port, pk.channel, bytes(pk.data)) == (15, 0, b"\x01abc")
    driver.send_packet(CRTPPacket(0xF0, b"\x02"))
    assert bytes(driver.receive_packet(-1).data) == b"\x02"  # block: returns what is queued

    result: list[Any] = ["pending"]
    reader = threading.Thread(target=lambda: result.__setitem__(0, driver.receive_packet(-1)))
    reader.start()
    reader.join(0.05)
    assert reader.is_alive()  # blocked: nothing to read
    driver.close()
    reader.join(1.0)
    assert not reader.is_alive() and result[0] is None  # close wakes a blocked reader
    driver.send_packet(CRTPPacket(0x30, struct.pack("<fffH", 1.0, 2.0, 3.0, 4)))
    assert sim.firmware.calls == []  # a closed link delivers nothing


def test_unregister_reports_the_link_lost(sim_uri: tuple[FakeSim, str]) -> None:
    sim, uri = sim_uri
    with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
        lost = threading.Event()
        scf.cf.connection_lost.add_callback(lambda u, msg: lost.set())
        unregister_simulator(uri)
        assert lost.wait(1.0)
        assert scf.cf.link is None


def test_log_blocks_stream_on_sim_time(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    sim.firmware.supervisor_state = "flying"
    conf = LogConfig("status", 20)
    for name in ("pm.vbat", "pm.state", "supervisor.info", "radio.rssi"):
        conf.add_variable(name)
    samples: list[tuple[int, dict]] = []
    cf.log.add_config(conf)
    conf.data_received_cb.add_callback(lambda ts, data, lc: samples.append((ts, data)))
    started = threading.Event()
    conf.started_cb.add_callback(lambda lc, ok: started.set())
    conf.start()
    assert started.wait(1.0)
    sim.step_to(0.2)
    sim.firmware.supervisor_state = "locked"
    sim.step_to(0.3)
    conf.stop()

    deadline = threading.Event()
    for _ in range(100):  # the samples cross cflib's receive thread
        if len(samples) == 15:
            break
        deadline.wait(0.01)
    assert [ts for ts, _ in samples] == [20 * k for k in range(1, 16)]
    first, last = samples[0][1], samples[-1][1]
    assert first["pm.vbat"] == pytest.approx(3.95, abs=1e-6)
    assert first["pm.state"] == 0
    assert first["radio.rssi"] > 0
    assert first["supervisor.info"] == supervisor_bitfield("flying")
    assert last["supervisor.info"] == supervisor_bitfield("locked")
    assert supervisor_bitfield("flying") & (1 << 4) and supervisor_bitfield("locked") & (1 << 6)


def test_log_block_errors(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    conf = LogConfig("missing", 100)
    conf.add_variable("stateEstimate.x", "float")
    with pytest.raises(KeyError):
        cf.log.add_config(conf)  # not in the served TOC: cflib refuses it up front
    replies: list[bytes] = []
    got = threading.Event()

    def on_log_control(pk: CRTPPacket) -> None:
        if pk.channel == 1:
            replies.append(bytes(pk.data))
            if pk.data[1] == 78:
                got.set()

    cf.add_port_callback(5, on_log_control)
    # Starting unknown blocks: each gets its own ENOENT reply (replies cross cflib's receive thread).
    cf.send_packet(CRTPPacket(0x51, bytes((3, 77, 10))))
    cf.send_packet(CRTPPacket(0x51, bytes((3, 78, 10))))
    assert got.wait(1.0)
    assert bytes((3, 77, 2)) in replies and bytes((3, 78, 2)) in replies


def test_params_read_write_and_supervisor_bitfield(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    assert float(cf.param.get_value("pm.lowVoltage")) == pytest.approx(3.2, abs=1e-6)
    assert cf.param.get_value("stabilizer.estimator") == "1"
    updated = threading.Event()
    cf.param.add_update_callback(group="stabilizer", name="estimator", cb=lambda n, v: updated.set())
    cf.param.set_value("stabilizer.estimator", 2)
    assert updated.wait(1.0)
    assert cf.param.get_value("stabilizer.estimator") == "2"

    sim.firmware.supervisor_state = "flying"
    assert cf.supervisor.read_bitfield() == supervisor_bitfield("flying")
    assert cf.supervisor.is_flying and not cf.supervisor.is_locked


def test_pm_state_goes_low_after_five_seconds_under_threshold(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    conf = LogConfig("pm", 500)
    conf.add_variable("pm.state")
    states: list[int] = []
    cf.log.add_config(conf)
    conf.data_received_cb.add_callback(lambda ts, data, lc: states.append(data["pm.state"]))
    started = threading.Event()
    conf.started_cb.add_callback(lambda lc, ok: started.set())
    conf.start()
    assert started.wait(1.0)
    sim.step_to(1.0)
    sim.battery_voltage = 3.1  # below pm.lowVoltage (3.2 V) from t = 1 s
    sim.step_to(8.0)
    sim.battery_voltage = 3.5  # recovered
    sim.step_to(9.0)
    conf.stop()
    for _ in range(100):
        if len(states) == 18:
            break
        threading.Event().wait(0.01)
    # Samples at 0.5, 1.0, ... 9.0 s. The low voltage is first seen by the step ending at
    # 1.002 s, so lowPower holds from 6.002 s: the samples at 6.5 ... 8.0 s (recovery is seen
    # by the step after 8.0 s).
    assert states == [0] * 12 + [3] * 4 + [0] * 2


def test_real_simulator_behind_stock_cflib() -> None:
    from cfknode.app.config import load_config
    from cfknode.sim_backend.crazyflie import SimCrazyflie

    sim = SimCrazyflie(load_config().vehicle, load_config().sim)
    uri = f"sim://{next(_uris)}"
    register_simulator(uri, sim)
    try:
        with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
            cf = scf.cf
            conf = LogConfig("status", 100)
            for name in ("pm.vbat", "supervisor.info"):
                conf.add_variable(name)
            samples: list[dict] = []
            conf.data_received_cb.add_callback(lambda ts, data, lc: samples.append(data))
            cf.log.add_config(conf)
            started = threading.Event()
            conf.started_cb.add_callback(lambda lc, ok: started.set())
            conf.start()
            assert started.wait(1.0)
            sim.step_to(0.2)
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)  # unlock
            cf.commander.send_setpoint(2.0, 3.0, 10.0, 40000)
            sim.step_to(0.5)
            fw = sim.firmware
            sp = fw.last_setpoint
            # The firmware stores the wire pitch (cflib negated it) and negates the yaw rate.
            assert (sp.roll, sp.pitch, sp.yaw_rate, sp.thrust) == (2.0, -3.0, -10.0, 40000)
            assert fw.setpoints_received == 2
            for _ in range(100):
                if len(samples) == 5:
                    break
                threading.Event().wait(0.01)
            assert len(samples) == 5
            assert samples[0]["supervisor.info"] == supervisor_bitfield("idle")
            assert samples[-1]["supervisor.info"] == supervisor_bitfield("flying")
            assert samples[-1]["pm.vbat"] == pytest.approx(sim.battery_voltage, abs=0.05)
            assert samples[-1]["pm.vbat"] < samples[0]["pm.vbat"]  # sags under the motors' load
    finally:
        unregister_simulator(uri)


# --- supervisor commands, the power switch, link statistics (the hardware radio's needs) ------


def test_emergency_stop_and_its_watchdog_are_decoded(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    sim.t = 3.0
    cf.supervisor.send_emergency_stop_watchdog()  # port 9 channel 1, protocol >= 12
    sim.t = 3.2
    cf.supervisor.send_emergency_stop()
    sim.t = 3.4
    cf.send_packet(CRTPPacket(0x61, bytes((4,))))  # the legacy localization channel (protocol < 12)
    cf.send_packet(CRTPPacket(0x61, bytes((3,))))
    before = cf.link.unknown_packets
    cf.send_packet(CRTPPacket(0x91, bytes((0x01, 1))))  # arming request: not modelled
    assert sim.firmware.calls == [("heartbeat", 3.0), ("estop", 3.2), ("heartbeat", 3.4), ("estop", 3.4)]
    assert all(sim.firmware.notes)
    assert cf.link.unknown_packets == before + 1


def test_cflib_power_switch_reaches_the_simulated_stm32(sim_uri: tuple[FakeSim, str]) -> None:
    from cflib.utils.power_switch import PowerSwitch

    sim, uri = sim_uri
    sim.t = 7.0
    switch = PowerSwitch(uri)  # cflib appends ?safelink=0&autoping=0&ackfilter=0 to the URI
    try:
        switch.stm_power_down()
        switch.stm_power_up()
        switch.reboot_to_fw()
    finally:
        switch.close()
    assert sim.firmware.calls == [("power_off", 7.0), ("power_on", 7.0), ("power_off", 7.0), ("power_on", 7.0)]


def test_link_options_in_the_uri_are_accepted_and_malformed_ones_not() -> None:
    from cfknode.sim_backend.link_driver import parse_sim_uri

    assert parse_sim_uri("sim://3?safelink=0&autoping=0&ackfilter=0") == "sim://3"
    assert parse_sim_uri(" sim://04/ ") == "sim://4"
    with pytest.raises(SimLinkError, match="malformed"):
        parse_sim_uri("sim://3?bad value")


def test_link_statistics_reach_cflib_callbacks(connected: tuple[FakeSim, Crazyflie]) -> None:
    sim, cf = connected
    quality: list[float] = []
    uplink: list[float] = []
    cf.link_statistics.link_quality_updated.add_callback(quality.append)
    cf.link_statistics.uplink_rate_updated.add_callback(uplink.append)
    for k in range(30):  # 30 setpoints over 0.3 s of sim time: 100 packets/s up
        cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)
        sim.step_to((k + 1) * 0.01)
    assert quality and all(q == 100.0 for q in quality)
    assert uplink and 95.0 <= uplink[-1] <= 135.0  # setpoints plus cflib's own pings (wall clock)


def test_stock_cflib_signs_and_thrust_clamp_on_the_real_simulator() -> None:
    """Acceptance: through cflib and sim://, +pitch is nose down (+x), +roll is right side down
    (-y), +yaw rate turns clockwise, thrust is clamped to 60000 and zeroed below 1000."""
    from cfknode.app.config import load_config
    from cfknode.models.quadrotor import quat_to_euler_zyx
    from cfknode.sim_backend.crazyflie import SimCrazyflie

    sim = SimCrazyflie(load_config().vehicle, load_config().sim)
    uri = f"sim://{next(_uris)}"
    register_simulator(uri, sim)
    try:
        with SyncCrazyflie(uri, cf=Crazyflie()) as scf:
            cf, fw = scf.cf, sim.firmware
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)  # unlock
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 65535)
            assert fw.last_setpoint.thrust == 60000  # RPYT MAX_THRUST
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 999)
            assert fw.last_setpoint.thrust == 0  # below MIN_THRUST
            with pytest.raises(ValueError):
                cf.commander.send_setpoint(0.0, 0.0, 0.0, 70000)  # cflib refuses it before the wire
            for k in range(60):  # climb with +pitch, +roll and +yaw rate for 0.6 s
                cf.commander.send_setpoint(3.0, 3.0, 45.0, 46000)
                sim.step_to((k + 1) * 0.01)
            x, y, z = sim.state[:3]
            vx, vy = sim.state[3:5]
            _, _, yaw = quat_to_euler_zyx(sim.state[6:10])
            assert z > 0.02 and vx > 0.02 and vy < -0.02
            assert yaw < -0.1  # clockwise seen from above
    finally:
        unregister_simulator(uri)
