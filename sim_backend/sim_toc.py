"""The simulated Crazyflie's log and parameter tables of contents, and the TOC/param services.

Each service is a pure function from a request payload to the reply payload (``None`` for a
request the firmware drops), so the link driver only routes packets.
"""

from __future__ import annotations

import errno
import struct
import zlib
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from cfknode.sim_backend.crtp_codes import (
    PARAM_MISC_DEFAULT_V2,
    TOC_INFO,
    TOC_INFO_V2,
    TOC_ITEM_V2,
    pack_clamped,
)

# A simulated link has no path loss; report what a Crazyradio sees a metre or two away.
SIM_RSSI = 35
PM_BATTERY, PM_LOW_POWER = 0, 3  # pm.state values (no charger in flight)

# Type id -> struct format, for each TOC (log and param number their types differently).
LOG_TYPES: dict[int, str] = {0x01: "<B", 0x02: "<H", 0x03: "<L", 0x04: "<b", 0x05: "<h",
                             0x06: "<i", 0x07: "<f", 0x08: "<e"}
PARAM_TYPES: dict[int, str] = {0x00: "<b", 0x01: "<h", 0x02: "<i", 0x03: "<q", 0x05: "<e",
                               0x06: "<f", 0x07: "<d", 0x08: "<B", 0x09: "<H", 0x0A: "<L",
                               0x0B: "<Q"}
_PARAM_READ_ONLY = 0x40


class EndpointView(Protocol):
    """What a log variable reads: the simulator, the power monitor's state and the accelerometer."""

    sim: Any
    pm_state: int

    @property
    def accelerometer(self) -> Any: ...  # sim_backend/accelerometer.py: reading_g() -> (x, y, z) in g


@dataclass(frozen=True)
class LogVariable:
    group: str
    name: str
    type_id: int  # log type id (LOG_TYPES)
    read: Callable[[EndpointView], float]  # value from the simulator (and its power monitor)


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


def _battery_voltage(endpoint: EndpointView) -> float:
    return endpoint.sim.battery_voltage


def _pm_state(endpoint: EndpointView) -> float:
    return endpoint.pm_state


def _supervisor_info(endpoint: EndpointView) -> float:
    return supervisor_bitfield(endpoint.sim.firmware.supervisor_state)


def _rssi(endpoint: EndpointView) -> float:
    return SIM_RSSI


def _acc(axis: int) -> Callable[[EndpointView], float]:
    def read(endpoint: EndpointView) -> float:
        return endpoint.accelerometer.reading_g()[axis]

    return read


# What a flight host logs (Crazyswarm2's status topic: docs/hardware.md#logging), then the
# accelerometer in g, body frame (the firmware's acc group; docs/hardware.md#imu-log).
# New variables go at the end: the ids of the older ones stay put.
LOG_TOC: tuple[LogVariable, ...] = (
    LogVariable("pm", "vbat", 0x07, _battery_voltage),
    LogVariable("pm", "state", 0x04, _pm_state),
    LogVariable("supervisor", "info", 0x02, _supervisor_info),
    LogVariable("radio", "rssi", 0x01, _rssi),
    LogVariable("acc", "x", 0x07, _acc(0)),
    LogVariable("acc", "y", 0x07, _acc(1)),
    LogVariable("acc", "z", 0x07, _acc(2)),
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


LOG_ITEMS = [_toc_item_bytes(v.type_id, v.group, v.name) for v in LOG_TOC]
PARAM_ITEMS = [
    _toc_item_bytes(p.type_id | (_PARAM_READ_ONLY if p.read_only else 0), p.group, p.name)
    for p in PARAM_TOC
]
LOG_CRC = _toc_crc(LOG_ITEMS)
PARAM_CRC = _toc_crc(PARAM_ITEMS)


def param_index(group: str, name: str) -> int:
    return next(i for i, p in enumerate(PARAM_TOC) if (p.group, p.name) == (group, name))


def toc_reply(data: bytearray, items: list[bytes], crc: int) -> bytes | None:
    """Answer a V2 TOC request (16-bit ids): the TOC's size and CRC, or one item."""
    cmd = data[0]
    if cmd == TOC_INFO_V2:
        return TOC_INFO.pack(TOC_INFO_V2, len(items), crc)
    if cmd == TOC_ITEM_V2:
        ident = data[1] | (data[2] << 8)
        if ident >= len(items):
            return None
        return bytes((TOC_ITEM_V2, data[1], data[2])) + items[ident]
    return None


def _param_id(data: bytearray) -> int | None:
    ident = data[0] | (data[1] << 8)
    return ident if ident < len(PARAM_TOC) else None


def param_read_reply(values: list[float], data: bytearray) -> bytes | None:
    ident = _param_id(data)
    if ident is None:
        return None
    fmt = PARAM_TYPES[PARAM_TOC[ident].type_id]
    return bytes((data[0], data[1], 0)) + pack_clamped(fmt, values[ident])


def param_write_reply(values: list[float], data: bytearray) -> bytes | None:
    """Store a written value (in place in ``values``) and echo it as the firmware does."""
    ident = _param_id(data)
    if ident is None or PARAM_TOC[ident].read_only:
        return None
    fmt = PARAM_TYPES[PARAM_TOC[ident].type_id]
    (value,) = struct.unpack(fmt, data[2:])
    values[ident] = value
    return bytes((data[0], data[1])) + pack_clamped(fmt, value)


def param_default_reply(data: bytearray) -> bytes:
    """Answer ``PARAM_MISC_DEFAULT_V2``: the default value, or ENOENT for an unknown id."""
    ident = _param_id(data[1:3])
    if ident is None:
        return bytes((PARAM_MISC_DEFAULT_V2, data[1], data[2], errno.ENOENT))
    definition = PARAM_TOC[ident]
    value = pack_clamped(PARAM_TYPES[definition.type_id], definition.default)
    return bytes((PARAM_MISC_DEFAULT_V2, data[1], data[2], 0)) + value


def set_param_by_name(values: list[float], body: bytearray) -> bool:
    """Apply a set-by-name request (group\\0name\\0type value); False if nothing was set."""
    group_end = body.find(0)
    name_end = body.find(0, group_end + 1)
    fmt = PARAM_TYPES.get(body[name_end + 1]) if 0 <= group_end < name_end else None
    if fmt is None:
        return False
    group = body[:group_end].decode("ascii")
    name = body[group_end + 1:name_end].decode("ascii")
    for ident, definition in enumerate(PARAM_TOC):
        if (definition.group, definition.name) == (group, name) and not definition.read_only:
            (values[ident],) = struct.unpack(fmt, body[name_end + 2:])
            return True
    return False
