"""The live flight status: a mutable snapshot the loop writes and the dashboard reads.

Writers pay only plain attribute stores: the 400 Hz loop calls ``on_tick`` once per tick, as a
``TickObserver``, after the tick's compute time is measured. Everything statistical (tick
compute median and p99, loop rate, speed factor) is computed lazily by the reader from
fixed-size ring buffers, at the reader's rate. What other parts publish on the flight log
(supervisor state, model events) arrives through ``StatusTap``, a wrapper around the log.

Concurrency: the loop and the dashboard are tasks of one asyncio event loop, so they never
run at the same time and no lock is needed. A writer on another thread (a trainer-result
receiver, the radio's TX thread) is also safe: each attribute store is atomic under the GIL,
and slow fields are replaced whole (``models`` is a new tuple, never mutated in place). A
reader may then see fields from neighbouring ticks (a position one tick newer than its
reference): harmless for display, which is all this object is for. Never control from it.

Slow sources (mocap statistics, radio statistics, battery) need no per-tick writes at all:
register a poller with ``add_poller``; the reader calls ``poll()`` before each frame.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol

import numpy as np

__all__ = [
    "FlightStatus",
    "ModelEntry",
    "StatusEvent",
    "StatusTap",
    "TickStats",
    "battery_poller",
    "mocap_poller",
    "radio_poller",
]

_NAN3 = (math.nan, math.nan, math.nan)
_TRAINER_EVENTS = {"crash": "crashed", "restart": "restarting"}  # /model events about the trainer process


@dataclass(frozen=True)
class ModelEntry:
    """One network of the KNODE queue, as the dashboard shows it."""

    version: int
    created_t: float  # flight time it joined the queue, s (age = now - created_t)
    weight: float  # forgetting weight in the queue sum (newest 1)
    val_error: float = math.nan  # validation error at acceptance, NaN if unknown


@dataclass(frozen=True)
class StatusEvent:
    t: float
    level: str  # debug, info, warning, error, critical (as on the log's /events channel)
    text: str


@dataclass(frozen=True)
class TickStats:
    """Statistics over the newest ``window`` ticks (NaN when there are too few)."""

    window: int
    compute_median_ms: float
    compute_p99_ms: float
    solve_median_ms: float  # over ticks that ran a solve
    solve_p99_ms: float
    loop_rate_hz: float  # ticks per flight-clock second
    wall_rate_hz: float  # ticks per wall second (above loop_rate_hz in lockstep)
    speed_factor: float  # flight seconds per wall second over the window
    since_last_tick_s: float  # wall time since the newest tick (a hung loop shows here)


class FlightStatus:
    """Every dashboard field, and a ``TickObserver`` of the loop (``on_tick``).

    Defaults say "not available" (NaN, None, "n/a", "off") until a part sets them.
    """

    __slots__ = (
        "title", "nominal_rate_hz", "t", "ticks", "position", "reference", "command_source",
        "missed_deadlines", "fallbacks", "supervisor_state", "mocap_rate_hz", "mocap_frames",
        "mocap_dropouts", "radio_latency_ms", "radio_ack_rate", "setpoints_sent", "radio_errors",
        "link_lost", "battery_v", "geofence_margin_m", "models", "model_version", "model_swaps",
        "model_rejects", "model_rollbacks", "trainer_state", "trainer_last_loss", "windows_accepted",
        "windows_rejected", "poll_error", "events", "_size", "_next", "_t", "_wall", "_compute",
        "_solve", "_pollers", "layer",
    )

    def __init__(self, nominal_rate_hz: float = 400.0, window: int = 800, title: str = "") -> None:
        if window < 2:
            raise ValueError(f"window must be >= 2 ticks, got {window}")
        self.title = title
        self.nominal_rate_hz = nominal_rate_hz
        # Tracking and loop (written every tick by record_tick).
        self.t = 0.0
        self.ticks = 0
        self.position: np.ndarray | tuple[float, float, float] = _NAN3
        self.reference: np.ndarray | tuple[float, float, float] = _NAN3
        self.command_source = ""
        self.missed_deadlines = 0
        self.fallbacks = 0
        # Safety supervisor; "n/a" until one exists.
        self.supervisor_state = "n/a"
        # Sensors and link (usually from pollers).
        self.mocap_rate_hz = math.nan
        self.mocap_frames = 0
        self.mocap_dropouts = 0
        self.radio_latency_ms = math.nan
        self.radio_ack_rate = math.nan  # 0..1
        self.setpoints_sent = 0
        self.radio_errors = 0
        self.link_lost: str | None = None
        self.battery_v = math.nan
        self.geofence_margin_m = math.nan  # distance to the hard fence, m (< 0: outside)
        # Online learning.
        self.models: tuple[ModelEntry, ...] = ()
        self.model_version: int | None = None
        self.model_swaps = 0
        self.model_rejects = 0
        self.model_rollbacks = 0
        self.trainer_state = "off"  # off | idle | training | running | restarting | crashed | failed
        self.trainer_last_loss = math.nan
        self.windows_accepted = 0
        self.windows_rejected = 0
        self.poll_error: str | None = None
        # The fast adaptation layer's estimate as flown (``AdaptationEstimate``); None without a layer.
        self.layer: Any = None
        self.events: deque[StatusEvent] = deque(maxlen=6)
        # Ring buffers of the newest ticks: plain lists, the cheapest store from Python.
        self._size = window
        self._next = 0
        self._t = [0.0] * window
        self._wall = [0.0] * window
        self._compute = [0.0] * window
        self._solve = [0.0] * window
        self._pollers: list[Callable[[FlightStatus], None]] = []

    # --- writers ---------------------------------------------------------------------------

    def record_tick(
        self,
        t: float,
        wall: float,
        compute_s: float,
        solve_s: float,
        missed: bool,
        source: str,
        position: Any,
        reference: Any,
    ) -> None:
        """One control tick: flight time, wall time (``time.perf_counter``), timings, what flew.

        ``source`` is the loop's command source ("mpc", "fallback", ...); "fallback" ticks are
        counted. ``position`` and ``reference`` (3-vectors) are kept by reference, not copied:
        pass arrays the caller will not modify in place afterwards.
        """
        i = self._next
        self._t[i] = t
        self._wall[i] = wall
        self._compute[i] = compute_s
        self._solve[i] = solve_s
        self._next = i + 1 if i + 1 < self._size else 0
        self.ticks += 1
        self.t = t
        if missed:
            self.missed_deadlines += 1
        if source == "fallback":
            self.fallbacks += 1
        self.command_source = source
        self.position = position
        self.reference = reference

    def on_tick(self, tick: Any) -> None:
        """``cfknode.flight.loop.TickObserver``: record a ``TickInfo`` (``parts.observers.append(status)``)."""
        est = tick.est
        self.record_tick(tick.t, time.perf_counter(), tick.compute_s, tick.solve_s, tick.missed, tick.source,
                         _NAN3 if est is None else est.p, tick.ref_p)
        self.missed_deadlines += tick.skipped  # the slots passed over before it: missed, with no command at all
        self.model_version = tick.model_version
        self.layer = getattr(tick, "layer", None)

    def add_event(self, t: float, level: str, text: str) -> None:
        """Keep an event for the dashboard's event panel (the newest few)."""
        self.events.append(StatusEvent(float(t), level, text))

    def add_poller(self, poller: Callable[[FlightStatus], None]) -> None:
        """``poller(status)`` runs before each dashboard frame, on the reader's side."""
        self._pollers.append(poller)

    # --- readers ---------------------------------------------------------------------------

    def poll(self) -> None:
        """Run the pollers. One that raises is reported in ``poll_error``, never propagated."""
        for poller in self._pollers:
            try:
                poller(self)
            except Exception as exc:  # a display source must never take the dashboard down
                self.poll_error = f"{getattr(poller, '__name__', 'poller')}: {type(exc).__name__}: {exc}"

    def error(self) -> np.ndarray:
        """Position minus reference, m (NaN before the first tick with a state)."""
        return np.asarray(self.position, dtype=float) - np.asarray(self.reference, dtype=float)

    def tick_stats(self, wall_now: float) -> TickStats:
        """Statistics of the ring buffers; ``wall_now`` is ``time.perf_counter()`` of the reader."""
        n = min(self.ticks, self._size)
        if n == 0:
            nan = math.nan
            return TickStats(0, nan, nan, nan, nan, nan, nan, nan, nan)
        newest = (self._next - 1) % self._size
        oldest = self._next % self._size if self.ticks >= self._size else 0
        compute = np.array(self._compute[:n]) * 1e3
        solve = np.array(self._solve[:n]) * 1e3
        solve = solve[np.isfinite(solve) & (solve > 0)]
        c_med, c_p99 = np.percentile(compute, (50, 99))
        s_med, s_p99 = np.percentile(solve, (50, 99)) if len(solve) else (math.nan, math.nan)
        span_t = self._t[newest] - self._t[oldest]
        span_wall = self._wall[newest] - self._wall[oldest]
        return TickStats(
            window=n,
            compute_median_ms=float(c_med),
            compute_p99_ms=float(c_p99),
            solve_median_ms=float(s_med),
            solve_p99_ms=float(s_p99),
            loop_rate_hz=(n - 1) / span_t if span_t > 0 else math.nan,
            wall_rate_hz=(n - 1) / span_wall if span_wall > 0 else math.nan,
            speed_factor=span_t / span_wall if span_wall > 0 else math.nan,
            since_last_tick_s=max(0.0, wall_now - self._wall[newest]),
        )


