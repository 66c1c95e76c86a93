"""``CflibRadio``: stock cflib objects behind a latest-value slot.

The loop writes the newest ``AttitudeSetpoint`` and mocap pose into slots; the radio
transmits the newest setpoint at ``tx_rate_hz`` (the firmware keeps only the latest, and
one Crazyradio carries about 500 packets/s: docs/hardware.md#radio-budget) and forwards
each new pose as an extpose. Two ways to drive it:

- ``lockstep=True``: nothing runs in the background; the loop calls ``pump(now)`` every
  tick and the packets go out in that call, stamped with the simulator's time.
- ``lockstep=False``: a TX thread sends on the wall clock, so cflib's blocking
  ``send_packet`` (up to 2 s on a bad link) never runs on the event-loop thread.

``LinkSafety.heartbeat_hz > 0`` also sends the emergency-stop-watchdog heartbeat
(docs/hardware.md#emergency-stop) on the same schedule owner, when the firmware has the
supervisor port (protocol >= 12).

In threaded mode every setpoint is stamped when the loop hands it over, and the TX thread
sends nothing stale (stale_setpoint.py): a loop that stops ticking gets a level, descending
hold after a few slots, then zeros and no more heartbeats. The TX thread is that watchdog:
it runs whatever the loop's thread is stuck in.

``imu_log=True`` also starts the accelerometer log block (imu_log.py): ``imu`` is then an
``ImuSource`` whose ``latest(now)`` the loop reads every tick.

``HardwareRadio`` (hardware_radio.py) adds what a real Crazyflie needs.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import cflib.crtp
import numpy as np
from cflib.crazyflie import Crazyflie

from cfknode.app.backends.imu_log import ImuLog, start_imu_log
from cfknode.app.backends.stale_setpoint import StaleGuard, StalePolicy
from cfknode.app.backends.tx_cadence import TIME_EPS, Cadence
from cfknode.kernel.messages import first_line

if TYPE_CHECKING:
    from cfknode.kernel.imu import ImuSample
    from cfknode.kernel.setpoint import AttitudeSetpoint

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
    imu_samples: int = 0  # accelerometer samples received (0 without the IMU block)
    imu_late: int = 0  # lockstep ticks that gave up waiting for an emitted accelerometer sample
    stale_holds: int = 0  # times the loop's setpoint went stale in flight and the radio held level, descending
    stale_stops: int = 0  # times (at most once) a stale setpoint made the radio stop the motors
    motors_off: bool = False  # nothing but zeros goes out: no thrust asked for yet or any more, stopped, or handed back


@dataclass(frozen=True)
class LinkSafety:
    """What the radio sends for safety besides the loop's setpoints.

    ``zero_stream_s``: how long the shutdown streams zeros; ``heartbeat_hz`` > 0: the emergency-stop
    watchdog's heartbeat (0 = never); ``stale``: when a setpoint counts as stale in threaded mode
    (None: hold after 4 slots, stop after 1 s)."""

    zero_stream_s: float = 0.1
    heartbeat_hz: float = 0.0
    stale: StalePolicy | None = None


class CflibRadio:
    """Sends attitude setpoints and extposes to one Crazyflie through cflib."""

    def __init__(
        self,
        uri: str,
        *,
        tx_rate_hz: float = 100.0,
        lockstep: bool = False,
        rw_cache: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        advance: Callable[[float], None] | None = None,
        imu_log: bool = False,
        safety: LinkSafety = LinkSafety(),
    ) -> None:
        """``clock`` is the flight clock (stats timestamps; lockstep shutdown timing).
        ``advance(t)`` steps a lockstep simulator to ``t`` so the shutdown zero stream spans
        simulated time; without it the zeros go out back to back. ``safety.heartbeat_hz`` > 0 sends
        the emergency-stop-watchdog heartbeat where the firmware supports it (0 = never).
        ``imu_log`` starts the accelerometer log block at connect (a firmware without it: a
        warning in ``imu_note``, and ``imu`` stays None). ``safety``: the shutdown's zero stream,
        the heartbeat and the stale-setpoint policy (``LinkSafety``)."""
        zero_stream_s, heartbeat_hz, stale = safety.zero_stream_s, safety.heartbeat_hz, safety.stale
        if not tx_rate_hz > 0:
            raise ValueError(f"tx_rate_hz must be positive, got {tx_rate_hz}")
        if heartbeat_hz < 0:
            raise ValueError(f"heartbeat_hz must be >= 0, got {heartbeat_hz}")
        self.uri = uri
        self.lockstep = lockstep
        self.tx_rate_hz = tx_rate_hz
        self._period = 1.0 / tx_rate_hz
        self._rw_cache = rw_cache
        self._zero_count = max(1, math.ceil(zero_stream_s * tx_rate_hz - TIME_EPS))
        self._clock = clock
        self._advance = advance
        self._cf: Crazyflie | None = None
        # Latest-value slots, each replaced whole (an atomic store under the GIL). The setpoint's
        # slot is stamped on the wall clock: its age is what the TX thread checks.
        self._stale = StaleGuard(stale or StalePolicy(4, 1.0), time.monotonic)
        self._extpose: tuple[int, tuple[float, ...]] | None = None
        self._extpose_seq = 0
        self._extpose_sent_seq = 0
        self._tx_cadence = Cadence(self._period)
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
        self._hb_cadence = Cadence(self._hb_period)
        self._heartbeats_sent = 0
        self._imu_requested = imu_log
        self.imu: ImuLog | None = None  # the accelerometer block, once running
        self.imu_note: str | None = None  # why there is no IMU although it was asked for

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
                raise RadioError(f"could not connect to {self.uri}: {first_line(failures[0])}")
            raise RadioError(f"no answer from {self.uri} within {timeout:g} s (powered on? right URI?)")
        cf.connection_lost.add_callback(self._on_link_lost)
        self._cf = cf
        try:
            self._prepare(cf, deadline)
            if self._imu_requested:
                self.imu, self.imu_note = start_imu_log(self.uri, cf, deadline, lockstep=self.lockstep,
                                                        clock=self._clock)
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
        if self.imu is not None:
            self.imu.set_clock(clock)

    def _on_link_lost(self, uri: str, message: str) -> None:
        self._link_lost = first_line(message)

    # --- the loop's side: latest-value slots -------------------------------------------------

    def latest_imu(self, now: float) -> "ImuSample | None":
        """The newest accelerometer sample measured at or before ``now`` (None without the block)."""
        imu = self.imu
        return imu.latest(now) if imu is not None else None

    def set_setpoint(self, sp: "AttitudeSetpoint") -> None:
        self._stale.stamp((sp.roll_deg, sp.pitch_deg, sp.yawrate_deg, int(sp.thrust)))

    def set_stale_hold(self, hold: "AttitudeSetpoint", listener: Callable[[str, float], None] | None = None) -> None:
        """The thrust of the hold a stale setpoint is replaced by (the supervisor's blind setpoint),
        and ``listener(phase, age_s)``, told from the TX thread when a stall reaches "hold" or "stop"."""
        self._stale.set_hold(int(hold.thrust), listener)

    def hold_level(self, thrust: int | None) -> None:
        """In a fleet, another drone is below this one: a stalled loop's hold is level at ``thrust`` (the
        hover thrust) rather than descending onto it; None: the descending hold (stale_setpoint.py)."""
        self._stale.hold_level(thrust)

    def stop_signal(self, count: int) -> None:
        """The flight's ``count``-th stop signal (any thread): during a stall the second stops the motors."""
        self._stale.stop_signal(count)

    def operator_stop(self) -> None:
        """An operator's stop (``cfknode estop``), from any thread: motors off now if the loop has stalled."""
        self._stale.operator_stop()

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
        self._send_new_extpose(now)
        setpoint = self._stale.latest  # lockstep: the loop sends in this very call, never stale
        if setpoint is not None and self._tx_cadence.due(now):
            self._send_setpoint(setpoint, now)
        if self._hb_enabled and self._hb_cadence.due(now):
            self._send_heartbeat()

    def _send_new_extpose(self, t: float) -> None:
        """Forward the pose slot if it holds a pose not sent yet."""
        extpose = self._extpose
        if extpose is not None and extpose[0] != self._extpose_sent_seq:
            self._extpose_sent_seq = extpose[0]
            self._send_extpose(extpose[1], t)

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
        start = time.monotonic()
        tx = Cadence(self._period, start)  # wall-clock schedules, separate from the lockstep ones
        hb = Cadence(self._hb_period, start if self._hb_enabled else math.inf)
        while not self._stop_tx:
            delay = min(tx.next_t, hb.next_t) - time.monotonic()
            if delay > 0:
                self._wake.wait(delay)
            self._wake.clear()
            if self._stop_tx:
                break
            self._send_new_extpose(self._clock())
            wall = time.monotonic()
            if tx.due(wall):
                setpoint = self._stale.outgoing()
                if setpoint is not None:
                    self._send_setpoint(setpoint, self._clock())
            if hb.due(wall) and not self._stale.stopped:
                self._send_heartbeat()
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
        imu = self.imu.stats() if self.imu is not None else None
        return RadioStats(
            setpoints_sent=self._setpoints_sent,
            extposes_sent=self._extposes_sent,
            last_send_time=self._last_send,
            send_errors=self._send_errors,
            last_error=self._last_error,
            link_lost=self._link_lost,
            heartbeats_sent=self._heartbeats_sent,
            imu_samples=imu.samples if imu is not None else 0,
            imu_late=imu.late if imu is not None else 0,
            stale_holds=self._stale.holds,
            stale_stops=self._stale.stops,
            motors_off=self._motors_off(),
        )

    def _motors_off(self) -> bool:
        """Whether the radio sends zero thrust (or nothing) whatever the loop does next: the loop's
        newest setpoint has none (never flown, landed), the stall guard stopped, or the link is handed back."""
        latest = self._stale.latest
        return self._shut or self._stale.stopped or latest is None or int(latest[3]) == 0


def ensure_cflib_drivers() -> None:
    """cflib's link drivers (radio, usb, udp, ...) registered once: ``init_drivers`` appends
    on every call, and the sim:// driver may already sit in front of them."""
    if not any(getattr(c, "__module__", "").startswith("cflib.") for c in cflib.crtp.CLASSES):
        cflib.crtp.init_drivers()
