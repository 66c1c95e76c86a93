"""A fleet flight on Ray: every drone a Ray actor on the node that has its radio (``--executor ray``).

What runs where (docs/fleet-ray.md):

- **actor** (``drone_actor.DroneActor``, one per drone): the whole control loop, as a single
  flight in lockstep with the fleet's placed reference for that drone, and that drone's MCAP
  log on the actor's node. It asks for the Ray custom resource of its radio
  (``fleet.ray_radio_resource``, e.g. ``crazyradio_0``), so Ray places it on the node that has
  the radio. Nothing is called per tick across the network.
- **driver** (this module): the pre-flight checks of the one-process fleet (separation,
  radio budget, unflyable configs, the model file), a refusal in one line when no node offers
  a drone's radio resource, and the fleet supervisor: it polls every actor's ``report()`` at
  ``POLL_HZ`` (each reply carries every tick since the last) and feeds the ticks, in flight-time
  order, to the same ``FleetCoordinator`` (separation watch, ``fleet.on_fault``) the local fleet
  uses; its landings, holds and timed landings go to the actors. The driver keeps
  the fleet's e-stop mailbox entries (``sim-cf1`` ...) and forwards each request (``cfknode
  estop --all``) to the drone's actor; Ctrl-C goes to every actor. It writes a small fleet log
  (``/config``, the fleet's ``/events``, ``/summary`` with every drone's log paths and node).

Restart: actors have ``max_restarts`` >= 1. A drone whose actor died is reported by its
restarted actor as a fault ending (cause ``actor_restart``), with its logs, and the fault
policy applies to the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from cfknode import __version__
from cfknode.app.bench.executor import ExecutorSettings, connect_ray
from cfknode.app.config import Config, ConfigError
from cfknode.app.fleet.drone_actor import DroneActor, DroneSpec
from cfknode.app.bench.ray_probe import RayAddressError
from cfknode.app.fleet.flight import (DroneResult, FleetCoordinator, FleetPlan, FleetResult, drone_configs,
                                      placed_fence_events, preflight, true_min_separation)
from cfknode.app.flight_checks import refuse_unflyable
from cfknode.app.logs.writer import FlightLog
from cfknode.app.mission import FlightResult, MissionError, build_model_slot
from cfknode.app.radio_budget import radio_index
from cfknode.flight.loop import FlightRecord
from cfknode.safety.estop_mailbox import EstopMailbox, MailboxError, mailbox_dir
from cfknode.safety.operator import estop_watch, stop_signal_handler
from cfknode.safety.supervisor import Outcome
from cfknode.safety.supervisor_types import State

POLL_HZ = 20.0  # the driver's fleet supervisor: status polls per second (wall)
PLACEMENT_TIMEOUT_S = 120.0  # actors that cannot start (no free CPU on their radio's node) by then: refused
# A drone asks for this share of its radio's resource: the resource places it, while the packet
# budget (radio_budget.py) decides how many drones a radio carries.
RESOURCE_SHARE = 0.001
MAX_RESTARTS = 1
LOST_CAUSE = "actor_lost"  # a drone whose actor's worker died (its link is gone)
ERROR_CAUSE = "actor_error"  # a drone whose flight raised inside its actor
RESTART_WAIT_S = 60.0  # how long a drone's restarting actor may take to answer again
ACTOR_THREADS = 4  # fly() on one thread; status and the driver's requests on the others


def radio_resource(cfg: Config, uri: str) -> str:
    """The Ray resource of the node that has ``uri``'s radio: ``fleet.ray_radio_resource`` with its index."""
    return cfg.fleet.ray_radio_resource.replace("{radio}", str(radio_index(uri, cfg.fleet.drones_per_sim_radio)))


def check_resources(names: Sequence[str], resources: Sequence[str], available: Mapping[str, float]) -> None:
    """Refuse (one line) a fleet with a drone whose radio resource no node of the cluster offers."""
    missing: dict[str, list[str]] = {}
    for name, res in zip(names, resources):
        if float(available.get(res, 0.0)) <= 0.0:
            missing.setdefault(res, []).append(name)
    if missing:
        res, who = next(iter(missing.items()))
        offered = sorted(k for k in available if k not in ("CPU", "GPU", "memory", "object_store_memory")
                         and not k.startswith(("node:", "accelerator_type:")))
        raise ConfigError(
            f"take-off refused: {' and '.join(who)} need{'s' if len(who) == 1 else ''} the Ray resource {res!r} "
            f"(the node with its radio), which no node of the cluster offers (custom resources: "
            f"{', '.join(offered) or 'none'}); start that node with --resources '{{\"{res}\": 1}}'")


