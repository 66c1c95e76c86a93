"""cflib link driver for ``sim://N``: the stock cflib stack talks to a simulated Crazyflie.

Every packet cflib sends is decoded here, synchronously in the sender's thread, into
``Firmware`` calls stamped with the simulator's time, so a lockstep flight stays exact.
Replies (handshake, ping echoes, TOC items, log data) go into a queue that cflib's
receive thread drains through ``receive_packet``.

The packet formats follow cflib 0.1.34 and the firmware's CRTP services
(docs/hardware.md, #rpyt-setpoint to #sim-link). cflib instantiates link drivers itself, with no arguments
(``cflib.crtp.get_link_driver``), so the URI -> simulator map has to be module state.
"""

from __future__ import annotations

import errno
import queue
import re
import struct
import threading
import zlib
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import cflib.crtp
from cflib.crtp.crtpdriver import CRTPDriver
from cflib.crtp.crtpstack import CRTPPacket
from cflib.crtp.exceptions import CommunicationException, WrongUriType

SCHEME = "sim://"
PROTOCOL_VERSION = 12  # >= 12: supervisor port and non-legacy generic setpoints (docs/hardware.md#sim-link)
PLATFORM_MAGIC = b"Bitcraze Crazyflie"
# A simulated link has no path loss; report what a Crazyradio sees a metre or two away.
SIM_RSSI = 35

# CRTP ports
_PORT_PARAM = 0x2
_PORT_COMMANDER = 0x3
_PORT_MEM = 0x4
_PORT_LOG = 0x5
_PORT_LOCALIZATION = 0x6
_PORT_GENERIC = 0x7
_PORT_HL = 0x8
_PORT_SUPERVISOR = 0x9
_PORT_PLATFORM = 0xD
_PORT_LINK = 0xF

# Command ids on those ports
_TOC_ITEM_V2 = 2
_TOC_INFO_V2 = 3
_GENERIC_STOP = 0
_META_NOTIFY_SETPOINT_STOP = 0
_LOC_EMERGENCY_STOP, _LOC_EMERGENCY_STOP_WATCHDOG = 3, 4  # legacy (protocol < 12) channel
_LOC_EXT_POSE = 8
_HL_STOP = 3
_PLATFORM_GET_PROTOCOL = 0
_MEM_GET_COUNT = 1
_SUPERVISOR_GET_BITFIELD = 0x0C
_SUPERVISOR_EMERGENCY_STOP, _SUPERVISOR_EMERGENCY_STOP_WATCHDOG = 0x03, 0x04
# Link-control channel 3 reaches the nRF51's power switch (cflib PowerSwitch: [0xfe, cmd, ...]).
_BOOTLOADER_TARGET_NRF = 0xFE
_POWER_ALL_OFF, _POWER_SYS_OFF, _POWER_SYS_ON = 0x01, 0x02, 0x03
_POWER_RESET_INIT, _POWER_RESET = 0xFF, 0xF0
# cflib's radio reports link statistics every 0.1 s (radio_link_statistics.py); so does the sim.
LINK_STATS_PERIOD = 0.1
_SUPERVISOR_RESPONSE = 0x80
_LOG_DELETE, _LOG_START, _LOG_STOP, _LOG_RESET = 2, 3, 4, 5
_LOG_CREATE_V2, _LOG_APPEND_V2 = 6, 7
_PARAM_MISC_SET_BY_NAME = 0
_PARAM_MISC_DEFAULT_V2 = 8

PM_BATTERY, PM_LOW_POWER = 0, 3  # pm.state values (no charger in flight)
PM_LOW_TIMEOUT_S = 5.0  # firmware: sustained low voltage before lowPower (docs/hardware.md#battery)

_LOG_MAX_BLOCKS = 16  # firmware LOG_MAX_BLOCKS
_LOG_MAX_PAYLOAD = 26  # firmware LOG_MAX_LEN

_RPYT = struct.Struct("<fffH")
_EXT_POSE = struct.Struct("<Bfffffff")
_TOC_INFO = struct.Struct("<BHI")
_U16 = struct.Struct("<H")

