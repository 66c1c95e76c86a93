"""The live terminal view of a fleet flight (``cfknode fly --fleet N``): one row per drone, the worst on top.

Each drone gets a ``DroneStatus``, a tick observer of its flight loop that pays a few plain
stores and one histogram increment per tick; everything else (percentiles, the worst values,
battery, link, the fast adaptation's mass factor) is read at frame time, a few times a second,
by the single dashboard's refresher (``run_dashboard`` in dashboard.py, with this module's
renderer). The frame reuses the single dashboard's layout pieces (frame.py).

Values shown: the position error is the state estimate's, as on the single dashboard (the
flight summary's MSE uses the simulator's true positions, so the two differ slightly); the
pattern RMS and MSE are over the ticks so far inside the pattern window; the tick median and
p99 are over every tick so far, from a log-spaced histogram (40 bins a decade: within 3 %).
"""

from __future__ import annotations

import asyncio
import math
import re
from collections import deque
from collections.abc import Sequence
from typing import Any

from rich.console import Console
from rich.style import Style

from cfknode.app.ui.dashboard import DashboardStats, FrameMeter, Pace, run_dashboard
from cfknode.app.ui.frame import (
    _BAD,
    _HEADER,
    _LABEL,
    _LEVEL_STYLES,
    footer_line,
    _NA,
    _STATE_STYLES,
    _WARN,
    DashboardFrame,
    Line,
    _kv,
    _num,
    _panel,
    _Panel,
)
from cfknode.app.ui.status import StatusEvent

__all__ = ["DroneStatus", "FleetDashboard", "FleetStatus", "TickHistogram", "render_fleet_frame"]

FLEET_KEY_HELP = "space/q land every drone (e-stop)   Ctrl-C land all, twice stop"
_COORDINATOR_EVENT = re.compile(r"\s*([-+0-9.eE]+) s (\w+): (.*)", re.S)  # FleetCoordinator.events lines


class TickHistogram:
    """Tick compute times over a whole flight in fixed memory: log-spaced bins from 1 us to 10 s."""

    __slots__ = ("counts", "total")
    LOW = -6.0  # log10 of the first bin's lower edge, s
    PER_DECADE = 40
    BINS = 7 * PER_DECADE

    def __init__(self) -> None:
        self.counts = [0] * self.BINS
        self.total = 0

    def add(self, seconds: float) -> None:
        k = int((math.log10(seconds) - self.LOW) * self.PER_DECADE) if seconds > 0 else 0
        self.counts[0 if k < 0 else (k if k < self.BINS else self.BINS - 1)] += 1
        self.total += 1

    def quantile_ms(self, q: float) -> float:
        """The ``q`` quantile (0..1) in ms, as its bin's geometric centre; NaN before the first tick."""
        if self.total == 0:
            return math.nan
        need = q * self.total
        seen = 0
        for k, n in enumerate(self.counts):
            seen += n
            if n and seen >= need:
                return 10 ** (self.LOW + (k + 0.5) / self.PER_DECADE) * 1e3
        return math.nan


