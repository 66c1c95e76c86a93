"""One fleet drone as a Ray actor: its whole flight runs here, on the node that has its radio.

``fleet_ray`` wraps ``DroneActor`` with ``ray.remote`` (this module imports no Ray at its top,
so it loads without Ray). The actor flies the drone as a single flight (``mission.run_flight``:
its own simulator in lockstep, estimator, ``Controller``, supervisor and MCAP log on this node),
with the fleet's placed reference for this drone. The control loop never waits for a call of the
driver's: its requests (land, hold, stop) are queued and applied by a tick observer on the
loop's own thread at the next tick, and ``status()`` returns the latest tick's snapshot. In
lockstep, a drone about to descend that has run ahead of the others waits after its tick for
the driver's view of them to catch up (landing_order.ViewGate.catch_up). A stop
signal goes straight to the supervisor (its queue is thread-safe), which passes it on to the
radio at once, so it acts while the loop is stuck. It is a threaded actor, so these calls are
served while ``fly()`` runs.

Restart: Ray re-runs ``__init__`` with the same ``DroneSpec`` (so the model file and the
config are the ones the drone was given). A restarted actor never flies again and never
touches the log written before the crash: it writes a new log for the continuation that
records the fault and names the old one, and reports the drone's flight as ended by a fault
(a hardware link's watchdog would have cut the motors; the simulated world died with the
worker). docs/fleet-ray.md.
"""

from __future__ import annotations

import dataclasses
import threading
import warnings
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cfknode import __version__
from cfknode.app.backends.sim_fleet import fault_free
from cfknode.app.config import Config
from cfknode.app.fleet.flight import drone_configs
from cfknode.app.fleet.landing_order import StackGeometry, ViewGate
from cfknode.app.logs.writer import FlightLog
from cfknode.app.mission import FlightResult, run_flight
from cfknode.app.ui.summary import compute_summary
from cfknode.flight.loop import FlightRecord
from cfknode.safety.ordered_landing import OrderedLanding
from cfknode.safety.supervisor import Outcome
from cfknode.safety.supervisor_types import State

RESTART_CAUSE = "actor_restart"
TRAIL_MAX = 400 * 600  # ticks kept for a driver that stopped asking (ten minutes at 400 Hz)
_HOLDABLE = ("TAKEOFF", "TRACK")


@dataclass(frozen=True)
class DroneSpec:
    """What an actor is created with (and re-created with after a restart)."""

    index: int  # the drone's place in the fleet
    fleet: Config  # the fleet's config; the drone's own comes from fleet.drone_configs
    log_hint: str  # unique per fleet flight and drone: names its logs, and finds them after a restart


@dataclass(frozen=True)
class DroneStatus:
    """The latest tick's snapshot, for the driver's fleet supervisor."""

    name: str
    t: float  # the drone's flight time (its own lockstep clock)
    p: tuple[float, float, float] | None  # position estimate; None before the first pose
    state: str  # supervisor state ("" before the first tick)
    cause: str  # supervisor cause so far
    ticks: int
    done: bool  # the flight has ended (fly() returned or will at once)
    restarted: bool  # this actor is a restart after its worker died
    node_id: str
    # Every tick since the previous report() as (t, state, cause, position or None): the driver
    # compares the drones at the same flight time, whatever their actors' pace.
    trail: tuple[tuple[float, str, str, tuple[float, float, float] | None], ...] = ()
    spot: tuple[float, float, float] | None = None  # where its ordered landing descends, once it has chosen