@dataclass(frozen=True)
class _Polled:
    """A status snapshot as FleetCoordinator.on_tick reads a tick."""

    t: float
    supervisor_state: str
    est: Any


@dataclass(frozen=True)
class _Position:
    p: np.ndarray


class _DroneLink:
    """The driver's handle on one actor, shaped as the supervisor FleetCoordinator and the e-stop watcher expect."""

    def __init__(self, actor: Any, log: Any) -> None:
        self.actor, self._log = actor, log
        self.cause = ""  # the latest polled supervisor cause (FleetCoordinator reads snapshot().cause)

    def snapshot(self) -> "_DroneLink":
        return self

    def request_land(self, reason: str = "fleet", cause: str = "operator_land") -> None:
        self.actor.request_land.remote(reason, cause)

    def request_stop(self, reason: str = "fleet", cause: str = "operator_stop") -> None:
        self.actor.request_stop.remote(reason, cause)

    def interrupt(self, signal_name: str = "SIGINT") -> None:
        self.actor.interrupt.remote(signal_name)

    def land_at(self, t: float, reason: str, cause: str) -> None:
        self.actor.land_at.remote(t, reason, cause)

    def note(self, level: str, text: str, source: str) -> None:
        self._log.write("/events", 0.0, {"level": level, "text": text, "source": source})


class _RemoteReference:
    """A drone's reference as FleetCoordinator holds it: its segments here, the hold in the actor."""

    def __init__(self, link: _DroneLink, local: Any) -> None:
        self._link, self.segments = link, local.segments

    def hold(self, t: float, p: Any, to: Any = None, move_s: float = 0.0) -> None:
        # The actor holds at its own latest estimate and tick (its lockstep clock is its own), and
        # glides to ``to`` from there.
        target = None if to is None else [float(v) for v in to]
        self._link.actor.hold.remote(f"held by the fleet at its {t:.2f} s", target, move_s)


class RemoteCoordinator(FleetCoordinator):
    """FleetCoordinator whose timed landings are kept by the actors, on their own flight clocks."""

    def _schedule_land(self, k: int, t_land: float, reason: str, cause: str) -> None:
        self._sups[k].land_at(t_land, reason, cause)


class _AllDrones:
    def __init__(self, links: Sequence[_DroneLink]) -> None:
        self._links = links

    def interrupt(self, signal_name: str) -> None:
        for link in self._links:
            link.interrupt(signal_name)


def run_fleet_ray(cfg: Config, settings: ExecutorSettings, name_hint: str = "fleet") -> FleetResult:
    """Fly ``cfg.fleet.size`` simulated drones, each a Ray actor on the node with its radio."""
    from cfknode.sim_backend.faults import check_faults

    cfg = _absolute_paths(cfg)
    if cfg.online.enabled:  # each actor would spawn its own trainer inside a Ray worker: not tried yet
        raise ConfigError("online learning is not wired for --executor ray fleets: fly the fleet on one machine "
                          "(--executor local) to learn online")
    names, configs, refs = drone_configs(cfg)
    check_faults(cfg.faults, cfg.sim, cfg.controller.kind, cfg.backend)
    forced = placed_fence_events(cfg, names, refs)
    radio_pps = preflight(cfg, names, configs, refs)
    forced = [*refuse_unflyable(cfg), *forced]
    build_model_slot(configs[0])  # a bad model file is refused here, before any actor starts
    resources = [radio_resource(cfg, c.radio.uri) for c in configs]
    import ray

    # A Ray started here is this machine alone: it has every simulated radio.
    try:
        owned = connect_ray(settings.address, len(names), {r: 1.0 for r in resources})
    except RayAddressError as exc:  # a bad or unreachable address: the user's to fix
        raise ConfigError(f"take-off refused: {exc}") from None
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {settings.address}" if settings.address else "a local Ray"
        raise MissionError(f"take-off refused: cannot join {where}: {str(exc).splitlines()[0][:200]}") from None
    try:
        check_resources(names, resources, ray.cluster_resources())
        boxes = [EstopMailbox(mailbox_dir(cfg.safety.estop_dir), f"sim-{n}") for n in names]
        try:
            for box in boxes:
                box.open()
        except MailboxError as exc:
            raise ConfigError(f"config key 'safety.estop_dir': {exc}") from None
        try:
            # No model slots or MPCs here: each actor builds its drone's own.
            plan = FleetPlan(names, refs, (), (), boxes, radio_pps, name_hint, forced)
            return _fly(ray, cfg, plan, [c.radio.uri for c in configs], resources)
        finally:
            for box in boxes:
                box.close()
    finally:
        if owned:
            ray.shutdown()