# --- Feeding the status ----------------------------------------------------------------------


class _Log(Protocol):
    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None: ...


class StatusTap:
    """A flight log that also feeds a ``FlightStatus`` from what other parts write to it.

    The per-tick data comes from the loop (``on_tick``); the tap brings what the supervisor
    and the online learner publish on their log channels, so the dashboard needs no handle on
    them: ``/safety`` (state, geofence margin, battery), ``/events`` (the event list; a
    supervisor event with a ``state`` field sets the state), ``/model`` (swaps, rejections,
    rollbacks, trainer crashes and restarts, and the queue when the message lists it) and
    ``/training`` (last loss; a window is accepted when its model is swapped in, rejected when
    the gate refuses it or its round fails). Other topics pass straight through,
    at the cost of one dict lookup; other attributes (``path``, ``flush``) are the log's.
    """

    def __init__(self, log: _Log, status: FlightStatus) -> None:
        self._log = log
        self._status = status
        self._model_t: dict[int, float] = {}  # version -> flight time it was swapped in
        self._model_val: dict[int, float] = {}
        self._handlers: dict[str, Callable[[float, Mapping[str, Any]], None]] = {
            "/safety": self._on_safety,
            "/events": self._on_event,
            "/model": self._on_model,
            "/training": self._on_training,
        }

    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None:
        self._log.write(topic, t, msg)
        handler = self._handlers.get(topic)
        if handler is not None:
            handler(t, msg)

    def __getattr__(self, name: str) -> Any:
        # Anything else (path, flush, close, ...) is the wrapped log's: the tap stands in for it.
        return getattr(self._log, name)

    def _on_safety(self, t: float, msg: Mapping[str, Any]) -> None:
        status = self._status
        status.supervisor_state = str(msg["state"])
        if "fence_margin_m" in msg:
            status.geofence_margin_m = _float(msg["fence_margin_m"])
        if "battery_v" in msg:
            status.battery_v = _float(msg["battery_v"])

    def _on_event(self, t: float, msg: Mapping[str, Any]) -> None:
        status = self._status
        status.add_event(t, str(msg.get("level", "info")), str(msg.get("text", "")))
        if msg.get("source") == "supervisor" and "state" in msg:
            status.supervisor_state = str(msg["state"])

    def _on_model(self, t: float, msg: Mapping[str, Any]) -> None:
        status = self._status
        version, event = int(msg["version"]), msg["event"]
        if event == "swap":
            status.model_swaps += 1
            status.windows_accepted += 1
            self._model_t[version] = t
            self._model_val[version] = _float(msg.get("val_error"))
        elif event == "reject":
            status.model_rejects += 1
            status.windows_rejected += 1
        elif event == "rollback":
            status.model_rollbacks += 1
        elif event in _TRAINER_EVENTS:
            status.trainer_state = _TRAINER_EVENTS[event]
        queue = msg.get("queue")
        if queue is not None:
            n = len(queue)
            status.models = tuple(
                ModelEntry(int(v), self._model_t.get(int(v), math.nan), math.exp(k + 1 - n),
                           self._model_val.get(int(v), math.nan))
                for k, v in enumerate(queue)
            )
        if event != "swap":
            reason = msg.get("reason")
            status.add_event(t, "warning", f"model {version} {event}" + (f": {reason}" if reason else ""))

    def _on_training(self, t: float, msg: Mapping[str, Any]) -> None:
        status = self._status
        if status.trainer_state in ("off", "crashed", "restarting"):
            status.trainer_state = "running"
        if msg.get("ok"):
            status.trainer_last_loss = _float(msg.get("loss"))
        else:  # the round made no model: its window is lost
            status.windows_rejected += 1