# Type id -> struct format, for each TOC (log and param number their types differently).
LOG_TYPES: dict[int, str] = {0x01: "<B", 0x02: "<H", 0x03: "<L", 0x04: "<b", 0x05: "<h",
                             0x06: "<i", 0x07: "<f", 0x08: "<e"}
PARAM_TYPES: dict[int, str] = {0x00: "<b", 0x01: "<h", 0x02: "<i", 0x03: "<q", 0x05: "<e",
                               0x06: "<f", 0x07: "<d", 0x08: "<B", 0x09: "<H", 0x0A: "<L",
                               0x0B: "<Q"}
_PARAM_READ_ONLY = 0x40


class SimulatorLike(Protocol):
    """What the driver needs of ``SimCrazyflie``."""

    t: float
    firmware: Any
    lock: threading.RLock
    battery_voltage: float

    def add_step_observer(self, cb: Callable[[float, Any], None]) -> None: ...


class SimLinkError(CommunicationException):
    """A ``sim://`` URI that is malformed or has no simulator registered."""


@dataclass(frozen=True)
class LogVariable:
    group: str
    name: str
    type_id: int  # log type id (LOG_TYPES)
    read: Callable[["_Endpoint"], float]  # value from the simulator (and its power monitor)


@dataclass(frozen=True)
class ParamDefinition:
    group: str
    name: str
    type_id: int  # param type id (PARAM_TYPES)
    default: float
    read_only: bool = False


# Supervisor bits (docs/hardware.md#supervisor): the sim auto-arms like a CF2.1 and has no HL planner state.
_CAN_BE_ARMED, _ARMED, _AUTO_ARM, _CAN_FLY, _FLYING, _LOCKED = 1, 2, 4, 8, 16, 64
_SUPERVISOR_BITS = {
    "idle": _CAN_BE_ARMED | _ARMED | _AUTO_ARM | _CAN_FLY,
    "landed": _CAN_BE_ARMED | _ARMED | _AUTO_ARM | _CAN_FLY,
    "flying": _CAN_BE_ARMED | _ARMED | _AUTO_ARM | _CAN_FLY | _FLYING,
    # Level-out still accepts setpoints (they return it to flying), so it can fly.
    "warning_level_out": _CAN_BE_ARMED | _ARMED | _AUTO_ARM | _CAN_FLY | _FLYING,
    "locked": _AUTO_ARM | _LOCKED,
}


def supervisor_bitfield(state: str) -> int:
    """``supervisor.info`` bits for a ``Firmware.supervisor_state`` string."""
    return _SUPERVISOR_BITS.get(state, _AUTO_ARM)


def _battery_voltage(endpoint: "_Endpoint") -> float:
    return endpoint.sim.battery_voltage


def _pm_state(endpoint: "_Endpoint") -> float:
    return endpoint.pm_state


def _supervisor_info(endpoint: "_Endpoint") -> float:
    return supervisor_bitfield(endpoint.sim.firmware.supervisor_state)


def _rssi(endpoint: "_Endpoint") -> float:
    return SIM_RSSI


# What a flight host logs (Crazyswarm2's status topic: docs/hardware.md#logging).
LOG_TOC: tuple[LogVariable, ...] = (
    LogVariable("pm", "vbat", 0x07, _battery_voltage),
    LogVariable("pm", "state", 0x04, _pm_state),
    LogVariable("supervisor", "info", 0x02, _supervisor_info),
    LogVariable("radio", "rssi", 0x01, _rssi),
)

# Parameters a host sets or reads before flight (docs/hardware.md#extpose, #parameters,
# #battery). The simulated firmware has one estimator and the PID attitude controller, so
# these are stored and echoed only.
PARAM_TOC: tuple[ParamDefinition, ...] = (
    ParamDefinition("stabilizer", "estimator", 0x08, 1),
    ParamDefinition("stabilizer", "controller", 0x08, 1),
    ParamDefinition("locSrv", "extPosStdDev", 0x06, 0.01),
    ParamDefinition("locSrv", "extQuatStdDev", 0x06, 4.5e-3),
    ParamDefinition("pm", "lowVoltage", 0x06, 3.2),
    ParamDefinition("pm", "criticalLowVoltage", 0x06, 3.0),
    ParamDefinition("kalman", "resetEstimation", 0x08, 0),
)