class DroneActor:
    """A drone's flight; create with ``ray.remote(DroneActor).options(...).remote(spec)``."""

    def __init__(self, spec: DroneSpec) -> None:
        import ray  # inside the actor only

        ctx = ray.get_runtime_context()
        self._spec = spec
        self._node_id = ctx.get_node_id()
        with warnings.catch_warnings():  # Ray's own property calls APIs it has deprecated
            warnings.simplefilter("ignore", DeprecationWarning)
            self._restarted = bool(ctx.was_current_actor_reconstructed)
        names, configs, refs = drone_configs(spec.fleet)
        cfg = configs[spec.index]
        if spec.index > 0:  # as in the one-process fleet: injected faults act on the first drone only
            cfg = dataclasses.replace(cfg, faults=fault_free(cfg.faults))
        self.name, self._cfg, self._ref = names[spec.index], cfg, refs[spec.index]
        # A held drone must be landing before the nominal landing starts (as FleetCoordinator).
        self._land_deadline = self._ref.segments["land"][0] - 2.0 / cfg.controller.rate_hz
        self._inbox: deque[tuple[str, tuple[Any, ...]]] = deque()
        self._land_at: tuple[float, str, str] | None = None
        self._sup: Any = None
        self._lock = threading.Lock()
        self._trail: deque[tuple[float, str, str, tuple[float, float, float] | None]] = deque(maxlen=TRAIL_MAX)
        self._status = DroneStatus(self.name, 0.0, None, "", "", 0, False, self._restarted, self._node_id)
        self._restart_result: FlightResult | None = None
        # Every supervised landing is ordered among the fleet as the driver last told it (fleet_view).
        self._gate = ViewGate(StackGeometry.from_config(cfg), spec.index, self._waits)
        self._lockstep = not cfg.sim.realtime  # its clock waits for the fleet's view before a descent
        if self._restarted:
            self._restart_result = self._report_restart()

    # -- the driver's calls (any thread) --------------------------------------------------

    def node_id(self) -> str:
        return self._node_id

    def status(self) -> DroneStatus:
        """The latest tick, for anyone who asks (an operator, a test); its trail is left for the driver."""
        with self._lock:
            return self._status

    def report(self) -> DroneStatus:
        """The driver's poll: the latest tick and every tick since its previous report (taken: each tick
        reaches the fleet's separation watch once, and a ``status()`` from elsewhere takes none of them)."""
        with self._lock:
            trail, self._trail = tuple(self._trail), deque(maxlen=TRAIL_MAX)
            return dataclasses.replace(self._status, trail=trail)

    def request_land(self, reason: str, cause: str) -> None:
        self._inbox.append(("land", (reason, cause)))

    def request_stop(self, reason: str, cause: str) -> None:
        self._inbox.append(("stop", (reason, cause)))

    def interrupt(self, signal_name: str = "SIGINT") -> None:
        # Straight to the supervisor once it exists (its inbox is thread-safe): a stalled loop takes
        # no inbox, and the supervisor passes the signal on to the radio, which acts during a stall.
        sup = self._sup
        if sup is not None:
            sup.interrupt(signal_name)
        else:
            self._inbox.append(("interrupt", (signal_name,)))

    def hold(self, reason: str, to: list[float] | None = None, move_s: float = 0.0) -> None:
        """Hover where the drone is now (its own latest estimate), gliding to ``to`` over ``move_s``
        seconds when given (clear of the drones below), until a landing is requested."""
        self._inbox.append(("hold", (reason, to, move_s)))

    def fleet_view(self, positions: list[Any], states: list[str], spots: dict[int, Any],
                   times: list[float]) -> None:
        """The fleet as the driver knows it now (every drone's position, supervisor state, landing spot
        and flight time, this one's included): what this drone's ordered landings are judged by."""
        self._gate.update(positions, states, spots, times)

    def land_at(self, t: float, reason: str, cause: str) -> None:
        """Land when the drone's own flight time reaches ``t`` (at once if it has)."""
        self._inbox.append(("land_at", (t, reason, cause)))

    def log_paths(self) -> list[str]:
        """This drone's logs of this fleet flight on this node (before and after a restart), oldest first."""
        return [str(p) for p in sorted(Path(self._cfg.log.dir).glob(f"*-{self._spec.log_hint}*.mcap"),
                                       key=lambda p: p.stat().st_mtime)]

    def fly(self) -> FlightResult:
        """Fly the mission (blocks for the flight); a restarted actor reports the lost flight instead."""
        if self._restart_result is not None:
            return self._restart_result
        try:
            flight = run_flight(self._cfg, name_hint=self._spec.log_hint, observers=[_Tap(self)],
                                on_supervisor=self._take_supervisor, trajectory=self._ref, estop=False)
            # Wall seconds its loop waited for the fleet's view before a descent (ViewGate.catch_up).
            extra = {**flight.summary.extra, "view_wait_s": round(self._gate.caught_up_s, 3)}
            return dataclasses.replace(flight, summary=dataclasses.replace(flight.summary, extra=extra))
        finally:
            with self._lock:
                self._status = dataclasses.replace(self._status, done=True)

    # -- on the flight loop's thread ---------------------------------------------------------

    def _take_supervisor(self, sup: Any) -> None:
        self._sup = sup
        gate = self._gate  # glide clear of the drones below, wait for them, then descend (as a local fleet)
        sup.set_landing_planner(lambda start, ground_z, t0, speed: OrderedLanding(gate, start, ground_z, t0, speed))

    def _waits(self, text: str) -> None:
        sup = self._sup
        if sup is not None:
            sup.note("info", f"{self.name} {text}", "fleet")

    def _on_tick(self, info: Any) -> None:
        t, sup = float(info.t), self._sup
        state = info.supervisor_state
        self._gate.at(t)
        while self._inbox:
            kind, args = self._inbox.popleft()
            if kind == "land":
                sup.request_land(*args)
            elif kind == "stop":
                sup.request_stop(*args)
            elif kind == "interrupt":
                sup.interrupt(*args)
            elif kind == "hold":
                if state in _HOLDABLE and info.est is not None and t < self._land_deadline:
                    self._ref.hold(t, info.est.p, to=args[1], move_s=args[2])
                    sup.note("warning", f"fleet: hold ({args[0]})", "fleet")
            elif kind == "land_at":
                t_land, reason, cause = args
                t_land = min(t_land, self._land_deadline)
                if self._land_at is None or t_land < self._land_at[0]:
                    self._land_at = (t_land, reason, cause)
        if self._land_at is not None and t >= self._land_at[0] - 1e-9:
            sup.request_land(self._land_at[1], self._land_at[2])
            self._land_at = None
        p = None if info.est is None else tuple(float(v) for v in np.asarray(info.est.p)[:3])
        cause = sup.snapshot().cause
        with self._lock:
            self._status = dataclasses.replace(self._status, t=t, p=p, state=state, cause=cause,
                                               ticks=self._status.ticks + 1, spot=self._gate.spot_now)
            self._trail.append((t, state, cause, p))
        if self._lockstep:  # last: the driver has this tick before the loop waits
            self._gate.catch_up()

    # -- after a restart ----------------------------------------------------------------------

    def _report_restart(self) -> FlightResult:
        """The continuation log (a new file: the old one is kept as the crash left it) and the fault ending."""
        kept = self.log_paths()
        text = (f"{self.name}: its Ray actor's worker died and the actor was restarted on node {self._node_id[:12]}; "
                "the flight is lost (a hardware link's watchdog cuts the motors) and ended as a fault")
        window = self._ref.pattern_window
        with FlightLog.create(self._cfg.log.dir, self._cfg.to_dict(), __version__,
                              f"{self._spec.log_hint}-restart") as log:
            log.write("/events", 0.0, {"level": "error", "text": text, "source": "fleet",
                                       "kept_logs": kept, "cause": RESTART_CAUSE})
            empty = FlightRecord.empty(0)
            summary = compute_summary(empty, window=window, wall_time=0.0,
                                      log_path=str(log.path),
                                      extra={"drone": self.name, "outcome": text, "safety_state": "EMERGENCY",
                                             "safety_cause": RESTART_CAUSE, "logs_before_restart": kept})
            log.write("/summary", 0.0, summary.to_dict())
        outcome = Outcome(State.EMERGENCY, text, RESTART_CAUSE, float("nan"))
        with self._lock:
            self._status = dataclasses.replace(self._status, state="EMERGENCY", cause=RESTART_CAUSE, done=True)
        return FlightResult(summary=summary, record=empty, outcome=outcome, log_incomplete=log.incomplete())


@dataclass
class _Tap:
    actor: DroneActor

    def on_tick(self, tick: Any) -> None:
        self.actor._on_tick(tick)


__all__ = ["DroneActor", "DroneSpec", "DroneStatus", "RESTART_CAUSE"]
