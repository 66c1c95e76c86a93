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

``python -m cfknode.app.ui.dashboard --demo`` flies a short simulated mission through
``cfknode.app.mission.run_flight`` with the dashboard (a test and a demo; ``--headless`` without).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import IO, Any, TypeVar

from rich.cells import cell_len
from rich.console import Console, ConsoleOptions, RenderResult
from rich.live import Live
from rich.segment import Segment
from rich.style import Style

from cfknode.app.ui.status import FlightStatus, TickStats

__all__ = [
    "DashboardStarter",
    "DashboardStats",
    "FrameMeter",
    "KeyReader",
    "KEY_HELP",
    "render_frame",
    "run_dashboard",
    "should_show_dashboard",
    "with_dashboard",
]

T = TypeVar("T")
KeyCallback = Callable[[str], None]
Line = list[tuple[str, Style | None]]

KEY_HELP = "space/q land (e-stop)   Ctrl-C land, twice stop"
_KEY_NAMES = {" ": "space", "\x1b": "escape", "\r": "enter", "\n": "enter", "\x7f": "backspace"}

_BORDER = Style(color="blue")
_TITLE = Style(bold=True)
_LABEL = Style(dim=True)
_VALUE = None
_GOOD = Style(color="green")
_WARN = Style(color="yellow", bold=True)
_BAD = Style(color="red", bold=True)
_NA = Style(dim=True, italic=True)
_HEADER = Style(bold=True, color="white", bgcolor="blue")
_STATE_STYLES = {
    "TRACK": _GOOD, "TAKEOFF": Style(color="cyan"), "LAND": Style(color="cyan"), "LANDED": _GOOD,
    "IDLE": _LABEL, "PREFLIGHT": Style(color="cyan"), "EMERGENCY": Style(color="white", bgcolor="red", bold=True),
}
_LEVEL_STYLES = {"warning": _WARN, "error": _BAD, "critical": _BAD, "debug": _LABEL}


# --- Frame layout ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Panel:
    title: str
    lines: tuple[Line, ...]
    width: int  # natural content width, cells
    full_row: bool = False  # takes a row of its own, stretched to the screen width
    optional: bool = False  # dropped first when the frame is taller than the screen


def _panel(title: str, lines: Sequence[Line], full_row: bool = False, optional: bool = False) -> _Panel:
    width = max([cell_len(title) + 2, *(sum(cell_len(text) for text, _ in line) for line in lines)])
    return _Panel(title, tuple(lines), width, full_row, optional)


class DashboardFrame:
    """One frame: a header line, panels packed into rows to fit the width, a key-help line."""

    def __init__(self, header: Line, panels: Sequence[_Panel], footer: Line) -> None:
        self.header = header
        self.panels = tuple(panels)
        self.footer = footer

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        width = max(20, options.max_width)
        height = options.height or console.height
        panels = list(self.panels)
        rows = _pack(panels, width)
        # Drop optional panels (the event list) rather than let the screen crop the key help.
        while sum(_row_height(r) for r in rows) + 2 > height and any(p.optional for p in panels):
            panels.remove(next(p for p in reversed(panels) if p.optional))
            rows = _pack(panels, width)
        yield from _line_segments(self.header, width, _HEADER)
        for row in rows:
            yield from _row_segments(row, width)
        yield from _line_segments(self.footer, width, None)


def _pack(panels: Sequence[_Panel], width: int) -> list[list[_Panel]]:
    rows: list[list[_Panel]] = []
    row: list[_Panel] = []
    used = 0
    for panel in panels:
        outer = panel.width + 4
        if panel.full_row or (row and used + 1 + outer > width):
            if row:
                rows.append(row)
            row, used = [], 0
        row.append(panel)
        used += outer + (1 if len(row) > 1 else 0)
        if panel.full_row:
            rows.append(row)
            row, used = [], 0
    if row:
        rows.append(row)
    return rows


def _row_height(row: Sequence[_Panel]) -> int:
    return max(len(p.lines) for p in row) + 2


