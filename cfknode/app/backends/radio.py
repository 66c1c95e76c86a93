"""The flight stack's radio: stock cflib objects behind a latest-value slot.

The loop writes the newest ``AttitudeSetpoint`` and mocap pose into slots; the radio
transmits the newest setpoint at ``tx_rate_hz`` (the firmware keeps only the latest, and
one Crazyradio carries about 500 packets/s: docs/hardware.md#radio-budget) and forwards
each new pose as an extpose. Two ways to drive it:

- ``lockstep=True``: nothing runs in the background; the loop calls ``pump(now)`` every
  tick and the packets go out in that call, stamped with the simulator's time.
- ``lockstep=False``: a TX thread sends on the wall clock, so cflib's blocking
  ``send_packet`` (up to 2 s on a bad link) never runs on the event-loop thread.

``heartbeat_hz > 0`` also sends the emergency-stop-watchdog heartbeat
(docs/hardware.md#emergency-stop) on the same schedule owner, when the firmware has the
supervisor port (protocol >= 12).

``HardwareRadio`` adds what a real Crazyflie needs before and during flight: parameters
(Kalman estimator, PID attitude controller, extpose noise), a telemetry log block
(``pm.vbat``, ``pm.state``, ``supervisor.info``, ``radio.rssi``), link statistics, an
estimator reset, extposes straight from the mocap thread, and a reboot after the hand-back
when the heartbeat armed the firmware's emergency-stop watchdog (a latch only a reboot clears).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

import cflib.crtp
import numpy as np
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig

if TYPE_CHECKING:
    from cfknode.kernel.setpoint import AttitudeSetpoint

_TIME_EPS = 1e-9  # s; tick times built as k * period must not miss a TX slot to rounding
SUPERVISOR_PROTOCOL = 12  # supervisor port and its e-stop watchdog (docs/hardware.md#emergency-stop)


class RadioError(RuntimeError):
    """The radio could not connect; the message is one line, for the operator."""


@dataclass(frozen=True)
class RadioStats:
    setpoints_sent: int  # RPYT packets, unlock and shutdown zeros included
    extposes_sent: int
    last_send_time: float | None  # flight-clock time of the newest packet sent
    send_errors: int
    last_error: str | None
    link_lost: str | None  # cflib's message if the link dropped, else None
    heartbeats_sent: int = 0  # emergency-stop-watchdog notifications
    latency_ms: float | None = None  # cflib's ping round trip (p95), where the radio measures it


class CflibRadio:
    """Sends attitude setpoints and extposes to one Crazyflie through cflib."""

    def __init__(
        self,
        uri: str,
        *,
        tx_rate_hz: float = 100.0,
        lockstep: bool = False,
        rw_cache: str | None = None,
        zero_stream_s: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
        advance: Callable[[float], None] | None = None,
        heartbeat_hz: float = 0.0,
    ) -> None:
        """``clock`` is the flight clock (stats timestamps; lockstep shutdown timing).
        ``advance(t)`` steps a lockstep simulator to ``t`` so the shutdown zero stream spans
        simulated time; without it the zeros go out back to back. ``heartbeat_hz`` > 0 sends
        the emergency-stop-watchdog heartbeat where the firmware supports it (0 = never)."""
        if not tx_rate_hz > 0:
            raise ValueError(f"tx_rate_hz must be positive, got {tx_rate_hz}")
        if heartbeat_hz < 0:
            raise ValueError(f"heartbeat_hz must be >= 0, got {heartbeat_hz}")
        self.uri = uri
        self.lockstep = lockstep
        self.tx_rate_hz = tx_rate_hz
        self._period = 1.0 / tx_rate_hz
        self._rw_cache = rw_cache
        self._zero_count = max(1, math.ceil(zero_stream_s * tx_rate_hz - _TIME_EPS))
        self._clock = clock
        self._advance = advance
        self._cf: Crazyflie | None = None
        # Latest-value slots, each replaced whole (an atomic store under the GIL).
        self._setpoint: tuple[float, float, float, int] | None = None
        self._extpose: tuple[int, tuple[float, ...]] | None = None
        self._extpose_seq = 0
        self._extpose_sent_seq = 0
        self._next_tx = -math.inf
        self._tx_thread: threading.Thread | None = None
        self._wake = threading.Event()
        self._stop_tx = False
        self._shutdown_lock = threading.Lock()
        self._shut = False
        self._setpoints_sent = 0
        self._extposes_sent = 0
        self._last_send: float | None = None
        self._send_errors = 0
        self._last_error: str | None = None
        self._link_lost: str | None = None
        self._fully_connected = threading.Event()  # all parameter values downloaded (cflib)
        self._hb_period = 1.0 / heartbeat_hz if heartbeat_hz > 0 else 0.0
        self._hb_enabled = False  # decided at connect: requested and supported by the firmware
        self._next_hb = -math.inf
        self._heartbeats_sent = 0

    @property
    def cf(self) -> Crazyflie | None:
        """The connected cflib ``Crazyflie`` (for log configs and params), or None."""
        return self._cf

    # --- connection ------------------------------------------------------------------------

    def connect(self, timeout: float = 10.0) -> None:
        """Open the link (blocking), send the unlock setpoint, start the TX thread if any."""
        if self._cf is not None or self._shut:
            raise RadioError(f"radio for {self.uri} is already connected or shut down; make a new one")
        deadline = time.monotonic() + timeout
        ensure_cflib_drivers()
        cf = Crazyflie(rw_cache=self._rw_cache)
        done = threading.Event()
        self._fully_connected.clear()
        failures: list[str] = []

        def on_connected(uri: str) -> None:
            done.set()

        def on_failed(uri: str, message: str) -> None:
            failures.append(message)
            done.set()

        def on_fully(uri: str) -> None:
            self._fully_connected.set()

        cf.connected.add_callback(on_connected)
        cf.connection_failed.add_callback(on_failed)
        cf.fully_connected.add_callback(on_fully)
        cf.open_link(self.uri)
        answered = done.wait(timeout)
        cf.connected.remove_callback(on_connected)
        cf.connection_failed.remove_callback(on_failed)
        if failures or not answered:
            cf.close_link()
            if failures:
                raise RadioError(f"could not connect to {self.uri}: {_first_line(failures[0])}")
            raise RadioError(f"no answer from {self.uri} within {timeout:g} s (powered on? right URI?)")
        cf.connection_lost.add_callback(self._on_link_lost)
        self._cf = cf
        try:
            self._prepare(cf, deadline)
        except BaseException:
            self._cf = None
            self._shut = True
            self._close_link(cf)
            raise
        self._hb_enabled = self._hb_period > 0 and self.protocol_version >= SUPERVISOR_PROTOCOL
        # The firmware ignores thrust until it has seen a zero-thrust RPYT packet
        # (docs/hardware.md#unlock).
        self._send_setpoint((0.0, 0.0, 0.0, 0), self._clock())
        if not self.lockstep:
            self._tx_thread = threading.Thread(target=self._tx_loop, name=f"radio-tx {self.uri}", daemon=True)
            self._tx_thread.start()

    def _prepare(self, cf: Crazyflie, deadline: float) -> None:
        """Between the link coming up and the unlock: nothing here; ``HardwareRadio`` configures."""

    @property
    def protocol_version(self) -> int:
        """The firmware's CRTP protocol version (-1 before the link is up)."""
        cf = self._cf
        return cf.platform.get_protocol_version() if cf is not None else -1

    @property
    def heartbeat_enabled(self) -> bool:
        """Whether the emergency-stop-watchdog heartbeat is being sent on this link."""
        return self._hb_enabled

    def set_clock(self, clock: Callable[[], float]) -> None:
        """Switch to a new flight clock (the hardware flight clock starts after the pre-flight)."""
        self._clock = clock

    def _on_link_lost(self, uri: str, message: str) -> None:
        self._link_lost = _first_line(message)

    # --- the loop's side: latest-value slots -------------------------------------------------

    def set_setpoint(self, sp: "AttitudeSetpoint") -> None:
        self._setpoint = (sp.roll_deg, sp.pitch_deg, sp.yawrate_deg, int(sp.thrust))

    def set_extpose(self, position: np.ndarray, quaternion_wxyz: np.ndarray) -> None:
        """Queue a pose for the onboard estimator; cflib wants the quaternion as x, y, z, w."""
        x, y, z = position.tolist()
        qw, qx, qy, qz = quaternion_wxyz.tolist()
        self._extpose_seq += 1
        self._extpose = (self._extpose_seq, (x, y, z, qx, qy, qz, qw))
        if self._tx_thread is not None:
            self._wake.set()

    def pump(self, now: float) -> None:
        """Lockstep only: send a new extpose, and the newest setpoint if a TX slot is due."""
        if not self.lockstep or self._cf is None or self._shut:
            return
        self._send_due(now)

    # --- sending ---------------------------------------------------------------------------

    def _send_due(self, now: float) -> None:
        extpose = self._extpose
        if extpose is not None and extpose[0] != self._extpose_sent_seq:
            self._extpose_sent_seq = extpose[0]
            self._send_extpose(extpose[1], now)
        setpoint = self._setpoint
        if setpoint is not None and now >= self._next_tx - _TIME_EPS:
            self._send_setpoint(setpoint, now)
            self._next_tx += self._period
            if self._next_tx <= now:  # first packet, or fell behind: restart the grid, no burst
                self._next_tx = now + self._period
        if self._hb_enabled and now >= self._next_hb - _TIME_EPS:
            self._send_heartbeat()
            self._next_hb += self._hb_period
            if self._next_hb <= now:
                self._next_hb = now + self._hb_period

    def _send_heartbeat(self) -> None:
        if self._link_lost is not None:
            return
        try:
            self._cf.supervisor.send_emergency_stop_watchdog()
        except Exception as exc:
            self._record_error(exc)
            return
        self._heartbeats_sent += 1

    def _send_setpoint(self, sp: tuple[float, float, float, int], t: float) -> None:
        if self._link_lost is not None:
            return  # cflib drops packets once the link is gone; do not count them as sent
        try:
            self._cf.commander.send_setpoint(*sp)
        except Exception as exc:  # a bad value must not kill the TX thread; it is counted
            self._record_error(exc)
            return
        self._setpoints_sent += 1
        self._last_send = t

    def _send_extpose(self, pose: tuple[float, ...], t: float) -> None:
        if self._link_lost is not None:
            return
        try:
            self._cf.extpos.send_extpose(*pose)
        except Exception as exc:
            self._record_error(exc)
            return
        self._extposes_sent += 1
        self._last_send = t

    def _record_error(self, exc: Exception) -> None:
        self._send_errors += 1
        self._last_error = f"{type(exc).__name__}: {exc}"

    def _tx_loop(self) -> None:
        """Threaded mode: newest setpoint every period (wall clock), extposes as they come,
        heartbeats on their own period."""
        next_wall = time.monotonic()
        next_hb = next_wall if self._hb_enabled else math.inf
        while not self._stop_tx:
            delay = min(next_wall, next_hb) - time.monotonic()
            if delay > 0:
                self._wake.wait(delay)
            self._wake.clear()
            if self._stop_tx:
                break
            extpose = self._extpose
            if extpose is not None and extpose[0] != self._extpose_sent_seq:
                self._extpose_sent_seq = extpose[0]
                self._send_extpose(extpose[1], self._clock())
            wall = time.monotonic()
            if wall >= next_wall:
                setpoint = self._setpoint
                if setpoint is not None:
                    self._send_setpoint(setpoint, self._clock())
                next_wall += self._period
                if next_wall <= wall:
                    next_wall = wall + self._period
            if wall >= next_hb:
                self._send_heartbeat()
                next_hb += self._hb_period
                if next_hb <= wall:
                    next_hb = wall + self._hb_period
        self._hand_back()

    # --- shutdown ----------------------------------------------------------------------------

    def shutdown(self) -> None:
        """Zero setpoints for a moment, notify-setpoint-stop, HL stop, close. Idempotent."""
        with self._shutdown_lock:
            if self._shut:
                return
            self._shut = True
        if self._cf is None:
            return
        thread = self._tx_thread
        if thread is not None:
            # The TX thread runs the hand-back itself, so cflib stays on one thread.
            self._stop_tx = True
            self._wake.set()
            thread.join(timeout=self._zero_count * self._period + 10.0)
        else:
            self._hand_back()

    def _hand_back(self) -> None:
        """Leave the firmware safe: motors off, and the watchdog satisfied
        (docs/hardware.md#commander-watchdog)."""
        cf = self._cf
        zero = (0.0, 0.0, 0.0, 0)
        for i in range(self._zero_count):
            if i > 0:
                self._wait_one_period()
            self._send_setpoint(zero, self._clock())
        try:
            # Streamed setpoints release the commander; a stopped HL planner then feeds null
            # setpoints, so the watchdog never reaches Locked.
            cf.commander.send_notify_setpoint_stop()
            cf.high_level_commander.stop()
        except Exception as exc:
            self._record_error(exc)
        self._close_link(cf)

    def _wait_one_period(self) -> None:
        if not self.lockstep:
            time.sleep(self._period)
        elif self._advance is not None:
            self._advance(self._clock() + self._period)

    @staticmethod
    def _close_link(cf: Crazyflie) -> None:
        # cflib's close_link() sends setpoint(0,0,0,0) first: that would take the commander
        # back from the HL planner and leave the watchdog to lock the drone at 2 s. So stop
        # the ping thread (the only other sender), detach the link and close it ourselves.
        cf.link_statistics.stop()
        link, cf.link = cf.link, None
        if link is not None:
            link.close()
        cf.close_link()

    def __enter__(self) -> "CflibRadio":
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def stats(self) -> RadioStats:
        return RadioStats(
            setpoints_sent=self._setpoints_sent,
            extposes_sent=self._extposes_sent,
            last_send_time=self._last_send,
            send_errors=self._send_errors,
            last_error=self._last_error,
            link_lost=self._link_lost,
            heartbeats_sent=self._heartbeats_sent,
        )


