"""A fleet flight: N simulated drones in one world, N flight loops in one event loop (``cfknode fly --fleet N``).

Each drone has everything a single flight has (docs/fleet.md): its ``sim://`` link through the
real cflib path, its estimator, its ``Controller`` and its ``Supervisor``, and runs the same
``flight.loop.fly`` coroutine. The N coroutines run under ``asyncio.gather`` on one lockstep
``FleetClock``: the world steps only when every loop waits for the next tick, so the drones
see the same instants and none runs ahead. One process and one event loop: with N MPCs
sharing two cores, threads would only add contention (the GIL) to the same compute.

Before take-off: the references are checked for ``fleet.min_separation`` and the radios for
their packet budget (cfknode/app/radio_budget.py); either refuses in one line. In flight the
``FleetCoordinator`` (a tick observer of every drone) watches the separation (too close: the
pair hovers in place for ``fleet.hold_s``, then lands) and applies ``fleet.on_fault`` when one
drone's supervisor lands or stops it. One MCAP log holds every drone's channels under its name
(``/cf1/state``); each drone has its own e-stop mailbox entry (``sim-cf1``), and ``cfknode estop
--all`` reaches them all. Stop signals (SIGINT, SIGTERM, SIGHUP) go to every drone's supervisor
through ``FleetCoordinator.interrupt``: the first lands them all, a second stops them all.
With ``--online`` every drone learns as a single flight does, its rounds on a trainer process shared
with the drones whose rounds train alike (cfknode/app/fleet/learning.py); which drones learn the wake of
the one above alone is chosen from the references (cfknode/app/fleet/wake_below.py).

A fleet of real robots (``--robots cf1,cf2``: cfknode/app/fleet/robots.py) shares all of this:
``preflight``, ``FleetCoordinator``, the channels and ``fly_drones``, which flies any drones
that are ``Backend``s, on a lockstep member clock or on one wall clock.
"""

from __future__ import annotations

import asyncio
import dataclasses
import re
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from cfknode import __version__
from cfknode.app.backends.base import Backend
from cfknode.app.backends.sim_fleet import FleetSimBackend
from cfknode.app.config import Config, ConfigError
from cfknode.app.fleet.coordinator import FleetCoordinator
from cfknode.app.fleet.landing_order import StallHold
from cfknode.app.fleet.learning import fleet_sessions, fleet_trainers
from cfknode.app.fleet.wake_below import wake_below_configs
from cfknode.app.flight_checks import refuse_unflyable
from cfknode.app.foxglove.view import Drawing, FoxgloveView, McapSink, reference_points
from cfknode.app.learning import attitude_lag_identifier, check_online, keep_learned_model, online_model_slot
from cfknode.app.logs.format import CHANNELS, ChannelSpec
from cfknode.app.logs.writer import FlightLog
from cfknode.app.mission import (_controller_label, air_model_observers, build_controller, build_model_slot,
                                 build_supervisor, imu_fields)
from cfknode.app.radio_budget import LinkLoad, check_radio_budget
from cfknode.app.stall_exit import LoopProgress, stall_exit
from cfknode.app.trajectory_fit import fence_problem
from cfknode.app.ui.summary import FlightSummary, compute_summary
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import VelocityEstimator
from cfknode.flight.formation import HoldableReference, fleet_references
from cfknode.flight.loop import FlightParts, FlightRecord, fly
from cfknode.flight.neighbours import NeighbourBoard
from cfknode.kernel.clock import run_loop
from cfknode.kernel.setpoint import thrust_command
from cfknode.safety.estop_mailbox import EstopMailbox, MailboxError, mailbox_dir
from cfknode.safety.geofence import Geofence, clamp_reference
from cfknode.safety.operator import stop_signal_handler
from cfknode.safety.separation import refusal
from cfknode.safety.supervisor import Outcome, Supervisor, SupervisorInputs

@dataclass(frozen=True)
class DroneResult:
    name: str
    uri: str
    summary: FlightSummary
    record: FlightRecord
    outcome: Outcome
    learner: Any = None  # the drone's OnlineLearner when it learned online


