"""``HardwareRadio``: ``CflibRadio`` plus what a real Crazyflie needs before and during flight.

Parameters (Kalman estimator, PID attitude controller, extpose noise), a telemetry log block
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
from typing import Any, Mapping

import numpy as np
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig

from cfknode.app.backends.cflib_radio import CflibRadio, RadioError, RadioStats
from cfknode.kernel.messages import first_line

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
            raise RadioError(f"{self.uri} refused the telemetry log block: {first_line(str(exc))}") from None
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
            self.handback_note = (f"reboot after the flight failed ({first_line(str(exc))}): the Crazyflie "
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
