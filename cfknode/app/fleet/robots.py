"""A fleet of named robots from the robots file: ``cfknode fly --robots cf1,cf2,cf3`` (docs/fleet.md).

The hardware counterpart of ``run_fleet`` (cfknode/app/fleet/flight.py), sharing its coordinator,
log channels, pre-flight checks, flight and summary: every robot flies its own estimator,
``Controller`` and ``Supervisor`` in one event loop, on one wall clock (real time, not
lockstep), with its own link and one shared mocap connection (backends/robot_fleet.py).

Before anything connects, the references from the robots' ``initial_position``s are checked
for ``fleet.min_separation`` and the radios (from the robots' real URIs) for their packet
budget. After the pre-flight checks, the references are rebuilt from where the mocap sees
each robot and checked again, so the flight that takes off is the flight that was checked.
"""

from __future__ import annotations

import logging
import math
import re
from typing import Any, Callable, Sequence

import numpy as np

from cfknode.app.backends.robots import Robot, load_robots
from cfknode.app.config import Config, ConfigError
from cfknode.app.fleet.flight import (FleetCoordinator, FleetPlan, FleetResult, fly_drones, placed_fence_events,
                                      preflight, separation_refusal)
from cfknode.flight.formation import HoldableReference, RotatedReference, stack_level
from cfknode.flight.trajectory import make_trajectory
from cfknode.safety.estop_mailbox import safe_name

_logger = logging.getLogger(__name__)


def select_robots(cfg: Config, names: Sequence[str]) -> list[Robot]:
    """The named robots of ``hardware.robots_file``; one-line ``ConfigError`` for an unknown,
    disabled or repeated name, listing the robots that can fly."""
    file = load_robots(cfg.hardware.robots_file or None)
    repeated = sorted({n for n in names if list(names).count(n) > 1})
    if repeated:
        raise ConfigError(f"--robots names {', '.join(repeated)} more than once")
    unknown = [n for n in names if n not in file.robots]
    disabled = [n for n in names if n in file.robots and not file.robots[n].enabled]
    if unknown or disabled:
        enabled = [n for n, r in file.robots.items() if r.enabled]
        off = [n for n, r in file.robots.items() if not r.enabled]
        what = "; ".join(part for part in (
            f"no robot {', '.join(unknown)}" if unknown else "",
            f"{', '.join(disabled)} disabled (enabled: false)" if disabled else "") if part)
        raise ConfigError(f"--robots: {what} in {file.path}; known robots: {', '.join(enabled) or 'none'}"
                          + (f" (disabled: {', '.join(off)})" if off else ""))
    robots = [file.robots[n] for n in names]
    clash = _first_clash(names, [safe_name(n) for n in names])
    if clash is not None:
        raise ConfigError(f"--robots: {clash[0]} and {clash[1]} share the file name {safe_name(clash[0])!r} (their "
                          f"e-stop lock and mailbox entry); rename one in {file.path}")
    clash = _first_clash(names, [link_identity(r.uri) for r in robots])
    if clash is not None:
        a, b = (file.robots[n] for n in clash)
        raise ConfigError(f"--robots: {a.name} ({a.uri}) and {b.name} ({b.uri}) are the same link in {file.path}: "
                          "one Crazyflie cannot fly as two robots")
    return robots


def link_identity(uri: str) -> tuple[str, ...]:
    """What makes two URIs one vehicle: a radio's channel, data rate and address (the dongle index
    aside: two dongles reach the same Crazyflie), anything else its whole URI."""
    text = uri.strip()
    m = re.fullmatch(r"radio://\d+/(\d+)/(\w+)(?:/([0-9A-Fa-f]+))?/?(\?.*)?", text)
    if m is None:
        return ("uri", text.lower())
    return ("radio", str(int(m.group(1))), m.group(2).upper(), (m.group(3) or "E7E7E7E7E7").upper().rjust(10, "0"))


def _first_clash(names: Sequence[str], keys: Sequence[Any]) -> tuple[str, str] | None:
    """The first two names whose keys are equal, or None."""
    seen: dict[Any, str] = {}
    for name, key in zip(names, keys):
        if key in seen:
            return seen[key], name
        seen[key] = name
    return None


def robot_references(cfg: Config, starts: Sequence[Sequence[float]]) -> list[HoldableReference]:
    """Each robot's reference, taking off from where it stands (``starts``), in ``fleet.layout``.

    ``ring``: robot i flies the pattern rotated by 2 pi i / N about its centre; ``stack``:
    robot i flies it ``fleet.stack_spacing * i`` higher (and lands ``fleet.ground_spacing``
    further along the circle), as ``--fleet`` does. The take-off goes from the robot's own
    start to its first point."""
    traj, fleet = cfg.trajectory, cfg.fleet
    n = len(starts)
    center = np.array([float(traj.center[0]), float(traj.center[1]), 0.0])
    refs: list[HoldableReference] = []
    for i, start in enumerate(starts):
        p0 = np.asarray(start, dtype=float)
        if fleet.layout == "ring":
            angle = 2.0 * math.pi * i / n
            # Built from the start turned back, so the turned reference starts where the robot stands.
            c, s = math.cos(-angle), math.sin(-angle)
            d = p0 - center
            local = center + np.array([c * d[0] - s * d[1], s * d[0] + c * d[1], d[2]])
            ref: Any = RotatedReference(make_trajectory(traj, local), center[:2], angle)
        elif fleet.layout == "stack":
            ref = make_trajectory(stack_level(traj, i, fleet.stack_spacing, fleet.ground_spacing), p0)
        else:
            raise ConfigError(f"config key 'fleet.layout' must be ring or stack, got {fleet.layout!r}")
        refs.append(HoldableReference(ref))
    return refs