class DroneStatus:
    """One drone's row; the drone's ``TickObserver`` (``on_tick``). Slow fields come from ``poll()``."""

    __slots__ = (
        "name", "uri", "state", "t", "ticks", "position", "reference", "window", "hist", "_sq_sum", "_sq_n",
        "_version", "models_accepted", "battery_v", "link", "mass_factor", "_events", "_supervisor",
        "_controller", "_radio",
    )

    def __init__(self, name: str, uri: str, window: tuple[float, float] | None, events: deque[StatusEvent],
                 supervisor: Any = None, controller: Any = None, radio: Any = None) -> None:
        self.name, self.uri = name, uri
        self.state = "n/a"
        self.t = 0.0
        self.ticks = 0
        self.position: Any = None
        self.reference: Any = None
        self.window = window  # pattern window [t0, t1], flight time s (None: the whole flight)
        self.hist = TickHistogram()
        self._sq_sum = 0.0  # sum over pattern ticks of |error|^2, m^2
        self._sq_n = 0
        self._version = 0
        self.models_accepted = 0
        self.battery_v = math.nan
        self.link = "n/a"
        self.mass_factor = math.nan
        self._events = events
        self._supervisor, self._controller, self._radio = supervisor, controller, radio

    def on_tick(self, tick: Any) -> None:
        self.t = t = tick.t
        self.ticks += 1
        self.hist.add(tick.compute_s)
        state = tick.supervisor_state
        if state and state != self.state:
            self._transition(t, state)
        if tick.model_version > self._version:  # a newer model flies: one more accepted
            self._version = tick.model_version
            self.models_accepted += 1
        est = tick.est
        if est is not None:
            self.position, self.reference = est.p, tick.ref_p
            w = self.window
            if w is None or w[0] <= t <= w[1]:
                d = est.p - tick.ref_p
                self._sq_sum += float(d @ d)
                self._sq_n += 1

    def _transition(self, t: float, state: str) -> None:
        # Rare (a few per flight): the supervisor's cause is worth a snapshot here. The routine
        # way up (the first state, take-off, tracking) is no event; landings and stops are.
        old, self.state = self.state, state
        if old == "n/a" or state in ("PREFLIGHT", "TAKEOFF", "TRACK"):
            return
        cause = ""
        if self._supervisor is not None:
            try:
                cause = self._supervisor.snapshot().cause
            except Exception:  # noqa: BLE001 - display only
                cause = ""
        level = "error" if state == "EMERGENCY" else ("warning" if cause and cause != "complete" else "info")
        self._events.append(StatusEvent(t, level, f"{self.name} {old} -> {state}" + (f" ({cause})" if cause else "")))

    def poll(self) -> None:
        """Battery, link and the mass factor, read from the drone's parts at frame time."""
        if self._supervisor is not None:
            snap = self._supervisor.snapshot()
            self.battery_v = float(snap.battery_v)
            silence = float(snap.link_silence_s)
            self.link = f"silent {silence:.1f} s" if silence > 0.1 else "ok"
        if self._radio is not None:
            stats = self._radio.stats()
            if stats.link_lost:
                self.link = "LOST"
            elif stats.send_errors:
                self.link = f"{stats.send_errors} errors"
        adapt = getattr(self._controller, "adaptation", None)
        if adapt is not None:
            self.mass_factor = float(adapt.estimate.thrust_scale)

    def error_m(self) -> float:
        """|estimate - reference| now, m (NaN before the first state)."""
        if self.position is None:
            return math.nan
        d = self.position - self.reference
        return float(math.sqrt(float(d @ d)))

    def pattern_rms_m(self) -> float:
        return math.sqrt(self._sq_sum / self._sq_n) if self._sq_n else math.nan

    def pattern_mse_m2(self) -> float:
        """Mean over the axes of the mean squared error (the summary's MSE), on the pattern so far."""
        return self._sq_sum / (3 * self._sq_n) if self._sq_n else math.nan


class FleetStatus:
    """Every drone's ``DroneStatus``, the fleet's events and its closest approach; read by the frame."""

    def __init__(self, title: str = "", min_separation: float = 0.0, show_mass: bool = False,
                 show_models: bool = False, max_events: int = 6) -> None:
        self.title = title
        self.min_separation = min_separation
        self.show_mass, self.show_models = show_mass, show_models
        self.drones: list[DroneStatus] = []
        self.events: deque[StatusEvent] = deque(maxlen=max_events)
        self.closest_m = math.nan
        self.poll_error: str | None = None
        self._coordinator: Any = None
        self._seen_events = 0

    def add_drone(self, name: str, uri: str, window: tuple[float, float] | None = None, supervisor: Any = None,
                  controller: Any = None, radio: Any = None) -> DroneStatus:
        drone = DroneStatus(name, uri, window, self.events, supervisor, controller, radio)
        self.drones.append(drone)
        return drone

    def watch(self, coordinator: Any) -> None:
        """Read the fleet's own decisions and closest approach from a ``FleetCoordinator`` at frame time."""
        self._coordinator = coordinator

    def poll(self) -> None:
        """Before each frame: the drones' slow fields and the coordinator's new events; never raises."""
        try:
            for drone in self.drones:
                drone.poll()
            c = self._coordinator
            if c is not None:
                self.closest_m = float(c.watch.closest)
                for line in c.events[self._seen_events:]:
                    self.events.append(_coordinator_event(line))
                self._seen_events = len(c.events)
        except Exception as exc:  # a display source must never take the dashboard down
            self.poll_error = f"{type(exc).__name__}: {exc}"

    @property
    def t(self) -> float:
        return max((d.t for d in self.drones), default=0.0)


