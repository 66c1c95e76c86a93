"""cflib link driver for ``sim://N``: the stock cflib stack talks to a simulated Crazyflie.

Every packet cflib sends is decoded here, synchronously in the sender's thread, into
``Firmware`` calls stamped with the simulator's time, so a lockstep flight stays exact.
Replies (handshake, ping echoes, TOC items, log data) go into a queue that cflib's
receive thread drains through ``receive_packet``.

The packet layouts are in ``crtp_codes``, the log/param tables and their services in
``sim_toc`` and ``sim_log_blocks``, the URI registry in ``sim_endpoint``.
"""

from __future__ import annotations

import queue
import struct
import threading
from typing import Any, Callable

import cflib.crtp
from cflib.crtp.crtpdriver import CRTPDriver
from cflib.crtp.crtpstack import CRTPPacket
from cflib.crtp.exceptions import WrongUriType

from cfknode.sim_backend.crtp_codes import (
    BOOTLOADER_TARGET_NRF,
    EXT_POSE,
    GENERIC_STOP,
    HL_STOP,
    LOC_EMERGENCY_STOP,
    LOC_EMERGENCY_STOP_WATCHDOG,
    LOC_EXT_POSE,
    MEM_GET_COUNT,
    META_NOTIFY_SETPOINT_STOP,
    PARAM_MISC_DEFAULT_V2,
    PARAM_MISC_SET_BY_NAME,
    PLATFORM_GET_PROTOCOL,
    PLATFORM_MAGIC,
    PORT_COMMANDER,
    PORT_GENERIC,
    PORT_HL,
    PORT_LINK,
    PORT_LOCALIZATION,
    PORT_LOG,
    PORT_MEM,
    PORT_PARAM,
    PORT_PLATFORM,
    PORT_SUPERVISOR,
    POWER_ALL_OFF,
    POWER_RESET,
    POWER_RESET_INIT,
    POWER_SYS_OFF,
    POWER_SYS_ON,
    RPYT,
    SCHEME,
    SUPERVISOR_EMERGENCY_STOP,
    SUPERVISOR_EMERGENCY_STOP_WATCHDOG,
    SUPERVISOR_GET_BITFIELD,
    SUPERVISOR_RESPONSE,
    U16,
    header,
)
from cfknode.sim_backend.sim_endpoint import (  # noqa: F401  (re-exported: the driver's public surface)
    PM_LOW_TIMEOUT_S,
    SimLinkError,
    SimulatorLike,
    _Endpoint,
    _registry,
    add_endpoint,
    lookup,
    parse_sim_uri,
    registered_uris,
    remove_endpoint,
)
from cfknode.sim_backend.sim_log_blocks import LogBlocks
from cfknode.sim_backend.sim_toc import (  # noqa: F401  (re-exported)
    LOG_CRC,
    LOG_ITEMS,
    LOG_TOC,
    LOG_TYPES,
    PARAM_CRC,
    PARAM_ITEMS,
    PARAM_TOC,
    PARAM_TYPES,
    PM_BATTERY,
    PM_LOW_POWER,
    SIM_RSSI,
    LogVariable,
    ParamDefinition,
    param_default_reply,
    param_read_reply,
    param_write_reply,
    set_param_by_name,
    supervisor_bitfield,
    toc_reply,
)

PROTOCOL_VERSION = 12  # >= 12: supervisor port and non-legacy generic setpoints (docs/hardware.md#sim-link)
# cflib's radio reports link statistics every 0.1 s (radio_link_statistics.py); so does the sim.
LINK_STATS_PERIOD = 0.1

_install_lock = threading.Lock()


def _install_driver() -> None:
    """Make cflib try ``SimLinkDriver`` first, with its own drivers behind it."""
    with _install_lock:
        classes = cflib.crtp.CLASSES
        if not any(c is not SimLinkDriver for c in classes):
            cflib.crtp.init_drivers()
        if SimLinkDriver not in classes:
            classes.insert(0, SimLinkDriver)


def register_simulator(uri: str, sim: SimulatorLike) -> None:
    """Serve ``sim`` at ``uri`` (``sim://N``) to any cflib ``Crazyflie`` in this process."""
    parse_sim_uri(uri)  # a malformed URI changes nothing
    _install_driver()
    add_endpoint(uri, sim)


