"""The accelerometer log block: ``acc.x``, ``acc.y``, ``acc.z`` at 100 Hz, as ``ImuSample``s on the flight clock.

``ImuLog`` adds one cflib ``LogConfig`` after the link is up; its callback (cflib's receive
thread) keeps the newest samples, converted from g to m/s^2, and the loop reads the newest one
measured at or before its tick with ``latest(now)`` (the ``ImuSource`` protocol). A firmware
without the variables gets one warning and no IMU: the flight goes on without it.

Time base (docs/hardware.md#imu-log): the log timestamp is the firmware's clock in ms (24 bits,
unwrapped here). In lockstep simulation it is simulated time, which is the flight clock, so the
stamp is the sample time exactly. On a wall clock the two clocks differ by an unknown offset;
``FirmwareClockMap`` estimates it as the smallest (host receive time - firmware time) over the
recent samples: the receive time is the measurement time plus a transport delay that is never
negative, and its smallest value over a few seconds is the delay's floor, so stamps are never in
the future and are late by at most that floor (a few ms over a radio). A sliding window rather
than the minimum since connect follows the two crystals' drift (tens of ppm).

Lockstep determinism: the simulator queues a log packet when it is stepped, and cflib reads it
on its own thread, so whether tick ``now`` sees the sample of ``now`` would be a race. In
lockstep ``latest`` first waits (bounded) until the callback has received every packet the
simulated firmware has emitted for this block (``log_payloads_emitted`` of the ``sim://`` link);
a wait that runs out is counted in ``late`` and the flight goes on with what has arrived.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig

from cfknode.kernel.imu import FIRMWARE_G, ImuSample
from cfknode.kernel.messages import first_line

_logger = logging.getLogger(__name__)

IMU_VARIABLES = ("acc.x", "acc.y", "acc.z")  # body frame, g (firmware's sensfusion-filtered accelerometer)
IMU_PERIOD_MS = 10  # the firmware's shortest log period: 100 Hz
STAMP_RESOLUTION_S = 1e-3  # firmware log timestamps are whole ms
_WRAP = 1 << 24  # cflib hands the 24-bit timestamp over as it came
_OFFSET_WINDOW = 500  # samples (5 s at 100 Hz) the clock offset's minimum is taken over
_RING = 32  # samples kept: a tick reads one of the newest few
LOCKSTEP_WAIT_S = 0.5  # wall time a lockstep read waits for the emitted samples before it counts one late


class FirmwareClockMap:
    """Firmware log timestamps (ms, 24-bit) -> flight-clock seconds; see the module docstring."""

    def __init__(self, exact: bool, window: int = _OFFSET_WINDOW) -> None:
        """``exact``: the firmware clock is the flight clock (lockstep simulation): no offset."""
        if window < 1:
            raise ValueError(f"window must be >= 1 sample, got {window}")
        self.exact = exact
        self._window = window
        self.reset()

    def reset(self) -> None:
        """Forget the offset and the wraps (a new flight clock)."""
        self._last_raw: int | None = None
        self._wraps = 0
        self._i = 0
        self._mins: collections.deque[tuple[int, float]] = collections.deque()  # increasing offsets

    @property
    def offset(self) -> float | None:
        """Flight clock - firmware clock, s (None before the first sample; 0 when exact)."""
        if self.exact:
            return 0.0
        return self._mins[0][1] if self._mins else None

    def firmware_seconds(self, raw_ms: int) -> float:
        """The unwrapped firmware time of a 24-bit timestamp, s (timestamps arrive in order)."""
        if self._last_raw is not None and raw_ms < self._last_raw - _WRAP // 2:
            self._wraps += 1
        self._last_raw = raw_ms
        return (raw_ms + self._wraps * _WRAP) / 1000.0

    def stamp(self, raw_ms: int, received: float) -> float:
        """The sample time on the flight clock, for a sample that arrived at flight time ``received``."""
        fw = self.firmware_seconds(raw_ms)
        if self.exact:
            return fw
        # Sliding-window minimum of (received - fw): a deque of increasing candidates.
        d = received - fw
        mins = self._mins
        while mins and mins[-1][1] >= d:
            mins.pop()
        mins.append((self._i, d))
        if mins[0][0] <= self._i - self._window:
            mins.popleft()
        self._i += 1
        return fw + mins[0][1]


@dataclass(frozen=True)
class ImuStats:
    samples: int  # received since connect
    late: int  # lockstep reads that gave up waiting for an emitted sample
    offset_s: float | None  # flight clock - firmware clock (0 in lockstep)


class ImuLog:
    """One radio's accelerometer block; ``start`` after the link is up, then ``latest(now)`` per tick."""

    def __init__(self, uri: str, *, lockstep: bool, clock: Callable[[], float],
                 wait_s: float = LOCKSTEP_WAIT_S) -> None:
        self.uri = uri
        self.lockstep = lockstep
        self._clock = clock
        self._wait_s = wait_s
        self._map = FirmwareClockMap(exact=lockstep)
        self._cond = threading.Condition(threading.Lock())
        self._ring: collections.deque[ImuSample] = collections.deque(maxlen=_RING)
        self._received = 0
        self._late = 0
        self._emitted: Callable[[], int] | None = None
        self.conf: LogConfig | None = None

    # --- set-up (the caller of connect) ---------------------------------------------------------

    def start(self, cf: Crazyflie, deadline: float) -> str | None:
        """Add and start the block; None when it runs, else a one-line reason there is no IMU."""
        conf = LogConfig("cfknode_imu", IMU_PERIOD_MS)
        for name in IMU_VARIABLES:
            conf.add_variable(name, "float")
        try:
            cf.log.add_config(conf)
        except KeyError as exc:
            return f"{self.uri} cannot log the accelerometer ({first_line(str(exc.args[0] if exc.args else exc))}): " \
                   "flying without IMU samples"
        except AttributeError as exc:
            return f"{self.uri} refused the accelerometer log block ({first_line(str(exc))}): flying without IMU samples"
        if not conf.valid:
            return f"{self.uri} has no log TOC for the accelerometer: flying without IMU samples"
        conf.data_received_cb.add_callback(self._on_data)
        started = threading.Event()
        conf.started_cb.add_callback(lambda lc, ok: started.set() if ok else None)
        conf.start()
        if not started.wait(max(deadline - time.monotonic(), 0.0)):
            conf.data_received_cb.remove_callback(self._on_data)
            return f"{self.uri} did not start the accelerometer log block in time: flying without IMU samples"
        counter = getattr(cf.link, "log_payloads_emitted", None) if self.lockstep else None
        if counter is not None:
            block_id = conf.id
            self._emitted = lambda: counter(block_id)
        self.conf = conf
        return None

    def set_clock(self, clock: Callable[[], float]) -> None:
        """A new flight clock: samples stamped on the old one are dropped and the offset re-learnt."""
        with self._cond:
            self._clock = clock
            self._map.reset()
            self._ring.clear()

    # --- cflib's receive thread -------------------------------------------------------------------

    def _on_data(self, timestamp: int, data: dict[str, Any], conf: LogConfig) -> None:
        force = np.array([data["acc.x"], data["acc.y"], data["acc.z"]], dtype=np.float64) * FIRMWARE_G
        with self._cond:
            received = 0.0 if self._map.exact else self._clock()
            self._ring.append(ImuSample(self._map.stamp(int(timestamp), received), force))
            self._received += 1
            self._cond.notify_all()

    # --- the loop's side ------------------------------------------------------------------------

    def latest(self, now: float) -> ImuSample | None:
        """The newest sample measured at or before ``now`` (within the stamp's 1 ms), or None."""
        emitted = self._emitted
        with self._cond:
            if emitted is not None:
                expected = emitted()
                if self._received < expected and not self._cond.wait_for(
                        lambda: self._received >= expected, timeout=self._wait_s):
                    self._late += 1
            limit = now + 0.5 * STAMP_RESOLUTION_S
            for sample in reversed(self._ring):
                if sample.t <= limit:
                    return sample
        return None

    def stats(self) -> ImuStats:
        return ImuStats(samples=self._received, late=self._late, offset_s=self._map.offset)


def start_imu_log(uri: str, cf: Crazyflie, deadline: float, *, lockstep: bool,
                  clock: Callable[[], float]) -> tuple[ImuLog | None, str | None]:
    """An ``ImuLog`` running on ``cf``, or None and the one-line warning (also logged) why not."""
    imu = ImuLog(uri, lockstep=lockstep, clock=clock)
    note = imu.start(cf, deadline)
    if note is not None:
        _logger.warning(note)
        return None, note
    return imu, None


__all__ = ["IMU_PERIOD_MS", "IMU_VARIABLES", "FirmwareClockMap", "ImuLog", "ImuStats", "start_imu_log"]