@dataclass(frozen=True)
class FleetResult:
    drones: tuple[DroneResult, ...]
    log_path: str
    min_separation_m: float  # closest true distance between any two drones while either flew
    radio_pps: dict[str, float]  # packets/s per radio
    events: tuple[str, ...]  # the fleet's own decisions (separation, fault policy)
    log_incomplete: str | None = None

    @property
    def complete(self) -> bool:
        return all(d.outcome.state.value == "LANDED" and d.outcome.cause == "complete" for d in self.drones)


def drone_names(cfg: Config) -> list[str]:
    return [f"{cfg.fleet.name_prefix}{i + 1}" for i in range(cfg.fleet.size)]


def fleet_channels(names: Sequence[str]) -> tuple[ChannelSpec, ...]:
    """The fleet log's channels: the flight-wide ones, then every drone's under ``/<name>``."""
    per_drone = [s for s in CHANNELS if s.topic != "/config"]
    return (*CHANNELS, *(dataclasses.replace(s, topic=f"/{n}{s.topic}") for n in names for s in per_drone))


class PrefixedLog:
    """A drone's view of the fleet log: its topics under ``/<name>``."""

    def __init__(self, inner: Any, name: str) -> None:
        self._inner = inner
        self._prefix = f"/{name}"

    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None:
        self._inner.write(self._prefix + topic, t, msg)


def drone_configs(cfg: Config) -> tuple[list[str], list[Config], list[HoldableReference]]:
    """Each drone's config (URI, start, seed) and reference, from the fleet settings."""
    n = cfg.fleet.size
    if n < 2:
        raise ConfigError(f"config key 'fleet.size' must be at least 2 for a fleet flight, got {n}")
    m = re.fullmatch(r"sim://(\d+)", cfg.radio.uri)
    if cfg.backend != "sim" or m is None:
        raise ConfigError("a fleet flies in simulation only (backend sim, radio.uri sim://N)")
    base = int(m.group(1))
    ground_z = float(cfg.sim.initial_position[2])
    try:
        placed = fleet_references(cfg.trajectory, n, cfg.fleet.layout, ground_z, cfg.fleet.stack_spacing,
                                  cfg.fleet.ground_spacing)
    except ValueError as exc:
        raise ConfigError(f"config section 'fleet': {exc}") from None
    names = drone_names(cfg)
    configs, refs = [], []
    for i, (start, ref) in enumerate(placed):
        configs.append(dataclasses.replace(
            cfg,
            sim=dataclasses.replace(cfg.sim, seed=cfg.sim.seed + i, initial_position=tuple(float(v) for v in start)),
            radio=dataclasses.replace(cfg.radio, uri=f"sim://{base + i}"),
        ))
        refs.append(HoldableReference(ref))
    return names, wake_below_configs(cfg, configs, [r.inner for r in refs]), refs


def preflight(cfg: Config, names: Sequence[str], configs: Sequence[Config], refs: Sequence[Any]) -> dict[str, float]:
    """Refuse a fleet whose references come too close or whose radios are over budget (one line each)."""
    line = separation_refusal(cfg, names, refs)
    if line is not None:
        raise ConfigError(line)
    loads = [LinkLoad(n, c.radio.uri, c.radio.tx_rate_hz, _pose_rate_hz(c), cfg.fleet.ping_hz)
             for n, c in zip(names, configs)]
    return check_radio_budget(loads, cfg.fleet.radio_budget_pps, cfg.fleet.drones_per_sim_radio)


def placed_fence_events(cfg: Config, names: Sequence[str], refs: Sequence[HoldableReference]) -> list[dict[str, Any]]:
    """Every drone's placed trajectory against the fence's soft box, as for a single drone: a
    one-line ``ConfigError``, or with ``hardware.force`` (``--force``) the log events of flying clamped."""
    if not cfg.safety.enabled:
        return []
    events = []
    for name, ref in zip(names, refs):
        problem = fence_problem(cfg, ref.inner, what=f"{name}'s placed trajectory")
        if problem is None:
            continue
        if not cfg.hardware.force:
            raise ConfigError(f"refusing to take off: {problem} (hardware.force / --force flies it clamped)")
        events.append({"level": "warning", "text": f"take-off FORCED despite: {problem}", "source": "preflight"})
    return events