def _row_segments(row: Sequence[_Panel], width: int) -> Iterable[Segment]:
    # Widths: natural content widths, the spare cells shared out so the row spans the screen.
    widths = [p.width for p in row]
    spare = width - sum(w + 4 for w in widths) - (len(row) - 1)
    if spare > 0:
        for i in range(len(widths)):
            widths[i] += spare // len(row) + (1 if i < spare % len(row) else 0)
    elif len(row) == 1:
        widths[0] = max(1, width - 4)
    height = _row_height(row) - 2
    for i, panel in enumerate(row):
        if i:
            yield Segment(" ")
        title = f" {panel.title} "[: max(0, widths[i])]
        yield Segment("╭─", _BORDER)
        yield Segment(title, _TITLE)
        yield Segment("─" * max(0, widths[i] + 1 - cell_len(title)) + "╮", _BORDER)
    yield Segment.line()
    for k in range(height):
        for i, panel in enumerate(row):
            if i:
                yield Segment(" ")
            yield Segment("│ ", _BORDER)
            line = panel.lines[k] if k < len(panel.lines) else []
            yield from Segment.adjust_line_length([Segment(text, style) for text, style in line], widths[i])
            yield Segment(" │", _BORDER)
        yield Segment.line()
    for i, _ in enumerate(row):
        if i:
            yield Segment(" ")
        yield Segment("╰" + "─" * (widths[i] + 2) + "╯", _BORDER)
    yield Segment.line()


def _line_segments(line: Line, width: int, pad_style: Style | None) -> Iterable[Segment]:
    yield from Segment.adjust_line_length([Segment(text, style) for text, style in line], width, pad_style)
    yield Segment.line()


# --- Panel contents ----------------------------------------------------------------------------


def _num(value: float, fmt: str, unit: str = "") -> tuple[str, Style | None]:
    if value is None or not math.isfinite(value):
        return ("n/a", _NA)
    return (f"{value:{fmt}}{unit}", _VALUE)


def _kv(label: str, *values: tuple[str, Style | None], width: int = 9) -> Line:
    return [(f"{label:<{width}}", _LABEL), *values]


def render_frame(status: FlightStatus, wall_now: float, key_error: str | None = None) -> DashboardFrame:
    """The dashboard for ``status`` now (``wall_now`` = ``time.perf_counter()``)."""
    stats = status.tick_stats(wall_now)
    header: Line = [(" cfknode ", _HEADER), (f" {status.title} " if status.title else "", _HEADER),
                    (f" t {status.t:7.2f} s ", _HEADER)]
    if math.isfinite(stats.speed_factor):
        header.append((f" {stats.speed_factor:5.1f}x real time ", _HEADER))
    if stats.since_last_tick_s > 0.5:
        header.append((f" no tick for {stats.since_last_tick_s:.1f} s ", Style(color="white", bgcolor="red")))
    panels = [
        _supervisor_panel(status),
        _tracking_panel(status),
        _loop_panel(status, stats),
        _models_panel(status),
        _trainer_panel(status),
        _link_panel(status),
        _events_panel(status),
    ]
    footer: Line = [(" Keys ", Style(reverse=True, bold=True)), (f"  {KEY_HELP}", _LABEL)]
    if key_error:
        footer.append((f"  key handler failed: {key_error}", _BAD))
    if status.poll_error:
        footer.append((f"  {status.poll_error}", _WARN))
    return DashboardFrame(header, panels, footer)


def _supervisor_panel(s: FlightStatus) -> _Panel:
    state = s.supervisor_state
    margin = s.geofence_margin_m
    fence_style = _BAD if margin < 0 else (_WARN if margin < 0.2 else _VALUE)
    return _panel("Supervisor", [
        _kv("state", (state, _STATE_STYLES.get(state, _NA if state == "n/a" else _VALUE))),
        _kv("command", (s.command_source or "n/a", _WARN if s.command_source == "fallback" else _VALUE)),
        _kv("Geofence", (_num(margin, "+.2f", " m")[0], fence_style if math.isfinite(margin) else _NA)),
        _kv("Battery", _num(s.battery_v, ".2f", " V")),
    ])


def _tracking_panel(s: FlightStatus) -> _Panel:
    p, r = s.position, s.reference
    lines: list[Line] = [[("    pos m    ref m   err mm", _LABEL)]]
    norm_sq = 0.0
    for i, axis in enumerate("xyz"):
        err_mm = (float(p[i]) - float(r[i])) * 1e3
        norm_sq += err_mm * err_mm
        lines.append([(f"{axis} ", _LABEL), _num(float(p[i]), "+8.3f"), (" ", None), _num(float(r[i]), "+8.3f"),
                      (" ", None), _num(err_mm, "+8.1f")])
    norm = math.sqrt(norm_sq)
    return _panel("Tracking" + (f" |e| {norm:.1f} mm" if math.isfinite(norm) else ""), lines)


