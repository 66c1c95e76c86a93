"""Flight clocks: the loop asks a clock for the time and to wait for the next tick.

``WallClock`` serves hardware and ``--realtime`` simulation. ``SimClock`` is virtual:
waiting for a tick steps the simulator to that time, so a lockstep flight runs as fast
as the computer allows and reproduces exactly with a seed.
"""

from __future__ import annotations

import asyncio
import selectors
import time
from typing import Any, Coroutine, Protocol, TypeVar

T = TypeVar("T")


class Clock(Protocol):
    lockstep: bool

    def now(self) -> float: ...

    async def sleep_until(self, t: float) -> None: ...


class Steppable(Protocol):
    t: float

    def step_to(self, t_target: float) -> None: ...


class WallClock:
    """Monotonic wall time, zero at construction."""

    lockstep = False

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def monotonic(self, t: float) -> float:
        """The ``time.monotonic()`` of this clock's time ``t``."""
        return self._t0 + t

    async def sleep_until(self, t: float) -> None:
        delay = t - self.now()
        # Always yield, so other tasks (dashboard, I/O) run even when the loop is late.
        await asyncio.sleep(delay if delay > 0 else 0)


def fine_timer_loop() -> asyncio.AbstractEventLoop:
    """An event loop whose timers wake within tens of microseconds of their time.

    asyncio's default selector on Linux (epoll) takes its timeout in whole milliseconds, rounded up: a
    400 Hz loop woke 0.8 ms late on median, a third of its tick, and lost slots. ``select()`` takes
    microseconds; a flight's loop waits on a few descriptors, far below select's limit of 1024
    (docs/design.md#honest-timing).
    """
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


def run_loop(main: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run`` on ``fine_timer_loop``: how every flight runs its loops."""
    with asyncio.Runner(loop_factory=fine_timer_loop) as runner:
        return runner.run(main)


class SimClock:
    """Lockstep virtual clock: time is the simulator's, and waiting steps the simulator."""

    lockstep = True

    def __init__(self, sim: Steppable) -> None:
        self._sim = sim

    def now(self) -> float:
        return self._sim.t

    async def sleep_until(self, t: float) -> None:
        if t > self._sim.t:
            self._sim.step_to(t)
        await asyncio.sleep(0)