def separation_refusal(cfg: Config, names: Sequence[str], refs: Sequence[HoldableReference]) -> str | None:
    """The separation refusal over the references as flown: clamped into the fence's soft box, as
    the supervisors clamp them (a forced drone clamped down onto the one below comes too close)."""
    flown: list[Any] = [r.inner for r in refs]
    if cfg.safety.enabled:
        fence = Geofence.from_config(cfg.safety)
        flown = [_Clamped(r, fence.soft_lo, fence.soft_hi) for r in flown]
    return refusal(names, flown, cfg.fleet.min_separation)


@dataclass(frozen=True)
class _Clamped:
    """A reference clamped into the soft box (``geofence.clamp_reference``), for the separation check."""

    inner: Any
    lo: np.ndarray
    hi: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.inner.duration)

    def sample(self, t: np.ndarray) -> Any:
        return clamp_reference(self.inner.sample(t), self.lo, self.hi)


def _pose_rate_hz(cfg: Config) -> float:
    """Extposes per second on a drone's link: one per frame of the mocap it flies with."""
    return cfg.hardware.mocap_rate_hz if cfg.backend == "cf" else cfg.sim.mocap_rate_hz


def run_fleet(cfg: Config, name_hint: str = "fleet",
              on_coordinator: Callable[[FleetCoordinator], None] | None = None, dashboard: Any = None,
              live: Any = None) -> FleetResult:
    """Fly ``cfg.fleet.size`` simulated drones in one flight and return each one's summary;
    ``on_coordinator``, ``dashboard`` and ``live`` as for ``fly_drones``."""
    names, configs, refs = drone_configs(cfg)
    from cfknode.sim_backend.faults import check_faults

    check_faults(cfg.faults, cfg.sim, cfg.controller.kind, cfg.backend)
    forced = placed_fence_events(cfg, names, refs)
    radio_pps = preflight(cfg, names, configs, refs)
    forced = [*refuse_unflyable(cfg), *forced]  # one vehicle for all drones: checked once
    check_online(cfg)
    models = [online_model_slot(c, build_model_slot(c)) for c in configs]  # online: each drone its own slot
    mpcs = [build_controller(c) for c in configs]  # built (and compiled) before the clock starts
    boxes = [EstopMailbox(mailbox_dir(cfg.safety.estop_dir), f"sim-{n}") for n in names]
    try:
        for box in boxes:
            box.open()
    except MailboxError as exc:
        for box in boxes:
            box.close()
        raise ConfigError(f"config key 'safety.estop_dir': {exc}") from None
    try:
        with fleet_trainers(configs) as trainers, FleetSimBackend.open(names, configs) as backend:
            def handback() -> list[dict[str, Any]]:
                for d in backend.drones:
                    d.radio.shutdown()
                firmware = backend.settle_after_handback()
                return [{"firmware_after_shutdown": firmware[n],
                         "vehicle_after_shutdown": d.after_handback()["vehicle_after_shutdown"]}
                        for n, d in zip(names, backend.drones)]

            plan = FleetPlan(names, refs, models, mpcs, boxes, radio_pps, name_hint, forced)
            return fly_drones(cfg, backend.drones, plan, handback, on_coordinator, trainers, dashboard, live)
    finally:
        for box in boxes:
            box.close()


@dataclass(frozen=True)
class FleetPlan:
    """What a fleet flight flies, settled before the drones connect: per drone (in ``names`` order)
    its reference, model slot, MPC (both empty where each drone builds its own: Ray actors) and
    e-stop mailbox; the radio load, the log's name and the forced config changes to log at t=0."""

    names: Sequence[str]
    refs: Sequence[HoldableReference]
    models: Sequence[Any]
    mpcs: Sequence[Any]
    boxes: Sequence[EstopMailbox]
    radio_pps: dict[str, float]
    name_hint: str
    forced: Sequence[dict[str, Any]]