def _toc_item_bytes(type_byte: int, group: str, name: str) -> bytes:
    return bytes((type_byte,)) + group.encode("ascii") + b"\0" + name.encode("ascii") + b"\0"


def _toc_crc(items: list[bytes]) -> int:
    # Derived from the contents, so a cflib rw_cache never serves a stale TOC.
    return zlib.crc32(b"".join(items)) & 0xFFFFFFFF


_LOG_ITEMS = [_toc_item_bytes(v.type_id, v.group, v.name) for v in LOG_TOC]
_PARAM_ITEMS = [
    _toc_item_bytes(p.type_id | (_PARAM_READ_ONLY if p.read_only else 0), p.group, p.name)
    for p in PARAM_TOC
]
_LOG_CRC = _toc_crc(_LOG_ITEMS)


def _param_index(group: str, name: str) -> int:
    return next(i for i, p in enumerate(PARAM_TOC) if (p.group, p.name) == (group, name))


_PARAM_CRC = _toc_crc(_PARAM_ITEMS)


def _pack_clamped(fmt: str, value: float) -> bytes:
    """Pack as the C cast would, saturating integers instead of raising."""
    if fmt in ("<f", "<e", "<d"):
        return struct.pack(fmt, float(value))
    size = struct.calcsize(fmt)
    if fmt[1].isupper():
        lo, hi = 0, (1 << (8 * size)) - 1
    else:
        lo, hi = -(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1
    return struct.pack(fmt, min(max(int(value), lo), hi))


def parse_sim_uri(uri: str) -> str:
    """Canonical ``sim://N``; raises ``SimLinkError`` if ``uri`` is a malformed sim URI.

    Link options after ``?`` (cflib's ``PowerSwitch`` appends ``?safelink=0&...``) are ignored:
    the simulated link has no packet loss to protect against."""
    m = re.fullmatch(r"sim://(\d+)/?(\?[\w=&.-]*)?", uri.strip())
    if m is None:
        raise SimLinkError(f"malformed simulator URI {uri!r}: expected sim://N with N an integer")
    return f"{SCHEME}{int(m.group(1))}"


class _Endpoint:
    """One registered simulator: its parameters, power state and the links attached to it."""

    def __init__(self, uri: str, sim: SimulatorLike) -> None:
        self.uri = uri
        self.sim = sim
        self.param_values: list[float] = [p.default for p in PARAM_TOC]
        self.pm_state = PM_BATTERY
        self.drivers: tuple[SimLinkDriver, ...] = ()  # replaced whole: read lock-free per step
        self._low_since: float | None = None
        self._low_voltage_index = _param_index("pm", "lowVoltage")
        self._lock = threading.Lock()
        self.active = True  # cleared on unregister (a step observer cannot be removed)
        # Observed from registration on: pm.state needs the voltage history, logs need sim time.
        sim.add_step_observer(self._on_step)

    def attach(self, driver: "SimLinkDriver") -> None:
        with self._lock:
            self.drivers = self.drivers + (driver,)

    def detach(self, driver: "SimLinkDriver") -> None:
        with self._lock:
            self.drivers = tuple(d for d in self.drivers if d is not driver)

    def _on_step(self, t: float, state: Any) -> None:
        if not self.active:
            return
        # Firmware pm task: below pm.lowVoltage for PM_LOW_TIMEOUT_S -> lowPower (docs/hardware.md#battery).
        if self.sim.battery_voltage < self.param_values[self._low_voltage_index]:
            if self._low_since is None:
                self._low_since = t
            if t - self._low_since >= PM_LOW_TIMEOUT_S:
                self.pm_state = PM_LOW_POWER
        else:
            self._low_since = None
            self.pm_state = PM_BATTERY
        for driver in self.drivers:
            driver._on_sim_step(t)


_registry: dict[str, _Endpoint] = {}
_registry_lock = threading.Lock()


def _install_driver() -> None:
    """Make cflib try ``SimLinkDriver`` first, with its own drivers behind it."""
    classes = cflib.crtp.CLASSES
    if not any(c is not SimLinkDriver for c in classes):
        cflib.crtp.init_drivers()
    if SimLinkDriver not in classes:
        classes.insert(0, SimLinkDriver)


def register_simulator(uri: str, sim: SimulatorLike) -> None:
    """Serve ``sim`` at ``uri`` (``sim://N``) to any cflib ``Crazyflie`` in this process."""
    key = parse_sim_uri(uri)
    with _registry_lock:
        _install_driver()
        old = _registry.get(key)
        if old is not None and old.sim is not sim:
            raise SimLinkError(f"{key} is already registered to another simulator; unregister it first")
        if old is None:
            _registry[key] = _Endpoint(key, sim)


def unregister_simulator(uri: str) -> None:
    """Stop serving ``uri``; open links to it are reported lost to cflib."""
    key = parse_sim_uri(uri)
    with _registry_lock:
        endpoint = _registry.pop(key, None)
    if endpoint is not None:
        endpoint.active = False
        for driver in endpoint.drivers:
            driver._lose_link(f"simulator {key} was unregistered")


def registered_uris() -> list[str]:
    with _registry_lock:
        return sorted(_registry)


class _LogBlock:
    """A log block as the firmware keeps it: variables, fetch types, period, next emission."""

    __slots__ = ("block_id", "entries", "period_s", "next_t", "started")

    def __init__(self, block_id: int) -> None:
        self.block_id = block_id
        self.entries: list[tuple[LogVariable, str]] = []  # (variable, fetch format)
        self.period_s = 0.0
        self.next_t = 0.0
        self.started = False

    def payload_size(self) -> int:
        return sum(struct.calcsize(fmt) for _, fmt in self.entries)


class SimLinkDriver(CRTPDriver):
    """``CRTPDriver`` for ``sim://N``: decodes commander traffic into ``Firmware`` calls."""

    def __init__(self) -> None:
        super().__init__()
        self.needs_resending = False  # in-process link: nothing is ever lost
        self.uri = ""
        self.packets_from_host = 0
        self.packets_to_host = 0
        self.setpoints = 0
        self.extposes = 0
        self.unknown_packets = 0
        self._endpoint: _Endpoint | None = None
        self._sim: SimulatorLike | None = None
        self._incoming: queue.SimpleQueue[CRTPPacket | None] = queue.SimpleQueue()
        self._closed = True
        self._link_error_cb: Callable[[str], None] | None = None
        self._link_stats_cb: Callable[[dict[str, float]], None] | None = None
        self._stats_next_t = 0.0
        self._stats_up = 0
        self._stats_down = 0
        self.power_commands = 0
        self._log_lock = threading.Lock()
        self._log_blocks: dict[int, _LogBlock] = {}
        self._logging = False  # any block started: the per-step check is this one flag
        self._handlers: dict[int, Callable[[bytearray], None]] = {
            (_PORT_COMMANDER << 4) | 0: self._on_rpyt,
            (_PORT_GENERIC << 4) | 0: self._on_generic_setpoint,
            (_PORT_GENERIC << 4) | 1: self._on_generic_meta,
            (_PORT_LOCALIZATION << 4) | 1: self._on_localization,
            (_PORT_HL << 4) | 0: self._on_high_level,
            (_PORT_LINK << 4) | 0: self._on_ping,
            (_PORT_LINK << 4) | 1: self._on_link_source,
            (_PORT_PLATFORM << 4) | 1: self._on_platform_version,
            (_PORT_MEM << 4) | 0: self._on_mem_info,
            (_PORT_LOG << 4) | 0: self._on_log_toc,
            (_PORT_LOG << 4) | 1: self._on_log_settings,
            (_PORT_PARAM << 4) | 0: self._on_param_toc,
            (_PORT_PARAM << 4) | 1: self._on_param_read,
            (_PORT_PARAM << 4) | 2: self._on_param_write,
            (_PORT_PARAM << 4) | 3: self._on_param_misc,
            (_PORT_SUPERVISOR << 4) | 0: self._on_supervisor_info,
            (_PORT_SUPERVISOR << 4) | 1: self._on_supervisor_command,
            (_PORT_LINK << 4) | 3: self._on_power_switch,
        }

    # --- CRTPDriver interface -------------------------------------------------------------

    def connect(self, uri: str, radio_link_statistics_callback: Any, link_error_callback: Any) -> None:
        if not isinstance(uri, str) or not uri.startswith(SCHEME):
            raise WrongUriType(f"not a simulator URI: {uri!r}")
        key = parse_sim_uri(uri)
        with _registry_lock:
            endpoint = _registry.get(key)
            known = sorted(_registry)
        if endpoint is None:
            raise SimLinkError(
                f"no simulator registered at {key} (registered: {', '.join(known) or 'none'}); "
                "call cfknode.sim_backend.link_driver.register_simulator(uri, sim) first"
            )
        self.uri = key
        self._endpoint = endpoint
        self._sim = endpoint.sim
        self._link_error_cb = link_error_callback
        self._link_stats_cb = radio_link_statistics_callback
        self._stats_next_t = endpoint.sim.t + LINK_STATS_PERIOD
        self._stats_up = self._stats_down = 0
        self._closed = False
        endpoint.attach(self)

    def send_packet(self, pk: CRTPPacket) -> None:
        if self._closed:
            return
        self.packets_from_host += 1
        handler = self._handlers.get(pk.header & 0xF3)
        if handler is None:
            self.unknown_packets += 1
            return
        try:
            handler(pk.data)
        except (struct.error, IndexError, UnicodeDecodeError):
            # A short or garbled packet is dropped and counted, as the firmware drops it.
            self.unknown_packets += 1

    def receive_packet(self, wait: float = 0) -> CRTPPacket | None:
        if self._closed:
            return None
        try:
            if wait == 0:
                pk = self._incoming.get(block=False)
            elif wait < 0:
                pk = self._incoming.get()
            else:
                pk = self._incoming.get(timeout=wait)
        except queue.Empty:
            return None
        return pk  # None is the wake-up put by close()

    def get_status(self) -> str:
        return "closed" if self._closed else f"simulated link to {self.uri}"

    def get_name(self) -> str:
        return "sim"

    def scan_interface(self, address: Any = None) -> list[list[str]]:
        return [[uri, "simulated Crazyflie"] for uri in registered_uris()]

    def enum(self) -> list[list[str]]:
        return self.scan_interface()

    def get_help(self) -> str:
        return "sim://N : a SimCrazyflie registered with register_simulator(uri, sim)"

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._log_lock:
            self._logging = False
            self._log_blocks.clear()
        if self._endpoint is not None:
            self._endpoint.detach(self)
        self._incoming.put(None)  # wake a reader blocked in receive_packet

    # --- helpers ---------------------------------------------------------------------------

    def _reply(self, port: int, channel: int, data: bytes | bytearray) -> None:
        self.packets_to_host += 1
        self._incoming.put(CRTPPacket((port << 4) | channel, data))

    def _lose_link(self, message: str) -> None:
        cb = self._link_error_cb
        self.close()
        if cb is not None:
            cb(message)

    # --- commander traffic -> firmware -------------------------------------------------------

    def _on_rpyt(self, data: bytearray) -> None:
        roll, pitch, yawrate, thrust = _RPYT.unpack(data)
        sim = self._sim
        with sim.lock:
            sim.firmware.on_rpyt(sim.t, roll, pitch, yawrate, thrust)
        self.setpoints += 1

    def _on_generic_setpoint(self, data: bytearray) -> None:
        if data[0] != _GENERIC_STOP:
            self.unknown_packets += 1  # other generic setpoints need a position controller
            return
        sim = self._sim
        with sim.lock:
            sim.firmware.on_stop(sim.t)
        self.setpoints += 1

    def _on_generic_meta(self, data: bytearray) -> None:
        if data[0] != _META_NOTIFY_SETPOINT_STOP:
            self.unknown_packets += 1
            return
        sim = self._sim
        with sim.lock:
            sim.firmware.on_notify_setpoint_stop(sim.t)

    def _on_localization(self, data: bytearray) -> None:
        if data[0] in (_LOC_EMERGENCY_STOP, _LOC_EMERGENCY_STOP_WATCHDOG):
            self._emergency_stop(data[0] == _LOC_EMERGENCY_STOP_WATCHDOG)
            return
        if data[0] != _LOC_EXT_POSE:
            self.unknown_packets += 1
            return
        _, x, y, z, qx, qy, qz, qw = _EXT_POSE.unpack(data)
        sim = self._sim
        with sim.lock:
            sim.firmware.on_extpose(sim.t, (x, y, z), (qx, qy, qz, qw))
        self.extposes += 1

    def _emergency_stop(self, watchdog: bool) -> None:
        sim = self._sim
        with sim.lock:
            if watchdog:
                sim.firmware.on_emergency_stop_watchdog(sim.t)
            else:
                sim.firmware.on_emergency_stop(sim.t)

    def _on_supervisor_command(self, data: bytearray) -> None:
        cmd = data[0]
        if cmd not in (_SUPERVISOR_EMERGENCY_STOP, _SUPERVISOR_EMERGENCY_STOP_WATCHDOG):
            self.unknown_packets += 1  # arming and crash recovery are not modelled
            return
        self._emergency_stop(cmd == _SUPERVISOR_EMERGENCY_STOP_WATCHDOG)

    def _on_power_switch(self, data: bytearray) -> None:
        """The nRF51's power commands: switch the simulated STM32 off, on, or reboot it."""
        if data[0] != _BOOTLOADER_TARGET_NRF:
            self.unknown_packets += 1  # bootloader traffic for the STM32 itself
            return
        cmd = data[1]
        sim = self._sim
        with sim.lock:
            firmware = sim.firmware
            if cmd in (_POWER_ALL_OFF, _POWER_SYS_OFF):
                firmware.power_off(sim.t)
            elif cmd == _POWER_SYS_ON:
                firmware.power_on(sim.t)
            elif cmd == _POWER_RESET and len(data) > 2 and data[2] == 1:  # reboot to firmware
                firmware.power_off(sim.t)
                firmware.power_on(sim.t)
            elif cmd != _POWER_RESET_INIT:
                self.unknown_packets += 1
                return
        self.power_commands += 1
        # The nRF acknowledges; PowerSwitch waits for any reply before it moves on.
        self._reply(_PORT_LINK, 3, bytes((_BOOTLOADER_TARGET_NRF, cmd)))

    def _on_high_level(self, data: bytearray) -> None:
        if data[0] != _HL_STOP:
            self.unknown_packets += 1  # takeoff/land/go_to need the onboard planner
            return
        sim = self._sim
        with sim.lock:
            sim.firmware.on_hl_stop(sim.t)

    # --- connection handshake ----------------------------------------------------------------

    def _on_ping(self, data: bytearray) -> None:
        self._reply(_PORT_LINK, 0, bytes(data))

    def _on_link_source(self, data: bytearray) -> None:
        self._reply(_PORT_LINK, 1, PLATFORM_MAGIC)

    def _on_platform_version(self, data: bytearray) -> None:
        if data[0] != _PLATFORM_GET_PROTOCOL:
            self.unknown_packets += 1
            return
        self._reply(_PORT_PLATFORM, 1, bytes((_PLATFORM_GET_PROTOCOL, PROTOCOL_VERSION)))

    def _on_mem_info(self, data: bytearray) -> None:
        if data[0] != _MEM_GET_COUNT:
            self.unknown_packets += 1
            return
        self._reply(_PORT_MEM, 0, bytes((_MEM_GET_COUNT, 0)))  # no memories

    def _on_supervisor_info(self, data: bytearray) -> None:
        if data[0] != _SUPERVISOR_GET_BITFIELD:
            self.unknown_packets += 1  # arming / emergency stop are not modelled
            return
        sim = self._sim
        with sim.lock:
            bits = supervisor_bitfield(sim.firmware.supervisor_state)
        self._reply(_PORT_SUPERVISOR, 0, bytes((_SUPERVISOR_GET_BITFIELD | _SUPERVISOR_RESPONSE,)) + _U16.pack(bits))

    # --- TOCs (V2 protocol: 16-bit ids) --------------------------------------------------

    def _serve_toc(self, port: int, data: bytearray, items: list[bytes], crc: int) -> None:
        cmd = data[0]
        if cmd == _TOC_INFO_V2:
            self._reply(port, 0, _TOC_INFO.pack(_TOC_INFO_V2, len(items), crc))
        elif cmd == _TOC_ITEM_V2:
            ident = data[1] | (data[2] << 8)
            if ident >= len(items):
                self.unknown_packets += 1
                return
            self._reply(port, 0, bytes((_TOC_ITEM_V2, data[1], data[2])) + items[ident])
        else:
            self.unknown_packets += 1

    def _on_log_toc(self, data: bytearray) -> None:
        self._serve_toc(_PORT_LOG, data, _LOG_ITEMS, _LOG_CRC)

    def _on_param_toc(self, data: bytearray) -> None:
        self._serve_toc(_PORT_PARAM, data, _PARAM_ITEMS, _PARAM_CRC)

    # --- logging -----------------------------------------------------------------------------

    def _on_log_settings(self, data: bytearray) -> None:
        cmd = data[0]
        if cmd == _LOG_RESET:
            with self._log_lock:
                self._log_blocks.clear()
                self._logging = False
            self._reply(_PORT_LOG, 1, bytes((_LOG_RESET, 0, 0)))
            return
        block_id = data[1]
        with self._log_lock:
            if cmd in (_LOG_CREATE_V2, _LOG_APPEND_V2):
                status = self._add_to_block(cmd, block_id, data[2:])
            elif cmd == _LOG_START:
                status = self._start_block(block_id, data[2])
            elif cmd == _LOG_STOP:
                block = self._log_blocks.get(block_id)
                status = errno.ENOENT if block is None else 0
                if block is not None:
                    block.started = False
            elif cmd == _LOG_DELETE:
                status = errno.ENOENT if self._log_blocks.pop(block_id, None) is None else 0
            else:
                self.unknown_packets += 1
                return
            self._logging = any(b.started for b in self._log_blocks.values())
        self._reply(_PORT_LOG, 1, bytes((cmd, block_id, status)))

    def _add_to_block(self, cmd: int, block_id: int, spec: bytearray) -> int:
        if cmd == _LOG_CREATE_V2:
            if block_id in self._log_blocks:
                return errno.EEXIST
            if len(self._log_blocks) >= _LOG_MAX_BLOCKS:
                return errno.ENOMEM
            block = _LogBlock(block_id)
        else:
            block = self._log_blocks.get(block_id)
            if block is None:
                return errno.ENOENT
        if len(spec) % 3 != 0:
            return errno.ENOEXEC  # raw memory addresses: the sim has no memory map
        entries = list(block.entries)
        for i in range(0, len(spec), 3):
            type_byte, ident = spec[i], spec[i + 1] | (spec[i + 2] << 8)
            fetch = LOG_TYPES.get(type_byte & 0x0F)
            if ident >= len(LOG_TOC) or fetch is None:
                return errno.ENOENT
            entries.append((LOG_TOC[ident], fetch))
        block.entries = entries
        if block.payload_size() > _LOG_MAX_PAYLOAD:
            return errno.E2BIG
        self._log_blocks[block_id] = block
        return 0

    def _start_block(self, block_id: int, period_10ms: int) -> int:
        block = self._log_blocks.get(block_id)
        if block is None:
            return errno.ENOENT
        block.period_s = max(period_10ms, 1) * 0.01
        block.next_t = self._sim.t + block.period_s
        block.started = True
        return 0

    def _on_sim_step(self, t: float) -> None:
        """Called after every simulator step: link statistics and log blocks that are due."""
        if t >= self._stats_next_t - 1e-9:
            self._report_link_statistics(t)
        if self._logging:
            self._emit_logs(t)

    def _report_link_statistics(self, t: float) -> None:
        """What cflib's radio driver reports (radio_link_statistics.py), for a lossless link.

        Rates are packets per second of simulated time in each direction; a link with no
        retries has link quality 100 (cflib: mean of 10 - retries, times 10).
        """
        up, down = self.packets_from_host, self.packets_to_host
        period = LINK_STATS_PERIOD + (t - self._stats_next_t)
        stats = {
            "link_quality": 100.0,
            "uplink_rate": (up - self._stats_up) / period,
            "downlink_rate": (down - self._stats_down) / period,
        }
        self._stats_up, self._stats_down = up, down
        self._stats_next_t = t + LINK_STATS_PERIOD
        cb = self._link_stats_cb
        if cb is not None and not self._closed:
            cb(stats)

    def _emit_logs(self, t: float) -> None:
        """Send each started log block that is due."""
        with self._log_lock:
            endpoint = self._endpoint
            stamp = int(round(t * 1000.0)) & 0xFFFFFF
            for block in self._log_blocks.values():
                if not block.started or t < block.next_t - 1e-9:
                    continue
                block.next_t += block.period_s
                if block.next_t <= t:  # fell behind (e.g. started long ago): resync, no burst
                    block.next_t = t + block.period_s
                payload = bytearray((block.block_id, stamp & 0xFF, (stamp >> 8) & 0xFF, stamp >> 16))
                for var, fmt in block.entries:
                    payload += _pack_clamped(fmt, var.read(endpoint))
                self._reply(_PORT_LOG, 2, payload)

    # --- parameters ----------------------------------------------------------------------------

    def _param_id(self, data: bytearray) -> int | None:
        ident = data[0] | (data[1] << 8)
        return ident if ident < len(PARAM_TOC) else None

    def _on_param_read(self, data: bytearray) -> None:
        ident = self._param_id(data)
        if ident is None:
            self.unknown_packets += 1
            return
        fmt = PARAM_TYPES[PARAM_TOC[ident].type_id]
        value = self._endpoint.param_values[ident]
        self._reply(_PORT_PARAM, 1, bytes((data[0], data[1], 0)) + _pack_clamped(fmt, value))

    def _on_param_write(self, data: bytearray) -> None:
        ident = self._param_id(data)
        if ident is None or PARAM_TOC[ident].read_only:
            self.unknown_packets += 1
            return
        fmt = PARAM_TYPES[PARAM_TOC[ident].type_id]
        (value,) = struct.unpack(fmt, data[2:])
        self._endpoint.param_values[ident] = value
        self._reply(_PORT_PARAM, 2, bytes((data[0], data[1])) + _pack_clamped(fmt, value))

    def _on_param_misc(self, data: bytearray) -> None:
        cmd = data[0]
        if cmd == _PARAM_MISC_DEFAULT_V2:
            ident = self._param_id(data[1:3])
            if ident is None:
                self._reply(_PORT_PARAM, 3, bytes((cmd, data[1], data[2], errno.ENOENT)))
                return
            definition = PARAM_TOC[ident]
            value = _pack_clamped(PARAM_TYPES[definition.type_id], definition.default)
            self._reply(_PORT_PARAM, 3, bytes((cmd, data[1], data[2], 0)) + value)
        elif cmd == _PARAM_MISC_SET_BY_NAME:
            self._set_param_by_name(data[1:])
        else:
            self.unknown_packets += 1  # persistent storage is not modelled

    def _set_param_by_name(self, body: bytearray) -> None:
        group_end = body.find(0)
        name_end = body.find(0, group_end + 1)
        fmt = PARAM_TYPES.get(body[name_end + 1]) if 0 <= group_end < name_end else None
        if fmt is not None:
            group = body[:group_end].decode("ascii")
            name = body[group_end + 1:name_end].decode("ascii")
            for ident, definition in enumerate(PARAM_TOC):
                if (definition.group, definition.name) == (group, name) and not definition.read_only:
                    (self._endpoint.param_values[ident],) = struct.unpack(fmt, body[name_end + 2:])
                    return
        self.unknown_packets += 1