def ensure_cflib_drivers() -> None:
    """cflib's link drivers (radio, usb, udp, ...) registered once: ``init_drivers`` appends
    on every call, and the sim:// driver may already sit in front of them."""
    if not any(getattr(c, "__module__", "").startswith("cflib.") for c in cflib.crtp.CLASSES):
        cflib.crtp.init_drivers()


def _first_line(message: str) -> str:
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    return lines[0] if lines else "unknown error"


# --- the hardware radio ------------------------------------------------------------------------

# Parameters the flight stack relies on (docs/hardware.md#extpose, #parameters): the onboard
# Kalman filter fuses the extposes, so the firmware's yaw is the mocap's (the attitude layer
# decomposes the thrust in that yaw); the default PID attitude controller flies RPYT setpoints.
ESTIMATOR_KALMAN = 2
CONTROLLER_PID = 1
# Crazyswarm2's status block (docs/hardware.md#logging): one log block, 4 + 1 + 2 + 1 = 8 bytes
# of the 26.
TELEMETRY_VARIABLES = (("pm.vbat", "float"), ("pm.state", "int8_t"), ("supervisor.info", "uint16_t"),
                       ("radio.rssi", "uint8_t"))


@dataclass(frozen=True)
class Telemetry:
    """The newest telemetry sample; ``received`` is ``time.monotonic()`` at its arrival."""

    vbat: float  # V, under the current load
    pm_state: int  # 0 battery, 1 charging, 2 charged, 3 lowPower, 4 shutDown
    supervisor_info: int  # bitfield (docs/hardware.md#supervisor)
    rssi: int  # dBm, magnitude
    firmware_ms: int  # the firmware's log timestamp
    received: float
    samples: int