def _coordinator_event(line: str) -> StatusEvent:
    m = _COORDINATOR_EVENT.match(line)
    if m is None:
        return StatusEvent(math.nan, "info", line)
    return StatusEvent(float(m.group(1)), m.group(2), m.group(3))


# --- The frame ---------------------------------------------------------------------------------


def render_fleet_frame(status: FleetStatus, wall_now: float, key_error: str | None = None) -> DashboardFrame:
    """The fleet view now: a header, the fleet's worst values, one row per drone, recent events."""
    header: Line = [(" cfknode fleet ", _HEADER), (f" {status.title} " if status.title else "", _HEADER),
                    (f" t {status.t:7.2f} s ", _HEADER)]
    panels = [_worst_panel(status), _drones_panel(status), _fleet_events_panel(status)]
    return DashboardFrame(header, panels, footer_line(FLEET_KEY_HELP, key_error, status.poll_error))


def _worst(drones: Sequence[DroneStatus], value: Any) -> tuple[DroneStatus | None, float]:
    best: tuple[DroneStatus | None, float] = (None, math.nan)
    for d in drones:
        v = value(d)
        if math.isfinite(v) and not v <= best[1]:  # NaN best: any finite value wins
            best = (d, v)
    return best


def _worst_panel(s: FleetStatus) -> _Panel:
    err_d, err = _worst(s.drones, DroneStatus.error_m)
    p99_d, p99 = _worst(s.drones, lambda d: d.hist.quantile_ms(0.99))
    closest = s.closest_m
    close_style = _BAD if s.min_separation > 0 and closest < s.min_separation else None
    off = [d for d in s.drones if d.state != "TRACK"]
    off_line: Line = _kv("not TRACK", width=11)
    for d in off:
        off_line += [(d.name, None), (" ", None), (d.state, _STATE_STYLES.get(d.state, _NA)), ("  ", None)]
    if not off:
        off_line.append(("none: every drone tracks", _STATE_STYLES["TRACK"]))
    return _panel(f"Fleet of {len(s.drones)}: worst", [
        _kv("error now", _num(err * 1e3, ".1f", " mm"), (f"  {err_d.name}" if err_d else "", _LABEL), width=11),
        _kv("tick p99", _num(p99, ".2f", " ms"), (f"  {p99_d.name}" if p99_d else "", _LABEL), width=11),
        _kv("closest", (_num(closest, ".3f", " m")[0], close_style if math.isfinite(closest) else _NA),
            (f"  (minimum {s.min_separation:g} m)" if s.min_separation > 0 else "", _LABEL), width=11),
        off_line,
    ], full_row=True)


