"""The live terminal dashboard: a rich ``Live`` view of a ``FlightStatus``, and the operator keys.

It runs as its own asyncio task beside the flight loop, on the same event loop, and must
not disturb it. So a frame is cheap: the panels are laid out here as rich ``Segment`` lines
(0.2 ms a frame where rich Panels in a Table grid took 2.3 ms; 1 to 2 ms in a pseudo-terminal
on a busy machine, statistics and the terminal write included), the refresh is manual (no
rich refresh thread competing for the GIL with the loop), and if frames ever cost more than
``budget`` of the wall time, they are spaced out to keep within it. In lockstep the loop
yields with ``asyncio.sleep(0)`` every tick, which lets the event loop run due timers, so the
dashboard still draws at its wall-clock rate.

Keys are read in cbreak mode (no echo, no line buffering, Ctrl-C still a signal) through
``loop.add_reader`` (no thread) and reported to a callback; the terminal is restored on every
exit path that runs Python code (return, exception, cancellation, Ctrl-C). A process killed
by SIGKILL cannot restore it; ``stty sane`` does.

``python -m cfknode.app.commands.dashboard_demo --demo`` flies a short simulated mission with
this dashboard (a test and a demo); it lives above the mission, which this module serves.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import IO, Any, TypeVar

from rich.console import Console
from rich.live import Live
from rich.style import Style

from cfknode.app.ui.status import FlightStatus

__all__ = [
    "DashboardStarter",
    "DashboardStats",
    "FrameMeter",
    "KeyReader",
    "Pace",
    "KEY_HELP",
    "render_frame",
    "run_dashboard",
    "should_show_dashboard",
    "with_dashboard",
]

T = TypeVar("T")
KeyCallback = Callable[[str], None]
Render = Callable[[Any, float, "str | None"], Any]  # (status, wall_now, key_error) -> a rich renderable
Line = list[tuple[str, Style | None]]

from cfknode.app.ui.frame import (  # noqa: F401 (re-exported)
    DashboardFrame,
    KEY_HELP,
    _BAD,
    _BORDER,
    _GOOD,
    _HEADER,
    _KEY_NAMES,
    _LABEL,
    _LEVEL_STYLES,
    _NA,
    _Panel,
    _STATE_STYLES,
    _TITLE,
    _VALUE,
    _WARN,
    _events_panel,
    _kv,
    _line_segments,
    _link_panel,
    _loop_panel,
    _models_panel,
    _num,
    _pack,
    _panel,
    _row_height,
    _row_segments,
    _supervisor_panel,
    _tracking_panel,
    _trainer_panel,
    render_frame,
)


# --- Keys --------------------------------------------------------------------------------------


class KeyReader:
    """Reports key presses on a terminal to ``on_key(name)``: "space", "q", "escape", "enter", or the character.

    A context manager: entering puts the terminal in cbreak mode and registers the file
    descriptor with the running event loop; leaving restores the saved terminal settings.
    Not a terminal (or no termios, e.g. Windows): it does nothing, and ``active`` is False.
    An exception from ``on_key`` is kept in ``error`` (and shown), never raised into the loop.
    """

    def __init__(self, stream: IO[str] | IO[bytes], on_key: KeyCallback) -> None:
        self._stream = stream
        self._on_key = on_key
        self._fd: int | None = None
        self._saved: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.error: str | None = None

    @property
    def active(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> KeyReader:
        try:
            import termios
            import tty

            fd = self._stream.fileno()
            if not os.isatty(fd):
                return self
            saved = termios.tcgetattr(fd)
        except (ImportError, AttributeError, OSError, ValueError):
            return self
        loop = asyncio.get_running_loop()
        tty.setcbreak(fd, termios.TCSANOW)
        try:
            loop.add_reader(fd, self._readable)
        except BaseException:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)
            raise
        self._fd, self._saved, self._loop = fd, saved, loop
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop reading and restore the terminal. Idempotent."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        import termios

        try:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(fd)
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, self._saved)

    def _readable(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, 64)
        except OSError:
            data = b""
        if not data:  # end of input (the terminal went away): stop watching it
            if self._loop is not None:
                self._loop.remove_reader(self._fd)
            return
        for char in data.decode(errors="replace"):
            try:
                self._on_key(_KEY_NAMES.get(char, char))
            except Exception as exc:  # an operator key must never kill the event loop
                self.error = f"{type(exc).__name__}: {exc}"


# --- The dashboard task ------------------------------------------------------------------------


@dataclass(frozen=True)
class DashboardStats:
    """What the dashboard cost: frames drawn and their wall time (render + terminal write)."""

    frames: int
    median_frame_ms: float
    max_frame_ms: float
    period_s: float  # the refresh period in the end (longer than asked if frames were costly)


class FrameMeter:
    """Frame costs of a dashboard run, readable even when the task was cancelled."""

    def __init__(self) -> None:
        self.costs: list[float] = []
        self.period_s = math.nan

    def stats(self) -> DashboardStats:
        ms = sorted(c * 1e3 for c in self.costs)
        if not ms:
            return DashboardStats(0, math.nan, math.nan, self.period_s)
        return DashboardStats(len(ms), ms[len(ms) // 2], ms[-1], self.period_s)


def should_show_dashboard(args: argparse.Namespace, stream: IO[str], enabled: bool = True) -> bool:
    """On by default in a terminal; off with ``--headless``, when ``enabled`` is False, or off a TTY."""
    if getattr(args, "headless", False) or not enabled:
        return False
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty()) and os.environ.get("TERM") != "dumb"


@dataclass(frozen=True)
class Pace:
    """How often the dashboard draws: ``refresh_hz`` at most, and frames within ``budget`` of wall time."""

    refresh_hz: float = 10.0
    budget: float = 0.02


async def run_dashboard(
    status: Any,
    stop_event: asyncio.Event,
    console: Console,
    on_key: KeyCallback | None = None,
    pace: Pace = Pace(),
    key_stream: IO[str] | None = None,
    meter: FrameMeter | None = None,
    render: Render = render_frame,
) -> DashboardStats:
    """Draw ``status`` at ``pace.refresh_hz`` until ``stop_event`` is set, then draw a last frame and return.

    ``on_key`` receives key names from ``key_stream`` (default stdin) while the dashboard runs.
    ``pace.budget`` is the largest share of wall time frames may take; costlier frames are spaced out.
    ``meter`` collects the frame costs (one is made if not given). ``render(status, wall_now,
    key_error)`` lays out a frame: any status with a ``poll()`` works with its own renderer
    (the fleet's view, cfknode/app/ui/fleet_dashboard.py).
    """
    refresh_hz, budget = pace.refresh_hz, pace.budget
    if refresh_hz <= 0:
        raise ValueError(f"refresh_hz must be > 0, got {refresh_hz}")
    period = 1.0 / refresh_hz
    meter = meter or FrameMeter()
    recent: deque[float] = deque(maxlen=10)
    keys = KeyReader(key_stream or sys.stdin, on_key) if on_key is not None else None
    live = Live(console=console, auto_refresh=False, transient=False, redirect_stdout=True, redirect_stderr=True)
    with live:
        try:
            if keys is not None:
                keys.__enter__()
            while True:
                start = time.perf_counter()
                status.poll()
                live.update(render(status, start, keys.error if keys else None), refresh=True)
                cost = time.perf_counter() - start
                meter.costs.append(cost)
                if len(meter.costs) > 1:  # the first frame pays one-off costs (rich's caches), not a rate
                    recent.append(cost)
                # Keep frames under the budget share of wall time. The median of recent frames
                # decides, so one frame preempted by the OS does not freeze the view.
                period = max(1.0 / refresh_hz, sorted(recent)[len(recent) // 2] / budget) if recent else 1.0 / refresh_hz
                meter.period_s = period
                if stop_event.is_set():
                    break
                try:
                    await asyncio.wait_for(stop_event.wait(), timeout=period)
                except TimeoutError:
                    pass
                except asyncio.CancelledError:
                    # Cancelled with its event loop (asyncio.run ending): leave the last state on screen.
                    start = time.perf_counter()
                    live.update(render(status, start, keys.error if keys else None), refresh=True)
                    meter.costs.append(time.perf_counter() - start)
                    raise
        finally:
            if keys is not None:
                keys.close()
    return meter.stats()


async def with_dashboard(
    flight: Awaitable[T],
    status: FlightStatus,
    console: Console,
    on_key: KeyCallback | None = None,
    refresh_hz: float = 10.0,
    on_error: Callable[[BaseException], None] | None = None,
) -> T:
    """Await ``flight`` (e.g. ``fly(parts)``) with the dashboard drawing beside it; its result.

    ``on_error(exc)``: the dashboard raised. It is called as soon as that happens and the
    flight goes on without a dashboard; without it the error is raised once the flight ends.
    """
    stop = asyncio.Event()
    task = asyncio.create_task(run_dashboard(status, stop, console, on_key, Pace(refresh_hz)))
    if on_error is not None:
        task.add_done_callback(lambda done: _report_failure(done, on_error))
    try:
        return await flight
    finally:
        stop.set()
        try:
            await task
        except Exception:
            if on_error is None:
                raise


def _report_failure(task: asyncio.Task[Any], on_error: Callable[[BaseException], None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        on_error(task.exception())


class DashboardStarter:
    """A loop ``TickObserver`` that starts the dashboard task on the loop's event loop at the first tick.

    For a flight whose coroutine cannot be wrapped in ``with_dashboard`` (``mission.run_flight``
    runs its own ``asyncio.run``): pass it with the status as observers. The task ends when
    that event loop closes (cancelled, after drawing a last frame).
    """

    def __init__(self, status: FlightStatus, console: Console, on_key: KeyCallback | None = None,
                 refresh_hz: float = 10.0) -> None:
        self._status, self._console, self._on_key, self._refresh_hz = status, console, on_key, refresh_hz
        self._task: asyncio.Task[DashboardStats] | None = None
        self.meter = FrameMeter()

    def on_tick(self, tick: Any) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(run_dashboard(
                self._status, asyncio.Event(), self._console, self._on_key, Pace(self._refresh_hz), meter=self.meter))

    @property
    def stats(self) -> DashboardStats:
        return self.meter.stats()