def _loop_panel(s: FlightStatus, st: TickStats) -> _Panel:
    return _panel("Loop & MPC", [
        _kv("rate", _num(st.loop_rate_hz, ".0f", " Hz"), ("  ", None), _num(st.wall_rate_hz, ".0f", "/s wall")),
        _kv("tick", _num(st.compute_median_ms, ".2f"), (" / ", _LABEL), _num(st.compute_p99_ms, ".2f", " ms"),
            (" med/p99", _LABEL)),
        _kv("missed", (f"{s.missed_deadlines}", _WARN if s.missed_deadlines else _VALUE),
            (f" of {s.ticks} ticks", _LABEL)),
        _kv("MPC", _num(st.solve_median_ms, ".2f"), (" / ", _LABEL), _num(st.solve_p99_ms, ".2f", " ms"),
            ("  fallback ", _LABEL), (f"{s.fallbacks}", _WARN if s.fallbacks else _VALUE)),
    ])


def _models_panel(s: FlightStatus) -> _Panel:
    lines: list[Line] = [[("ver   age s  weight  val err", _LABEL)]]
    for entry in s.models[::-1]:  # newest first; * marks the version flying
        flying = entry.version == s.model_version
        lines.append([(f"{'*' if flying else ' '}v{entry.version:<4d}", _GOOD if flying else _VALUE),
                      _num(s.t - entry.created_t, "6.1f"), (" ", None), _num(entry.weight, "7.3f"), (" ", None),
                      _num(entry.val_error, "8.2g")])
    if not s.models:
        lines.append([("nominal model, no networks", _NA)])
    lines.append([("swaps ", _LABEL), (f"{s.model_swaps}", None), (" rejects ", _LABEL),
                  (f"{s.model_rejects}", _WARN if s.model_rejects else None), (" rollbacks ", _LABEL),
                  (f"{s.model_rollbacks}", _BAD if s.model_rollbacks else None)])
    return _panel("Model queue", lines)


def _trainer_panel(s: FlightStatus) -> _Panel:
    state_style = {"training": _GOOD, "running": _GOOD, "off": _NA, "failed": _BAD, "crashed": _BAD,
                   "restarting": _WARN}.get(s.trainer_state, _VALUE)
    return _panel("Trainer", [
        _kv("state", (s.trainer_state, state_style)),
        _kv("loss", _num(s.trainer_last_loss, ".3g")),
        _kv("windows", (f"{s.windows_accepted}", None), (" ok  ", _LABEL),
            (f"{s.windows_rejected}", _WARN if s.windows_rejected else None), (" rejected", _LABEL)),
    ])


def _link_panel(s: FlightStatus) -> _Panel:
    ack = s.radio_ack_rate * 100.0 if math.isfinite(s.radio_ack_rate) else math.nan
    sent: Line = _kv("", (f"{s.setpoints_sent}", None), (" setpoints sent", _LABEL))
    if s.radio_errors:
        sent.append((f"  {s.radio_errors} errors", _WARN))
    lines = [
        _kv("Mocap", _num(s.mocap_rate_hz, ".0f", " Hz"), ("  ", None),
            (f"{s.mocap_dropouts}", _WARN if s.mocap_dropouts else None), (" dropouts", _LABEL)),
        _kv("Radio", _num(s.radio_latency_ms, ".1f", " ms"), ("  acks ", _LABEL), _num(ack, ".1f", " %")),
        sent,
    ]
    if s.link_lost:
        lines.append(_kv("", (f"LINK LOST: {s.link_lost}", _BAD)))
    return _panel("Mocap & radio", lines)


def _events_panel(s: FlightStatus) -> _Panel:
    lines: list[Line] = [
        [(f"{e.t:7.2f} s ", _LABEL), (f"{e.level:<8} ", _LEVEL_STYLES.get(e.level, None)), (e.text, None)]
        for e in list(s.events)[-4:]
    ]
    return _panel("Events", lines or [[("none", _NA)]], full_row=True, optional=True)


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