def _drones_panel(s: FleetStatus) -> _Panel:
    head = f"{'drone':<6}{'uri':<10}{'state':<10}{'err mm':>7}{'rms mm':>8}{'mse m2':>9}{'tick ms':>8}{'p99':>7}"
    head += f"{'mass':>6}" if s.show_mass else ""
    head += f"{'models':>7}" if s.show_models else ""
    head += f"{'batt V':>7}  link"
    lines: list[Line] = [[(head, _LABEL)]]
    for d in s.drones:
        p99 = d.hist.quantile_ms(0.99)
        line: Line = [(f"{d.name:<6.6}", None), (f"{d.uri:<10.10}", _LABEL),
                      (f"{d.state:<10.10}", _STATE_STYLES.get(d.state, _NA)),
                      _cell(d.error_m() * 1e3, 7, ".1f"), _cell(d.pattern_rms_m() * 1e3, 8, ".2f"),
                      _cell(d.pattern_mse_m2(), 9, ".1e"), _cell(d.hist.quantile_ms(0.5), 8, ".2f"),
                      _cell(p99, 7, ".2f")]
        if s.show_mass:
            line.append(_cell(d.mass_factor, 6, ".2f"))
        if s.show_models:
            line.append((f"{d.models_accepted:>7d}", None))
        line.append(_cell(d.battery_v, 7, ".2f"))
        line.append((f"  {d.link}", _BAD if d.link == "LOST" else (_WARN if d.link != "ok" else None)))
        lines.append(line)
    return _panel("Drones (pattern RMS/MSE and tick times so far)", lines, full_row=True)


def _cell(value: float, width: int, fmt: str) -> tuple[str, Style | None]:
    text, style = _num(value, fmt)
    return (f"{text:>{width}}", style)


def _fleet_events_panel(s: FleetStatus) -> _Panel:
    lines: list[Line] = [
        [(f"{e.t:7.2f} s " if math.isfinite(e.t) else " " * 10, _LABEL),
         (f"{e.level:<8} ", _LEVEL_STYLES.get(e.level, None)), (e.text, None)]
        for e in sorted(s.events, key=lambda e: e.t if math.isfinite(e.t) else math.inf)
    ]
    return _panel("Fleet events", lines or [[("none", _NA)]], full_row=True, optional=True)


# --- Wiring into a fleet flight ---------------------------------------------------------------


class FleetDashboard:
    """The fleet view for ``run_fleet(..., dashboard=)``: per drone, ``observers(...)`` gives its tick observers.

    The first drone's observers also start the refresher on the flight's event loop at its first
    tick; it draws a last frame when that loop ends. A refresher that fails is kept in ``error``
    and the flight goes on without it. Space or q lands every drone.
    """

    def __init__(self, console: Console, status: FleetStatus, refresh_hz: float = 10.0) -> None:
        self.console, self.status, self.refresh_hz = console, status, refresh_hz
        self.meter = FrameMeter()
        self.error: str | None = None
        self._supervisors: list[Any] = []
        self._task: asyncio.Task[DashboardStats] | None = None

    def observers(self, i: int, drone: Any, reference: Any, controller: Any, supervisor: Any,
                  coordinator: Any) -> list[Any]:
        """Drone ``i``'s observers: its row (fed every tick) and, for the first, the refresher's starter.

        ``drone``: a ``FleetDrone`` (name, URI, radio); ``reference``: its trajectory (the pattern
        window); ``controller``, ``supervisor``: read at frame time; ``coordinator``: the fleet's
        ``FleetCoordinator`` (its events and closest approach).
        """
        if i == 0:
            self.status.watch(coordinator)
        self._supervisors.append(supervisor)
        row = self.status.add_drone(drone.name, drone.config.radio.uri, getattr(reference, "pattern_window", None),
                                    supervisor, controller, drone.radio)
        return [row, self] if i == 0 else [row]

    def on_tick(self, tick: Any) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(run_dashboard(
                self.status, asyncio.Event(), self.console, self._on_key, Pace(self.refresh_hz), meter=self.meter,
                render=render_fleet_frame))
            self._task.add_done_callback(self._done)

    def _on_key(self, key: str) -> None:
        if key in ("space", "q"):
            for sup in self._supervisors:
                sup.request_land(f"operator e-stop key ({key})")

    def _done(self, task: asyncio.Task[DashboardStats]) -> None:
        if not task.cancelled() and task.exception() is not None:
            exc = task.exception()
            self.error = f"{type(exc).__name__}: {exc}"

    @property
    def stats(self) -> DashboardStats:
        return self.meter.stats()