@dataclass(frozen=True)
class _Flying:
    """A fleet flight once its log, supervisors and learners are up: what ``_fly_drones`` flies."""

    plan: FleetPlan
    drones: Sequence[Backend]
    flog: Any
    sups: Sequence[Supervisor]
    logs: Sequence[Any]
    learners: Sequence[Any]
    ground: Sequence[float]
    coordinator: FleetCoordinator
    board: NeighbourBoard | None = None  # the drones' positions: neighbour input, the layers' wake guard (None: off)


def fly_drones(cfg: Config, drones: Sequence[Backend], plan: FleetPlan,
               handback: Callable[[], Sequence[dict[str, Any]]],
               on_coordinator: Callable[[FleetCoordinator], None] | None = None,
               trainers: Sequence[Any] | None = None, dashboard: Any = None, live: Any = None) -> FleetResult:
    """Fly connected drones (simulated or real: each a ``Backend``) under one coordinator and one log.

    ``handback()`` hands every drone back once all flight loops ended and returns each one's
    summary extras (firmware state, pre-flight report). On a wall clock the solve deadline and
    the supervisor's deadline watch apply, as for a single hardware flight.
    ``on_coordinator(coordinator)`` is called once before take-off, for the stop signals that
    arrive outside the flight loops (``ProcessSignals.route``). ``trainers``: each drone's port on
    the shared trainer when it learns online (``fleet_learning.fleet_trainers``), else None.
    ``dashboard``: a live view (cfknode/app/ui/fleet_dashboard.py ``FleetDashboard``) whose
    ``observers(i, drone, reference, controller, supervisor, coordinator)`` watch drone i; None: none.
    ``live``: a Foxglove live server to show the fleet on (docs/foxglove.md)."""
    names, refs, radio_pps = plan.names, plan.refs, plan.radio_pps
    config_dict = {**cfg.to_dict(), "fleet_drones": {n: d.config.radio.uri for n, d in zip(names, drones)}}
    with FlightLog.create(cfg.log.dir, config_dict, __version__, plan.name_hint, channels=fleet_channels(names)) as log:
        # Every drone's frame, reference, plan and the fence in Foxglove's schemas, in the log and to ``live``.
        fence = (cfg.safety.fence_min, cfg.safety.fence_max)
        flog = FoxgloveView(log, [McapSink(log), *([live] if live is not None else [])],
                            {n: Drawing(reference_points(ref.inner), fence) for n, ref in zip(names, refs)})
        for event in plan.forced:
            flog.write("/events", 0.0, event)
        logs = [PrefixedLog(flog, n) for n in names]
        for d, log in zip(drones, logs):
            for event in d.events:  # its pre-flight checks (hardware)
                log.write("/events", 0.0, event)
        sups = [build_supervisor(d.config, d.radio, trajectory=ref, log=log, deadlines_apply=not d.clock.lockstep,
                                 inputs=SupervisorInputs(battery_voltage=d.battery_voltage, link_status=d.link_status))
                for d, ref, log in zip(drones, refs, logs)]
        coordinator = FleetCoordinator(cfg, names, sups, refs, flog, _stall_holds(drones))
        for k, sup in enumerate(sups):  # every supervised landing bottom-up, clear of the drones below
            sup.set_landing_planner(coordinator.landing_planner(k))
        if on_coordinator is not None:
            on_coordinator(coordinator)
        ground = [float(d.start_position[2]) for d in drones]
        board = neighbour_board(cfg, refs, plan.models)  # before the learners: their windows record it
        ports = list(trainers) if trainers is not None else [None] * len(drones)
        sessions = fleet_sessions([d.config for d in drones], plan.models, logs, [d.clock for d in drones], ports, ground)
        with sessions as learners:
            flying = _Flying(plan, drones, flog, sups, logs, learners, ground, coordinator, board)
            results = _fly_drones(cfg, flying, handback, dashboard)
        closest = true_min_separation([r.record for r in results])
        t_end = max((r.record.t[-1] for r in results if r.record.ticks), default=0.0)
        coordinator.log_signals(t_end)  # the ones no tick logged (during the hand-back)
        flog.write("/summary", t_end, {"fleet": list(names), "min_separation_m": closest, "radio_pps": radio_pps,
                                       "outcomes": {r.name: r.outcome.message for r in results}})
    # After close: closing writes the footer, which a full disk can refuse too.
    return FleetResult(tuple(results), str(flog.path), closest, radio_pps, tuple(coordinator.events),
                       flog.incomplete())