def _absolute_paths(cfg: Config) -> Config:
    # The actors' working directory is not the driver's: hand them absolute paths.
    log = dataclasses.replace(cfg.log, dir=str(Path(cfg.log.dir).expanduser().resolve()))
    model = cfg.controller.model
    ctrl = dataclasses.replace(cfg.controller, model=str(Path(model).expanduser().resolve()) if model else model)
    return dataclasses.replace(cfg, log=log, controller=ctrl)


def _fly(ray: Any, cfg: Config, plan: FleetPlan, uris: Sequence[str], resources: Sequence[str]) -> FleetResult:
    names, refs, boxes, radio_pps, name_hint = plan.names, plan.refs, plan.boxes, plan.radio_pps, plan.name_hint
    token = secrets.token_hex(3)
    remote = ray.remote(DroneActor)
    config_dict = {**cfg.to_dict(), "executor": "ray", "fleet_resources": dict(zip(names, resources))}
    with FlightLog.create(cfg.log.dir, config_dict, __version__, name_hint) as flog:
        for event in plan.forced:
            flog.write("/events", 0.0, event)
        # Named as its logs are (<hint>-<drone>-<token>), so an operator can find it: ray.get_actor(name).
        actors = [remote.options(resources={res: RESOURCE_SHARE}, num_cpus=1, max_restarts=MAX_RESTARTS,
                                 max_task_retries=0, max_concurrency=ACTOR_THREADS,
                                 name=f"{name_hint}-{n}-{token}").remote(DroneSpec(i, cfg, f"{name_hint}-{n}-{token}"))
                  for i, (n, res) in enumerate(zip(names, resources))]
        try:
            nodes = ray.get([a.node_id.remote() for a in actors], timeout=PLACEMENT_TIMEOUT_S)
        except ray.exceptions.GetTimeoutError:
            for a in actors:
                ray.kill(a, no_restart=True)
            raise MissionError(f"take-off refused: the drones' actors could not start within {PLACEMENT_TIMEOUT_S:g} s "
                               "(each needs a free CPU on the node with its radio)") from None
        for n, res, node in zip(names, resources, nodes):
            flog.write("/events", 0.0, {"level": "info", "text": f"{n} flies on node {node} ({res})", "source": "fleet"})
        links = [_DroneLink(a, flog) for a in actors]
        coordinator = RemoteCoordinator(cfg, names, links, [_RemoteReference(k, r) for k, r in zip(links, refs)], flog)
        try:
            flights = asyncio.run(_supervise(ray, actors, links, boxes, coordinator))
            logs_of = [_log_paths(ray, a, f) for a, f in zip(actors, flights)]
        finally:
            for a in actors:  # done (or the driver failed): free their CPUs now
                ray.kill(a, no_restart=True)
        results = []
        for name, uri, flight, node, logs in zip(names, uris, flights, nodes, logs_of):
            summary = dataclasses.replace(flight.summary, extra={**flight.summary.extra, "drone": name, "uri": uri,
                                                                 "ray_node": node, "logs": logs})
            results.append(DroneResult(name, uri, summary, flight.record, flight.outcome))
        closest = true_min_separation([r.record for r in results])  # tick-aligned: every drone ticks from t = 0
        t_end = max((r.record.t[-1] for r in results if r.record.ticks), default=0.0)
        flog.write("/summary", t_end, {"fleet": list(names), "min_separation_m": closest, "radio_pps": radio_pps,
                                       "outcomes": {r.name: r.outcome.message for r in results},
                                       "logs": {r.name: r.summary.extra["logs"] for r in results},
                                       "nodes": dict(zip(names, nodes))})
    return FleetResult(tuple(results), str(flog.path), closest, radio_pps, tuple(coordinator.events), flog.incomplete())


