"""Run the simulator against the wall clock (``--realtime``), in its own thread.

In real time the flight loop sleeps on a ``WallClock`` exactly as on hardware, so the
simulated vehicle has to advance by itself; this thread keeps it at wall time.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from cfknode.kernel.clock import Steppable


class RealtimeStepper:
    """Steps ``sim`` to ``now()`` every ``period`` seconds until stopped."""

    def __init__(self, sim: Steppable, now: Callable[[], float], period: float = 0.001) -> None:
        self._sim = sim
        self._now = now
        self._period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-realtime", daemon=True)
        self.max_lag = 0.0

    def start(self) -> "RealtimeStepper":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            target = self._now()
            self.max_lag = max(self.max_lag, target - self._sim.t)
            try:
                self._sim.step_to(target)
            except Exception:  # noqa: BLE001 - the plant froze itself and records why (SimCrazyflie.failure)
                pass
            time.sleep(self._period)
