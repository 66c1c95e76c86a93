"""CRTP ports, command ids and packet layouts the simulated Crazyflie answers.

The formats follow cflib 0.1.34 and the firmware's CRTP services (docs/hardware.md,
#rpyt-setpoint to #sim-link).
"""

from __future__ import annotations

import struct

SCHEME = "sim://"
PLATFORM_MAGIC = b"Bitcraze Crazyflie"

# CRTP ports
PORT_PARAM = 0x2
PORT_COMMANDER = 0x3
PORT_MEM = 0x4
PORT_LOG = 0x5
PORT_LOCALIZATION = 0x6
PORT_GENERIC = 0x7
PORT_HL = 0x8
PORT_SUPERVISOR = 0x9
PORT_PLATFORM = 0xD
PORT_LINK = 0xF

# Command ids on those ports
TOC_ITEM_V2 = 2
TOC_INFO_V2 = 3
GENERIC_STOP = 0
META_NOTIFY_SETPOINT_STOP = 0
LOC_EMERGENCY_STOP, LOC_EMERGENCY_STOP_WATCHDOG = 3, 4  # legacy (protocol < 12) channel
LOC_EXT_POSE = 8
HL_STOP = 3
PLATFORM_GET_PROTOCOL = 0
MEM_GET_COUNT = 1
SUPERVISOR_GET_BITFIELD = 0x0C
SUPERVISOR_EMERGENCY_STOP, SUPERVISOR_EMERGENCY_STOP_WATCHDOG = 0x03, 0x04
SUPERVISOR_RESPONSE = 0x80
# Link-control channel 3 reaches the nRF51's power switch (cflib PowerSwitch: [0xfe, cmd, ...]).
BOOTLOADER_TARGET_NRF = 0xFE
POWER_ALL_OFF, POWER_SYS_OFF, POWER_SYS_ON = 0x01, 0x02, 0x03
POWER_RESET_INIT, POWER_RESET = 0xFF, 0xF0
LOG_DELETE, LOG_START, LOG_STOP, LOG_RESET = 2, 3, 4, 5
LOG_CREATE_V2, LOG_APPEND_V2 = 6, 7
PARAM_MISC_SET_BY_NAME = 0
PARAM_MISC_DEFAULT_V2 = 8

RPYT = struct.Struct("<fffH")
EXT_POSE = struct.Struct("<Bfffffff")
TOC_INFO = struct.Struct("<BHI")
U16 = struct.Struct("<H")


def header(port: int, channel: int) -> int:
    """The CRTP header byte the driver dispatches on (link bits masked off)."""
    return (port << 4) | channel


def pack_clamped(fmt: str, value: float) -> bytes:
    """Pack as the C cast would, saturating integers instead of raising."""
    if fmt in ("<f", "<e", "<d"):
        return struct.pack(fmt, float(value))
    size = struct.calcsize(fmt)
    if fmt[1].isupper():
        lo, hi = 0, (1 << (8 * size)) - 1
    else:
        lo, hi = -(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1
    return struct.pack(fmt, min(max(int(value), lo), hi))