def _log_paths(ray: Any, actor: Any, flight: FlightResult) -> list[str]:
    try:
        return list(ray.get(actor.log_paths.remote(), timeout=10.0))
    except Exception:  # noqa: BLE001 - the actor is gone: the flight's own summary still names its log
        return [flight.summary.log_path] if flight.summary.log_path else []


class Timeline:
    """The drones' ticks, fed to the coordinator in flight-time order and only up to the time every
    drone still flying has reached, so the separation watch compares the drones at the same
    instant (as the one-process fleet does) however far apart their actors' lockstep clocks run."""

    def __init__(self, coordinator: FleetCoordinator, links: Sequence[_DroneLink]) -> None:
        self._co, self._links = coordinator, links
        self._queues: list[list[tuple[float, str, str, Any]]] = [[] for _ in links]
        self._open = [True] * len(links)
        self.last_t = [float("-inf")] * len(links)  # the latest tick reported by each drone

    def add(self, i: int, trail: Sequence[tuple[float, str, str, Any]]) -> None:
        if self._open[i] and trail:
            self._queues[i].extend(trail)
            self.last_t[i] = float(trail[-1][0])

    def close(self, i: int, state: str, cause: str) -> None:
        """Drone i reports no more: its ending follows its last tick, and it holds nobody back."""
        if self._open[i]:
            self._queues[i].append((max(self.last_t[i], 0.0), state, cause, None))
            self._open[i] = False

    def feed(self) -> None:
        horizon = min((t for t, o in zip(self.last_t, self._open) if o), default=float("inf"))
        due: list[tuple[float, int, str, str, Any]] = []
        for i, queue in enumerate(self._queues):
            n = 0
            while n < len(queue) and queue[n][0] <= horizon:
                due.append((queue[n][0], i, *queue[n][1:]))
                n += 1
            del queue[:n]
        due.sort(key=lambda d: (d[0], d[1]))
        for t, i, state, cause, p in due:
            self._links[i].cause = cause
            self._co.on_tick(i, _Polled(t, state, None if p is None else _Position(np.asarray(p, dtype=float))))


class FleetView:
    """Every drone's latest position, supervisor state, landing spot and flight time as its actor last
    reported them (not held back to a common flight time, as the Timeline is: a drone below that is down
    is down), pushed to every flying actor each poll: what their ordered landings are judged by
    (landing_order.ViewGate), so a Ray fleet lands a stack bottom-up as the one-process fleet does. The
    times let an actor that ran ahead wait for the view to catch up before it descends."""

    def __init__(self, n: int, coordinator: FleetCoordinator) -> None:
        self._co = coordinator
        self.positions: list[Any] = [None] * n
        self.states = [""] * n
        self.times = [0.0] * n  # inf once a drone's flight has ended: it holds nobody back
        self._spots: dict[int, Any] = {}

    def seen(self, i: int, status: Any) -> None:
        if status.p is not None:
            self.positions[i] = tuple(status.p)
        if status.state:
            self.states[i] = status.state
        if status.spot is not None:
            self._spots[i] = tuple(status.spot)
        if self.times[i] != float("inf"):
            self.times[i] = max(self.times[i], float(status.t))

    def ended(self, i: int, state: str) -> None:
        self.states[i] = state
        self.times[i] = float("inf")

    def spots(self) -> dict[int, Any]:
        """The spots the actors chose, else the one the driver's coordinator glides a held drone to."""
        held = {j: tuple(float(v) for v in q) for j, q in self._co._spots.items()}
        return {**held, **self._spots}

    def push(self, actors: Sequence[Any], flying: Sequence[bool]) -> None:
        spots = self.spots()
        for a, on in zip(actors, flying):
            if on:
                a.fleet_view.remote(list(self.positions), list(self.states), spots, list(self.times))