async def run_dashboard(
    status: FlightStatus,
    stop_event: asyncio.Event,
    console: Console,
    on_key: KeyCallback | None = None,
    refresh_hz: float = 10.0,
    budget: float = 0.02,
    key_stream: IO[str] | None = None,
    meter: FrameMeter | None = None,
) -> DashboardStats:
    """Draw ``status`` at ``refresh_hz`` until ``stop_event`` is set, then draw a last frame and return.

    ``on_key`` receives key names from ``key_stream`` (default stdin) while the dashboard runs.
    ``budget`` is the largest share of wall time frames may take; costlier frames are spaced out.
    ``meter`` collects the frame costs (one is made if not given).
    """
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
                live.update(render_frame(status, start, keys.error if keys else None), refresh=True)
                cost = time.perf_counter() - start
                meter.costs.append(cost)
                recent.append(cost)
                # Keep frames under the budget share of wall time. The median of recent frames
                # decides, so one frame preempted by the OS does not freeze the view.
                period = max(1.0 / refresh_hz, sorted(recent)[len(recent) // 2] / budget)
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
                    live.update(render_frame(status, start, keys.error if keys else None), refresh=True)
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
    task = asyncio.create_task(run_dashboard(status, stop, console, on_key, refresh_hz))
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
                self._status, asyncio.Event(), self._console, self._on_key, self._refresh_hz, meter=self.meter))

    @property
    def stats(self) -> DashboardStats:
        return self.meter.stats()


# --- Demo: a short simulated flight with the dashboard ---------------------------------------

DEMO_OVERRIDES = {
    "trajectory.duration": 4.0,
    "trajectory.takeoff_duration": 2.0,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 2.0,
    "trajectory.ramp_duration": 1.0,
}


def _demo(argv: Sequence[str] | None = None) -> int:
    """Fly a short simulated circle through ``cfknode.app.mission.run_flight`` with the dashboard.

    The status and a ``DashboardStarter`` are passed as tick observers, so it needs nothing
    of the mission beyond its ``observers`` argument. Prints one line of timings at the end.
    """
    import numpy as np

    from cfknode.app.config import load_config, parse_override
    from cfknode.app.mission import run_flight

    parser = argparse.ArgumentParser(prog="python -m cfknode.app.ui.dashboard", description=_demo.__doc__)
    parser.add_argument("--demo", action="store_true", required=True, help="fly the demo flight")
    parser.add_argument("--headless", action="store_true", help="fly without the dashboard")
    parser.add_argument("--log-dir", default="flights", help="directory for the flight log")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    args = parser.parse_args(argv)
    cfg = load_config(overrides={**DEMO_OVERRIDES, "log.dir": args.log_dir, **dict(map(parse_override, args.set))})
    console = Console()
    t = cfg.trajectory
    status = FlightStatus(cfg.controller.rate_hz, title=f"{t.kind} r={t.radius} m · {cfg.controller.kind} "
                          f"({cfg.controller.solver}) · {'realtime' if cfg.sim.realtime else 'lockstep'} demo")

    def on_key(name: str) -> None:
        # The safety supervisor owns the action; the demo shows that the key arrived.
        status.add_event(status.t, "warning", f"key {name!r} pressed: e-stop requested")

    starter = None
    if should_show_dashboard(args, console.file, cfg.dashboard.enabled):
        starter = DashboardStarter(status, console, on_key, cfg.dashboard.refresh_hz)
    result = run_flight(cfg, name_hint="dashboard-demo", observers=[status, *([starter] if starter else [])])
    if starter is not None:
        dash = starter.stats
        console.print(f"dashboard: {dash.frames} frames, {dash.median_frame_ms:.2f} ms median, "
                      f"{dash.max_frame_ms:.2f} ms max, every {dash.period_s * 1e3:.0f} ms", highlight=False)
    record = result.record
    compute_ms = record.compute_s * 1e3
    duration = float(record.t[-1] - record.t[0]) if record.ticks else 0.0
    console.print(
        f"demo flight: {record.ticks} ticks, speed {duration / record.wall_time:.2f}x real time, "
        f"tick median {np.median(compute_ms):.3f} ms, p99 {np.percentile(compute_ms, 99):.3f} ms, "
        f"missed {int(record.missed.sum())}, log {result.summary.log_path}",
        soft_wrap=True,
        highlight=False,
    )
    return 0


if __name__ == "__main__":
    sys.exit(_demo())