def mocap_poller(source: Any) -> Callable[[FlightStatus], None]:
    """Poller copying a pose source's ``stats()`` (frames, dropouts, rate) into the status."""

    def poll_mocap(status: FlightStatus) -> None:
        stats = source.stats()
        status.mocap_rate_hz = stats.rate_hz
        status.mocap_frames = stats.frames
        status.mocap_dropouts = stats.dropouts

    return poll_mocap


def radio_poller(radio: Any) -> Callable[[FlightStatus], None]:
    """Poller copying a radio's ``stats()``; latency and ack rate when the radio reports them."""

    def poll_radio(status: FlightStatus) -> None:
        stats = radio.stats()
        status.setpoints_sent = stats.setpoints_sent
        status.radio_errors = stats.send_errors
        status.link_lost = stats.link_lost
        status.radio_latency_ms = _float(getattr(stats, "latency_ms", None))
        status.radio_ack_rate = _float(getattr(stats, "ack_rate", None))

    return poll_radio


def battery_poller(read_voltage: Callable[[], float]) -> Callable[[FlightStatus], None]:
    """Poller for the battery voltage (simulator: ``lambda: sim.battery_voltage``)."""

    def poll_battery(status: FlightStatus) -> None:
        status.battery_v = float(read_voltage())

    return poll_battery


def _float(value: Any) -> float:
    return math.nan if value is None else float(value)