async def _supervise(ray: Any, actors: Sequence[Any], links: Sequence[_DroneLink], boxes: Sequence[EstopMailbox],
                     coordinator: FleetCoordinator) -> list[FlightResult]:
    """Poll the actors until every flight has ended; the fleet policy and the e-stops act meanwhile."""
    lost = (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError)
    flights = {a.fly.remote(): i for i, a in enumerate(actors)}
    restart_deadline: dict[int, float] = {}
    retry: list[int] = []  # drones whose flight call is asked again (of a restarting actor) next round
    results: list[FlightResult | None] = [None] * len(actors)
    polls: dict[Any, int] = {}
    timeline = Timeline(coordinator, links)
    view = FleetView(len(actors), coordinator)
    with contextlib.ExitStack() as stack:
        stack.enter_context(stop_signal_handler(_AllDrones(links)))
        for link, box in zip(links, boxes):
            stack.enter_context(estop_watch(link, box))
        while flights or retry:
            for i in retry:
                flights[actors[i].fly.remote()] = i
            retry.clear()
            asked = set(polls.values())
            for i, a in enumerate(actors):
                if results[i] is None and i not in restart_deadline and i not in asked:
                    polls[a.report.remote()] = i
            ready, _ = ray.wait(list(polls), num_returns=len(polls), timeout=0) if polls else ([], [])
            for ref in ready:
                i = polls.pop(ref)
                with contextlib.suppress(*lost):  # restarting: its flight call says what happened
                    status = ray.get(ref)
                    view.seen(i, status)
                    timeline.add(i, status.trail)
            done, _ = ray.wait(list(flights), num_returns=len(flights), timeout=0)
            for ref in done:
                i = flights.pop(ref)
                name = coordinator.names[i]
                try:
                    results[i] = ray.get(ref)
                except lost as exc:
                    # Unavailable: the worker died and Ray restarts the actor; asked again, the restarted
                    # actor reports the lost flight. Died: no restart is left.
                    timeline.close(i, "EMERGENCY", LOST_CAUSE)  # lost now: the fleet policy acts at once
                    view.ended(i, "EMERGENCY")
                    waiting = restart_deadline.setdefault(i, time.monotonic() + RESTART_WAIT_S)
                    if isinstance(exc, ray.exceptions.ActorUnavailableError) and time.monotonic() < waiting:
                        retry.append(i)
                        continue
                    why = str(exc).splitlines()[0][:200]
                    results[i] = _ended(f"{name}: its Ray actor died and could not be restarted ({why}); the "
                                        "flight is lost", LOST_CAUSE, timeline.last_t[i])
                    continue
                except ray.exceptions.RayTaskError as exc:  # the flight raised in the actor: that drone's fault
                    why = str(getattr(exc, "cause", None) or exc).splitlines()[0][:200]
                    results[i] = _ended(f"{name}: its flight failed in the actor: {why}", ERROR_CAUSE,
                                        timeline.last_t[i])
                if i not in restart_deadline:  # the ticks since the last poll (in order), then the ending
                    last = [r for r, k in polls.items() if k == i] + [actors[i].report.remote()]
                    for r in last:
                        polls.pop(r, None)
                        with contextlib.suppress(Exception):
                            status = ray.get(r, timeout=10.0)
                            view.seen(i, status)  # where it ended: a drone that lands later avoids it
                            timeline.add(i, status.trail)
                out = results[i].outcome
                timeline.close(i, out.state.value, out.cause if out.cause != "complete" else "")
                view.ended(i, out.state.value)
            view.push(actors, [r is None and i not in restart_deadline for i, r in enumerate(results)])
            timeline.feed()
            await asyncio.sleep(1.0 / POLL_HZ)
    return [r for r in results if r is not None]


def _ended(text: str, cause: str, t: float) -> FlightResult:
    """A drone whose flight result never came (its actor died for good, or its flight raised): a fault ending."""
    from cfknode.app.ui.summary import compute_summary

    empty = FlightRecord.empty(0)
    summary = compute_summary(empty, window=(0.0, 0.0), wall_time=0.0,
                              extra={"outcome": text, "safety_state": "EMERGENCY", "safety_cause": cause})
    return FlightResult(summary=summary, record=empty, outcome=Outcome(State.EMERGENCY, text, cause, t))


__all__ = ["FleetView", "RemoteCoordinator", "Timeline", "check_resources", "radio_resource", "run_fleet_ray"]
