"""The flight stack's radio: stock cflib objects behind a latest-value slot.

The loop writes the newest ``AttitudeSetpoint`` and mocap pose into slots; the radio
transmits the newest setpoint at ``tx_rate_hz`` (the firmware keeps only the latest, and
one Crazyradio carries about 500 packets/s: HF 1.8) and forwards each new pose as an
extpose. Two ways to drive it:

- ``lockstep=True``: nothing runs in the background; the loop calls ``pump(now)`` every
  tick and the packets go out in that call, stamped with the simulator's time.
- ``lockstep=False``: a TX thread sends on the wall clock, so cflib's blocking
  ``send_packet`` (up to 2 s on a bad link) never runs on the event-loop thread.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from cflib.crazyflie import Crazyflie

if TYPE_CHECKING:
    from cfknode.config import RadioConfig
    from cfknode.flight.mellinger import AttitudeSetpoint

_TIME_EPS = 1e-9  # s; tick times built as k * period must not miss a TX slot to rounding


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
    ) -> None:
        """``clock`` is the flight clock (stats timestamps; lockstep shutdown timing).
        ``advance(t)`` steps a lockstep simulator to ``t`` so the shutdown zero stream spans
        simulated time; without it the zeros go out back to back."""
        if not tx_rate_hz > 0:
            raise ValueError(f"tx_rate_hz must be positive, got {tx_rate_hz}")
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

    @classmethod
    def from_config(cls, config: "RadioConfig", **kwargs: Any) -> "CflibRadio":
        return cls(config.uri, tx_rate_hz=config.tx_rate_hz, **kwargs)

    @property
    def cf(self) -> Crazyflie | None:
        """The connected cflib ``Crazyflie`` (for log configs and params), or None."""
        return self._cf

    # --- connection ------------------------------------------------------------------------

    def connect(self, timeout: float = 10.0) -> None:
        """Open the link (blocking), send the unlock setpoint, start the TX thread if any."""
        if self._cf is not None or self._shut:
            raise RadioError(f"radio for {self.uri} is already connected or shut down; make a new one")
        cf = Crazyflie(rw_cache=self._rw_cache)
        done = threading.Event()
        failures: list[str] = []

        def on_connected(uri: str) -> None:
            done.set()

        def on_failed(uri: str, message: str) -> None:
            failures.append(message)
            done.set()

        cf.connected.add_callback(on_connected)
        cf.connection_failed.add_callback(on_failed)
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
        # The firmware ignores thrust until it has seen a zero-thrust RPYT packet (HF 1.2).
        self._send_setpoint((0.0, 0.0, 0.0, 0), self._clock())
        if not self.lockstep:
            self._tx_thread = threading.Thread(target=self._tx_loop, name=f"radio-tx {self.uri}", daemon=True)
            self._tx_thread.start()

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
        """Threaded mode: newest setpoint every period (wall clock), extposes as they come."""
        next_wall = time.monotonic()
        while not self._stop_tx:
            delay = next_wall - time.monotonic()
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
        """Leave the firmware safe: motors off, and the watchdog satisfied (HF 1.3)."""
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
        )


def _first_line(message: str) -> str:
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    return lines[0] if lines else "unknown error"