@dataclass(frozen=True)
class LinkStatistics:
    """Link health as cflib reports it; None where nothing has been reported yet.

    ``link_quality`` is cflib's figure from the radio's retries (100 = every packet acked at
    the first try), which is what the radio exposes of the ack rate; the rates are packets
    per second in each direction.
    """

    latency_ms: float | None  # p95 round trip of cflib's pings (10 Hz)
    link_quality: float | None
    uplink_rate: float | None
    downlink_rate: float | None
    packets_sent: int  # by this radio: setpoints, extposes and heartbeats
    send_errors: int
    link_lost: str | None


class HardwareRadio(CflibRadio):
    """``CflibRadio`` configured for a real Crazyflie (or the simulator behind ``sim://``).

    ``connect`` waits for the parameter values, sets ``params`` (``group.name`` -> value, each
    confirmed by the firmware's echo), starts the telemetry block and the link statistics,
    and then unlocks. Every cflib call runs in the caller of ``connect``/``shutdown``, the
    TX thread or cflib's own threads: the flight loop only writes slots and reads snapshots.
    """

    def __init__(
        self,
        uri: str,
        *,
        params: Mapping[str, float] | None = None,
        telemetry_hz: float = 10.0,
        reboot_after_heartbeat: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(uri, **kwargs)
        period_ms = round(1000.0 / telemetry_hz) if telemetry_hz > 0 else 0
        if not 10 <= period_ms <= 2540:
            raise ValueError(f"telemetry_hz must give a log period of 10..2540 ms, got {telemetry_hz}")
        self._params = dict(params or {})
        self._telemetry_period_ms = period_ms
        self._reboot_after_heartbeat = reboot_after_heartbeat
        self._telemetry: Telemetry | None = None
        self._telemetry_samples = 0
        self._latency_ms: float | None = None
        self._link_quality: float | None = None
        self._uplink_rate: float | None = None
        self._downlink_rate: float | None = None
        self._direct_extpose = False
        self.handback_note: str | None = None  # what the hand-back could not do, for the operator

    # --- connection ------------------------------------------------------------------------

    def _prepare(self, cf: Crazyflie, deadline: float) -> None:
        if not self._fully_connected.wait(max(deadline - time.monotonic(), 0.0)):
            raise RadioError(f"{self.uri} did not send its parameter values in time (weak link?)")
        self._set_params(cf, self._params, deadline)
        stats = cf.link_statistics
        stats.latency_updated.add_callback(self._on_latency)
        stats.link_quality_updated.add_callback(self._on_link_quality)
        stats.uplink_rate_updated.add_callback(self._on_uplink_rate)
        stats.downlink_rate_updated.add_callback(self._on_downlink_rate)
        self._start_telemetry(cf, deadline)

    def _set_params(self, cf: Crazyflie, params: Mapping[str, float], deadline: float) -> None:
        for name, value in params.items():
            self._set_param(cf, name, value, deadline)

    def _set_param(self, cf: Crazyflie, name: str, value: float, deadline: float) -> None:
        """Set one parameter and wait for the firmware's echo of the new value."""
        group, _, short = name.partition(".")
        echoed: list[str] = []
        event = threading.Event()

        def on_update(complete_name: str, new_value: str) -> None:
            echoed.append(new_value)
            event.set()

        cf.param.add_update_callback(group=group, name=short, cb=on_update)
        try:
            try:
                cf.param.set_value(name, value)
            except KeyError:
                raise RadioError(f"{self.uri} has no parameter {name!r} (firmware too old, or a typo?)") from None
            except AttributeError:
                raise RadioError(f"parameter {name!r} on {self.uri} is read-only") from None
            if not event.wait(max(deadline - time.monotonic(), 0.0)):
                raise RadioError(f"{self.uri} did not confirm parameter {name} = {value:g} in time")
        finally:
            cf.param.remove_update_callback(group=group, name=short, cb=on_update)
        if not math.isclose(float(echoed[-1]), float(value), rel_tol=1e-6, abs_tol=1e-9):
            raise RadioError(f"{self.uri} set parameter {name} to {echoed[-1]}, not {value:g}")

    def reset_estimator(self, timeout: float = 5.0) -> None:
        """Restart the onboard Kalman filter (``kalman.resetEstimation`` 1 then 0) once
        extposes flow, so it starts from the mocap pose rather than from wherever it drifted."""
        cf = self._require_link()
        deadline = time.monotonic() + timeout
        self._set_param(cf, "kalman.resetEstimation", 1, deadline)
        self._set_param(cf, "kalman.resetEstimation", 0, deadline)

    def _start_telemetry(self, cf: Crazyflie, deadline: float) -> None:
        conf = LogConfig("cfknode_status", self._telemetry_period_ms)
        for name, fetch in TELEMETRY_VARIABLES:
            conf.add_variable(name, fetch)
        try:
            cf.log.add_config(conf)
        except KeyError as exc:
            raise RadioError(f"{self.uri} cannot log {exc.args[0] if exc.args else exc} (firmware too old?)") from None
        except AttributeError as exc:
            raise RadioError(f"{self.uri} refused the telemetry log block: {_first_line(str(exc))}") from None
        conf.data_received_cb.add_callback(self._on_telemetry)
        started = threading.Event()
        conf.started_cb.add_callback(lambda lc, ok: started.set() if ok else None)
        conf.start()
        # The block is created and started over two round trips; wait, so that telemetry
        # flows from the first tick on (and a refusal is an error here, not a silent gap).
        if not started.wait(max(deadline - time.monotonic(), 0.0)):
            raise RadioError(f"{self.uri} did not start the telemetry log block in time")

    def _require_link(self) -> Crazyflie:
        cf = self._cf
        if cf is None or self._shut:
            raise RadioError(f"radio for {self.uri} is not connected")
        return cf

    # --- cflib callbacks (cflib's threads): each replaces one snapshot whole ----------------

    def _on_telemetry(self, timestamp: int, data: dict[str, Any], conf: LogConfig) -> None:
        self._telemetry_samples += 1
        self._telemetry = Telemetry(
            vbat=float(data["pm.vbat"]),
            pm_state=int(data["pm.state"]),
            supervisor_info=int(data["supervisor.info"]),
            rssi=int(data["radio.rssi"]),
            firmware_ms=int(timestamp),
            received=time.monotonic(),
            samples=self._telemetry_samples,
        )

    def _on_latency(self, latency_ms: float) -> None:
        self._latency_ms = float(latency_ms)

    def _on_link_quality(self, quality: float) -> None:
        self._link_quality = float(quality)

    def _on_uplink_rate(self, rate: float) -> None:
        self._uplink_rate = float(rate)

    def _on_downlink_rate(self, rate: float) -> None:
        self._downlink_rate = float(rate)

    # --- snapshots for the loop, the pre-flight checks and the dashboard --------------------

    def telemetry(self) -> Telemetry | None:
        return self._telemetry

    def stats(self) -> RadioStats:
        return dataclasses.replace(super().stats(), latency_ms=self._latency_ms)

    def link_statistics(self) -> LinkStatistics:
        stats = self.stats()
        return LinkStatistics(
            latency_ms=self._latency_ms,
            link_quality=self._link_quality,
            uplink_rate=self._uplink_rate,
            downlink_rate=self._downlink_rate,
            packets_sent=stats.setpoints_sent + stats.extposes_sent + stats.heartbeats_sent,
            send_errors=stats.send_errors,
            link_lost=stats.link_lost,
        )

    def wait_for_telemetry(self, timeout: float) -> Telemetry | None:
        """Block (not on the event loop) until a telemetry sample has arrived, or ``timeout``."""
        end = time.monotonic() + timeout
        while self._telemetry is None and time.monotonic() < end and self._link_lost is None:
            time.sleep(0.01)
        return self._telemetry

    # --- extposes straight from the mocap thread ---------------------------------------------

    def feed_extpose(self, position: np.ndarray, quaternion_wxyz: np.ndarray) -> None:
        """From the mocap thread, every frame: the extpose goes out at the mocap rate, one
        frame after the SDK delivered it, instead of waiting for the loop's next tick."""
        self._direct_extpose = True
        super().set_extpose(position, quaternion_wxyz)

    def set_extpose(self, position: np.ndarray, quaternion_wxyz: np.ndarray) -> None:
        # Once the mocap thread feeds extposes, the loop's copy of the same frame is redundant.
        if not self._direct_extpose:
            super().set_extpose(position, quaternion_wxyz)

    # --- hand-back -----------------------------------------------------------------------------

    def _hand_back(self) -> None:
        super()._hand_back()
        if self._heartbeats_sent == 0:
            return
        # The firmware's emergency-stop watchdog, once armed, stays armed until a reboot: with
        # the heartbeat gone it stops and Locks the drone 1 s later, landed or not
        # (docs/hardware.md#emergency-stop).
        if not self._reboot_after_heartbeat:
            self.handback_note = ("the emergency-stop watchdog is armed: the Crazyflie locks 1 s after the "
                                  "last heartbeat; power-cycle it before the next flight")
            return
        try:
            self._power_cycle()
        except Exception as exc:
            self._record_error(exc)
            self.handback_note = (f"reboot after the flight failed ({_first_line(str(exc))}): the Crazyflie "
                                  "locks 1 s after the last heartbeat; power-cycle it by hand")

    def _power_cycle(self) -> None:
        """Reboot the STM32 through the nRF51 (cflib ``PowerSwitch``), the one way to disarm
        the emergency-stop watchdog; the motors are already off."""
        from cflib.utils.power_switch import PowerSwitch

        switch = PowerSwitch(self.uri)
        try:
            switch.stm_power_cycle()
        finally:
            switch.close()