def _stall_holds(drones: Sequence[Backend]) -> list[StallHold]:
    """Each drone's stalled-loop hold, level over another drone (wall clock only: in lockstep a stalled
    loop stalls the simulator too, and no radio holds anything)."""
    if any(d.clock.lockstep or not hasattr(d.radio, "hold_level") for d in drones):
        return []
    return [StallHold(d.radio, thrust_command(d.config.vehicle.mass * d.config.vehicle.gravity, d.config.vehicle))
            for d in drones]


def _fly_drones(cfg: Config, flying: _Flying, handback: Callable[[], Sequence[dict[str, Any]]],
                dashboard: Any = None) -> list[DroneResult]:
    """Fly every drone to its end and write its summary (with its learner's fields when it learned online)."""
    plan, drones, flog, sups, learners = flying.plan, flying.drones, flying.flog, flying.sups, flying.learners
    names, refs, ground, coordinator = plan.names, plan.refs, flying.ground, flying.coordinator
    boxes, models, mpcs, logs = plan.boxes, plan.models, plan.mpcs, flying.logs
    parts = []
    for i, (d, ref, sup, log, model, mpc, box) in enumerate(zip(drones, refs, sups, logs, models, mpcs, boxes)):
        deadline = d.config.safety.solve_deadline_s if sup.deadlines_apply else None
        controller = Controller(d.config.controller, d.config.vehicle, model=model, solver=d.wrap_solver(mpc),
                                deadline_s=deadline, ground_z=ground[i])
        estimator = VelocityEstimator(d.config.estimator)
        if learners[i] is not None:
            identifier = attitude_lag_identifier(d.config, learners[i], estimator, model)
            controller.observers.extend([learners[i], *([identifier] if identifier is not None else [])])
        if flying.board is not None and layer_sees_wakes(d.config) and controller.adaptation is not None:
            controller.adaptation.neighbour = flying.board.feed(i)
        flog.follow_plan(names[i], lambda c=controller: c.predicted_positions)
        taps = [flying.board.tap(i)] if flying.board is not None else []
        parts.append(FlightParts(clock=d.clock, mocap=d.mocap, estimator=estimator,
                                 trajectory=ref, controller=controller, supervisor=sup, log=log, truth=d.truth,
                                 imu=getattr(d, "imu", None),  # its accelerometer, as a single flight's
                                 observers=[coordinator.tap(i), *taps, *d.fault_observers(model),
                                            *air_model_observers(d.config, model)], estop=box,
                                 signals=False))
    for i, (d, p) in enumerate(zip(drones, parts) if dashboard is not None else ()):
        p.observers.extend(dashboard.observers(i, d, p.trajectory, p.controller, p.supervisor, coordinator))
    progress = LoopProgress()  # the loops share one thread: any drone's tick says it is alive
    for p in parts:
        p.observers.insert(0, progress)
    with stall_exit([d.radio for d in drones], flog, progress):  # a loop that never returns ends the process
        records = run_loop(_gather(drones, parts, coordinator))
    after = handback()
    results = []
    for name, d, p, rec, sup, ref, learner, extra in zip(names, drones, parts, records, sups, refs, learners, after):
        outcome = sup.outcome()
        online = {} if learner is None else {**learner.summary_fields(), **keep_learned_model(learner, flog.path, name)}
        summary = compute_summary(
            rec, window=ref.pattern_window, wall_time=rec.wall_time, log_path=str(flog.path),
            extra={"drone": name, "uri": d.config.radio.uri, "outcome": outcome.message,
                   "safety_state": outcome.state.value, "safety_cause": outcome.cause, "fallback_ticks": rec.fallbacks,
                   "controller": _controller_label(cfg, bool(cfg.controller.model), learner is not None),
                   "backend": d.config.backend, "lockstep": bool(d.clock.lockstep),
                   **imu_fields(d.radio, p.imu is not None), **extra, **rec.adaptation, **online})
        flog.write(f"/{name}/summary", rec.t[-1] if rec.ticks else 0.0, summary.to_dict())
        results.append(DroneResult(name, d.config.radio.uri, summary, rec, outcome, learner))
    return results