def check_robot_fleet(cfg: Config, names: Sequence[str]) -> tuple[list[Robot], list[Config], dict[str, float]]:
    """Everything that can be refused before connecting: the settings, the names, the references
    from the robots' initial positions (separation) and the radios (packet budget, real URIs).
    Returns the robots, each one's flight config and the packets/s per radio."""
    from cfknode.app.backends.robot_fleet import robot_configs
    from cfknode.sim_backend.faults import check_faults

    if len(names) < 2:
        raise ConfigError("a fleet of robots needs at least two names (--robots cf1,cf2)")
    if cfg.backend != "cf":
        raise ConfigError("--robots flies robots from the robots file: backend cf (leave --backend out, or cf)")
    if cfg.fleet.size >= 2:
        raise ConfigError("--robots and --fleet (fleet.size) are two kinds of fleet: give one")
    if cfg.controller.adaptation == "oracle":
        raise ConfigError("controller.adaptation oracle reads the simulator's true mass: simulation only (backend sim)")
    check_faults(cfg.faults, cfg.sim, cfg.controller.kind, cfg.backend)
    robots = select_robots(cfg, names)
    configs = robot_configs(cfg, robots)
    refs = robot_references(cfg, [r.initial_position for r in robots])
    placed_fence_events(cfg, names, refs)  # refused here; a forced fleet's events are logged once it connected
    radio_pps = preflight(cfg, names, configs, refs)
    return robots, configs, radio_pps


def run_robot_fleet(cfg: Config, names: Sequence[str], name_hint: str = "robots", console: Any = None,
                    on_coordinator: Callable[[FleetCoordinator], None] | None = None,
                    dashboard: Any = None, live: Any = None) -> FleetResult:
    """Fly the named robots together; ``ConfigError`` for a refused fleet, ``MissionError`` for
    a robot that could not be connected or failed its pre-flight checks. ``on_coordinator`` and
    ``live`` as for ``fly_drones``."""
    from cfknode.app.backends.crazyflie import HARDWARE_ERRORS
    from cfknode.app.backends.robot_fleet import RobotFleetBackend
    from cfknode.app.fleet.learning import fleet_trainers
    from cfknode.app.flight_checks import refuse_unflyable
    from cfknode.app.learning import online_model_slot
    from cfknode.app.mission import MissionError, build_controller, build_model_slot
    from cfknode.flight.tick_guard import hand_back
    from cfknode.safety.estop_mailbox import EstopMailbox, FlightRunning, MailboxError, mailbox_dir

    robots, configs, radio_pps = check_robot_fleet(cfg, names)
    forced: list[dict[str, Any]] = []
    for robot, c in zip(robots, configs):  # robots may differ in mass and thrust: each is checked
        forced.extend(refuse_unflyable(c, where=f"robot {robot.name}"))
    models = [online_model_slot(c, build_model_slot(c)) for c in configs]  # online: each robot its own slot
    mpcs = [build_controller(c) for c in configs]  # built (and compiled) before the clock starts
    boxes = [EstopMailbox(mailbox_dir(cfg.safety.estop_dir), r.name, exclusive=not r.uri.startswith("sim://"))
             for r in robots]
    try:
        for box in boxes:
            box.open()
    except (MailboxError, FlightRunning) as exc:
        for box in boxes:
            box.close()
        if isinstance(exc, FlightRunning):
            raise MissionError(f"take-off refused: {exc}") from None
        raise ConfigError(f"config key 'safety.estop_dir': {exc}") from None
    try:
        # Online learning: one shared trainer, up before any robot connects (docs/fleet.md#design).
        with fleet_trainers(configs) as trainers, RobotFleetBackend.open(cfg, robots, console) as backend:
            # Where the mocap sees them, within the pre-flight tolerance of their initial positions.
            refs = robot_references(cfg, [d.start_position for d in backend.drones])
            forced.extend(placed_fence_events(cfg, names, refs))
            line = separation_refusal(cfg, names, refs)
            if line is not None:
                raise ConfigError(line)

            def handback() -> list[dict[str, Any]]:
                out = []
                for d in backend.drones:
                    errors: list[str] = []

                    def sink(part: str, exc: BaseException, errors: list[str] = errors) -> None:
                        errors.append(f"{part} failed: {type(exc).__name__}: {exc}")
                        _logger.error("%s: %s", d.hw.robot.name, errors[-1])

                    extra = hand_back(d.radio.shutdown, d.after_handback, sink)
                    out.append({**extra, **({"internal_errors": errors} if errors else {})})
                return out

            plan = FleetPlan(names, refs, models, mpcs, boxes, radio_pps, name_hint, forced)
            return fly_drones(cfg, backend.drones, plan, handback, on_coordinator, trainers, dashboard, live)
    except HARDWARE_ERRORS as exc:
        raise MissionError(str(exc)) from exc
    finally:
        for box in boxes:
            box.close()


__all__ = ["check_robot_fleet", "robot_references", "run_robot_fleet", "select_robots"]