def unregister_simulator(uri: str) -> None:
    """Stop serving ``uri``; open links to it are reported lost to cflib."""
    remove_endpoint(uri)


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
        self.power_commands = 0
        self._endpoint: _Endpoint | None = None
        self._sim: SimulatorLike | None = None
        self._incoming: queue.SimpleQueue[CRTPPacket | None] = queue.SimpleQueue()
        self._closed = True
        self._link_error_cb: Callable[[str], None] | None = None
        self._link_stats_cb: Callable[[dict[str, float]], None] | None = None
        self._stats_next_t = 0.0
        self._stats_up = 0
        self._stats_down = 0
        self._logs = LogBlocks()
        self._handlers: dict[int, Callable[[bytearray], None]] = {
            header(PORT_COMMANDER, 0): self._on_rpyt,
            header(PORT_GENERIC, 0): self._on_generic_setpoint,
            header(PORT_GENERIC, 1): self._on_generic_meta,
            header(PORT_LOCALIZATION, 1): self._on_localization,
            header(PORT_HL, 0): self._on_high_level,
            header(PORT_LINK, 0): self._on_ping,
            header(PORT_LINK, 1): self._on_link_source,
            header(PORT_PLATFORM, 1): self._on_platform_version,
            header(PORT_MEM, 0): self._on_mem_info,
            header(PORT_LOG, 0): self._on_log_toc,
            header(PORT_LOG, 1): self._on_log_settings,
            header(PORT_PARAM, 0): self._on_param_toc,
            header(PORT_PARAM, 1): self._on_param_read,
            header(PORT_PARAM, 2): self._on_param_write,
            header(PORT_PARAM, 3): self._on_param_misc,
            header(PORT_SUPERVISOR, 0): self._on_supervisor_info,
            header(PORT_SUPERVISOR, 1): self._on_supervisor_command,
            header(PORT_LINK, 3): self._on_power_switch,
        }

    # --- CRTPDriver interface -------------------------------------------------------------

    def connect(self, uri: str, radio_link_statistics_callback: Any, link_error_callback: Any) -> None:
        if not isinstance(uri, str) or not uri.startswith(SCHEME):
            raise WrongUriType(f"not a simulator URI: {uri!r}")
        endpoint = lookup(uri)
        self.uri = endpoint.uri
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
        self._logs.clear()
        if self._endpoint is not None:
            self._endpoint.detach(self)
        self._incoming.put(None)  # wake a reader blocked in receive_packet

    # --- helpers ---------------------------------------------------------------------------

    def _reply(self, port: int, channel: int, data: bytes | bytearray) -> None:
        self.packets_to_host += 1
        self._incoming.put(CRTPPacket(header(port, channel), data))

    def _reply_or_drop(self, port: int, channel: int, data: bytes | None) -> None:
        if data is None:
            self.unknown_packets += 1  # the firmware drops a request it cannot answer
        else:
            self._reply(port, channel, data)

    def _lose_link(self, message: str) -> None:
        cb = self._link_error_cb
        self.close()
        if cb is not None:
            cb(message)

    def _firmware_call(self, name: str, *args: Any) -> None:
        """Call ``Firmware.<name>(t, *args)`` at simulator time, under the simulator's lock."""
        sim = self._sim
        with sim.lock:
            getattr(sim.firmware, name)(sim.t, *args)

    # --- commander traffic -> firmware -------------------------------------------------------

    def _on_rpyt(self, data: bytearray) -> None:
        self._firmware_call("on_rpyt", *RPYT.unpack(data))
        self.setpoints += 1

    def _on_generic_setpoint(self, data: bytearray) -> None:
        if data[0] != GENERIC_STOP:
            self.unknown_packets += 1  # other generic setpoints need a position controller
            return
        self._firmware_call("on_stop")
        self.setpoints += 1

    def _on_generic_meta(self, data: bytearray) -> None:
        if data[0] != META_NOTIFY_SETPOINT_STOP:
            self.unknown_packets += 1
            return
        self._firmware_call("on_notify_setpoint_stop")

    def _on_localization(self, data: bytearray) -> None:
        if data[0] in (LOC_EMERGENCY_STOP, LOC_EMERGENCY_STOP_WATCHDOG):
            self._emergency_stop(data[0] == LOC_EMERGENCY_STOP_WATCHDOG)
            return
        if data[0] != LOC_EXT_POSE:
            self.unknown_packets += 1
            return
        _, x, y, z, qx, qy, qz, qw = EXT_POSE.unpack(data)
        self._firmware_call("on_extpose", (x, y, z), (qx, qy, qz, qw))
        self.extposes += 1

    def _emergency_stop(self, watchdog: bool) -> None:
        self._firmware_call("on_emergency_stop_watchdog" if watchdog else "on_emergency_stop")

    def _on_supervisor_command(self, data: bytearray) -> None:
        cmd = data[0]
        if cmd not in (SUPERVISOR_EMERGENCY_STOP, SUPERVISOR_EMERGENCY_STOP_WATCHDOG):
            self.unknown_packets += 1  # arming and crash recovery are not modelled
            return
        self._emergency_stop(cmd == SUPERVISOR_EMERGENCY_STOP_WATCHDOG)

    def _on_power_switch(self, data: bytearray) -> None:
        """The nRF51's power commands: switch the simulated STM32 off, on, or reboot it."""
        if data[0] != BOOTLOADER_TARGET_NRF:
            self.unknown_packets += 1  # bootloader traffic for the STM32 itself
            return
        cmd = data[1]
        sim = self._sim
        with sim.lock:
            firmware = sim.firmware
            if cmd in (POWER_ALL_OFF, POWER_SYS_OFF):
                firmware.power_off(sim.t)
            elif cmd == POWER_SYS_ON:
                firmware.power_on(sim.t)
            elif cmd == POWER_RESET and len(data) > 2 and data[2] == 1:  # reboot to firmware
                firmware.power_off(sim.t)
                firmware.power_on(sim.t)
            elif cmd != POWER_RESET_INIT:
                self.unknown_packets += 1
                return
        self.power_commands += 1
        # The nRF acknowledges; PowerSwitch waits for any reply before it moves on.
        self._reply(PORT_LINK, 3, bytes((BOOTLOADER_TARGET_NRF, cmd)))

    def _on_high_level(self, data: bytearray) -> None:
        if data[0] != HL_STOP:
            self.unknown_packets += 1  # takeoff/land/go_to need the onboard planner
            return
        self._firmware_call("on_hl_stop")

    # --- connection handshake ----------------------------------------------------------------

    def _on_ping(self, data: bytearray) -> None:
        self._reply(PORT_LINK, 0, bytes(data))

    def _on_link_source(self, data: bytearray) -> None:
        self._reply(PORT_LINK, 1, PLATFORM_MAGIC)

    def _on_platform_version(self, data: bytearray) -> None:
        if data[0] != PLATFORM_GET_PROTOCOL:
            self.unknown_packets += 1
            return
        self._reply(PORT_PLATFORM, 1, bytes((PLATFORM_GET_PROTOCOL, PROTOCOL_VERSION)))

    def _on_mem_info(self, data: bytearray) -> None:
        if data[0] != MEM_GET_COUNT:
            self.unknown_packets += 1
            return
        self._reply(PORT_MEM, 0, bytes((MEM_GET_COUNT, 0)))  # no memories

    def _on_supervisor_info(self, data: bytearray) -> None:
        if data[0] != SUPERVISOR_GET_BITFIELD:
            self.unknown_packets += 1  # arming / emergency stop are not modelled
            return
        sim = self._sim
        with sim.lock:
            bits = supervisor_bitfield(sim.firmware.supervisor_state)
        self._reply(PORT_SUPERVISOR, 0, bytes((SUPERVISOR_GET_BITFIELD | SUPERVISOR_RESPONSE,)) + U16.pack(bits))

    # --- TOCs, logging, parameters (services in sim_toc / sim_log_blocks) ---------------------

    def _on_log_toc(self, data: bytearray) -> None:
        self._reply_or_drop(PORT_LOG, 0, toc_reply(data, LOG_ITEMS, LOG_CRC))

    def _on_param_toc(self, data: bytearray) -> None:
        self._reply_or_drop(PORT_PARAM, 0, toc_reply(data, PARAM_ITEMS, PARAM_CRC))

    def _on_log_settings(self, data: bytearray) -> None:
        self._reply_or_drop(PORT_LOG, 1, self._logs.settings_reply(data, self._sim.t))

    def _on_param_read(self, data: bytearray) -> None:
        self._reply_or_drop(PORT_PARAM, 1, param_read_reply(self._endpoint.param_values, data))

    def _on_param_write(self, data: bytearray) -> None:
        self._reply_or_drop(PORT_PARAM, 2, param_write_reply(self._endpoint.param_values, data))

    def _on_param_misc(self, data: bytearray) -> None:
        cmd = data[0]
        if cmd == PARAM_MISC_DEFAULT_V2:
            self._reply(PORT_PARAM, 3, param_default_reply(data))
        elif cmd != PARAM_MISC_SET_BY_NAME or not set_param_by_name(self._endpoint.param_values, data[1:]):
            self.unknown_packets += 1  # persistent storage is not modelled

    def log_payloads_emitted(self, block_id: int) -> int:
        """Log-data packets block ``block_id`` has queued for the host so far. In lockstep the host
        waits until its callbacks have seen this many (cflib reads them on its own thread)."""
        return self._logs.emitted(block_id)

    # --- per-step work ---------------------------------------------------------------------------

    def _on_sim_step(self, t: float) -> None:
        """Called after every simulator step: link statistics and log blocks that are due."""
        if t >= self._stats_next_t - 1e-9:
            self._report_link_statistics(t)
        if self._logs.logging:
            for payload in self._logs.due_payloads(t, self._endpoint):
                self._reply(PORT_LOG, 2, payload)

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