async def _gather(drones: Sequence[Backend], parts: Sequence[FlightParts],
                  coordinator: FleetCoordinator) -> list[FlightRecord]:
    """Every drone's loop to its end. The stop signals go to the coordinator (so to every drone)
    from one relay thread for the whole fleet: the loops do not take them (``FlightParts.signals``),
    and a signal still reaches every supervisor, and its radio, while the loops' thread is stuck."""

    async def one(drone: Backend, p: FlightParts) -> FlightRecord:
        try:
            return await fly(p)
        finally:
            leave = getattr(drone.clock, "leave", None)  # a lockstep member must not hold the others back
            if leave is not None:
                leave()

    with stop_signal_handler(coordinator):
        return list(await asyncio.gather(*(one(d, p) for d, p in zip(drones, parts))))


def neighbour_board(cfg: Config, refs: Sequence[HoldableReference], slots: Sequence[Any]) -> NeighbourBoard | None:
    """The drones' positions, shared: with ``fleet.neighbour_input`` every drone's model slot reads its neighbour
    input from it (docs/fleet.md#neighbour-input), and every drone's fast layer sees the drone above, under whose
    wake it calls no heavier step (``controller.adaptation_settings.wake_radius``). None when neither applies."""
    inputs = cfg.fleet.neighbour_input and any(s is not None for s in slots)
    c = cfg.controller
    if not (inputs or (len(refs) >= 2 and layer_sees_wakes(cfg))):
        return None
    board = NeighbourBoard(refs, 1.0 / c.rate_hz, c.dt, c.horizon, lead=cfg.estimator.command_delay)
    e = cfg.estimator
    for i, slot in enumerate(slots):
        if slot is not None and inputs:
            slot.neighbour = board.feed(i)
            slot.vertical_lead = e.command_delay - (e.command_delay if e.command_delay_z is None else e.command_delay_z)
    return board


def layer_sees_wakes(cfg: Config) -> bool:
    """Whether the drones' fast layers watch for the drone above's wake (wake_guard.py)."""
    return cfg.controller.adaptation == "dob" and cfg.controller.adaptation_settings.wake_radius > 0.0


def true_min_separation(records: Sequence[FlightRecord]) -> float:
    """The smallest distance between any two drones' recorded positions at the same tick (true
    positions in simulation), over the ticks where either still recorded; inf for fewer than two.

    A drone whose loop has ended stays where it was last recorded (landed, or stopped and fallen),
    so a drone that lands later onto one that landed first is measured too."""
    best = float("inf")
    for i in range(len(records)):
        for j in range(i + 1, len(records)):
            a, b = records[i], records[j]
            if a.ticks == 0 or b.ticks == 0:
                continue
            n = max(a.ticks, b.ticks)
            d = np.linalg.norm(_held(a.p[:a.ticks], n) - _held(b.p[:b.ticks], n), axis=1)
            best = min(best, float(d.min()))
    return best


def _held(p: np.ndarray, n: int) -> np.ndarray:
    """``p`` (ticks, 3) extended to ``n`` ticks with its last row."""
    return p if len(p) >= n else np.concatenate([p, np.repeat(p[-1:], n - len(p), axis=0)])


__all__ = ["DroneResult", "FleetCoordinator", "FleetResult", "PrefixedLog", "drone_configs", "fleet_channels",
           "FleetPlan", "fly_drones", "preflight", "run_fleet", "true_min_separation"]
