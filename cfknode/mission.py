"""Wiring: build the parts a configuration asks for, fly, and summarise.

This is the one place that knows which backend is in use. The flight loop itself sees
only a clock, a pose source, a safety supervisor (which owns the radio) and a log,
identical in simulation and on hardware. Fault injection (``faults:``) is installed here,
around the simulator's parts, and nowhere in the flight path.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from cfknode import __version__
from cfknode.config import Config, ConfigError
from cfknode.flight.clock import SimClock, WallClock
from cfknode.flight.estimator import VelocityEstimator
from cfknode.flight.flightlog import FlightLog
from cfknode.flight.mpc_codegen import default_cache_dir
from cfknode.flight.loop import FlightParts, FlightRecord, TickObserver, fly
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc
from cfknode.flight.radio import CflibRadio
from cfknode.flight.summary import FlightSummary, compute_summary
from cfknode.flight.trajectory import make_trajectory
from cfknode.safety.operator import EstopMailbox, mailbox_dir
from cfknode.safety.supervisor import Outcome, Supervisor, SupervisorInputs
from cfknode.safety.watchdogs import radio_link_status, worst_link


class MissionError(RuntimeError):
    """A flight could not start or finish; the message is one line for the user."""


@dataclass(frozen=True)
class FlightResult:
    summary: FlightSummary
    record: FlightRecord
    outcome: Outcome  # how the flight ended; ``outcome.message`` is the line the user sees


def build_controller(cfg: Config) -> TranslationalMpc | None:
    if cfg.controller.kind == "geometric":
        return None
    return TranslationalMpc(cfg.controller, cfg.vehicle)


def build_model_slot(cfg: Config) -> ModelSlot | None:
    """The KNODE residual to fly with, loaded before take-off so a bad file refuses the flight."""
    ctrl = cfg.controller
    if ctrl.kind == "geometric":
        if ctrl.model:
            raise ConfigError("controller.model is set but controller.kind is geometric, which uses no model")
        return None
    if ctrl.kind == "knode-mpc" and not ctrl.model:
        raise ConfigError("controller.kind knode-mpc needs a model file: --model FILE (see cfknode train)")
    if not ctrl.model:
        return None
    from cfknode.models.modelfile import ModelFileError, load_model
    from cfknode.models.residual_np import ResidualQueue

    try:
        queue = ResidualQueue.from_model_file(load_model(ctrl.model))
    except ModelFileError as exc:
        raise ConfigError(f"refusing to fly: {exc}") from None
    return ModelSlot(queue, version=1)


def run_flight(
    cfg: Config,
    name_hint: str = "flight",
    observers: Sequence[TickObserver] = (),
    on_supervisor: Callable[[Supervisor], None] | None = None,
) -> FlightResult:
    """Fly one mission with the configured backend and return its summary.

    ``observers`` get every tick (a training recorder, a dashboard); the injected faults'
    observers run after them. ``on_supervisor(supervisor)`` is called once before take-off,
    for operator controls outside the loop (the dashboard's e-stop key calls its
    ``request_land()`` / ``request_stop()``).
    """
    if cfg.backend != "sim":
        raise ConfigError("backend 'cf' (hardware) is not available in this version; use --backend sim")
    if not cfg.radio.uri.startswith("sim://"):
        raise ConfigError(f"config key 'radio.uri' must be a sim:// URI with backend sim, got {cfg.radio.uri!r}")
    from cfknode.sim_backend.faults import check_faults

    check_faults(cfg)
    model = build_model_slot(cfg)
    loaded_model = model is not None
    if model is None and cfg.faults.nan_model_at >= 0:
        model = ModelSlot(None)  # nominal until the injected model is swapped in
    mpc = build_controller(cfg)  # built (and compiled) before the clock starts
    with _sim_backend(cfg) as (sim, mocap, radio, clock, faults):
        trajectory = make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float))
        link = radio_link_status(radio)
        if faults.link_status is not None:
            link = worst_link(link, faults.link_status)
        with FlightLog.create(cfg.log.dir, cfg.to_dict(), __version__, name_hint) as log:
            supervisor = Supervisor.from_config(
                cfg,
                radio,
                trajectory=trajectory,
                log=log,
                deadlines_apply=not clock.lockstep,
                inputs=SupervisorInputs(battery_voltage=lambda: sim.battery_voltage, link_status=link),
            )
            parts = FlightParts(
                clock=clock,
                mocap=mocap,
                estimator=VelocityEstimator(cfg.estimator),
                trajectory=trajectory,
                mpc=faults.controller(mpc, clock.now),
                supervisor=supervisor,
                log=log,
                vehicle=cfg.vehicle,
                controller=cfg.controller,
                truth=lambda: sim.state,
                model=model,
                observers=[*observers, *faults.observers(model)],
                estop=EstopMailbox(mailbox_dir(cfg.safety.estop_dir), cfg.hardware.robot),
            )
            if on_supervisor is not None:
                on_supervisor(supervisor)
            record = asyncio.run(fly(parts))
            radio.shutdown()
            firmware_after = _firmware_after_handback(sim, clock)
            outcome = supervisor.outcome()
            summary = compute_summary(
                t=record.t,
                p=record.p,
                p_ref=record.p_ref,
                compute_s=record.compute_s,
                solve_s=record.solve_s,
                missed=record.missed,
                window=trajectory.pattern_window,
                wall_time=record.wall_time,
                log_path=str(log.path),
                extra={
                    "outcome": outcome.message,
                    "safety_state": outcome.state.value,
                    "safety_cause": outcome.cause,
                    "fallback_ticks": record.fallbacks,
                    "fallback_reasons": dict(record.fallback_reasons),
                    "fence_excursion_m": float(supervisor.fence.excursion(record.p).max()) if record.ticks else 0.0,
                    "controller": "knode-mpc" if loaded_model else cfg.controller.kind,
                    "model": cfg.controller.model or None,
                    "solver": cfg.controller.solver if mpc is not None else "none",
                    "lockstep": not cfg.sim.realtime,
                    "mocap_dropouts": mocap.stats().dropouts,
                    "firmware_after_shutdown": firmware_after,
                    "vehicle_after_shutdown": _vehicle_after(sim),
                },
            )
            log.write("/summary", record.t[-1] if record.ticks else 0.0, summary.to_dict())
    return FlightResult(summary=summary, record=record, outcome=outcome)


def _vehicle_after(sim: Any) -> dict[str, Any]:
    """Where the simulated drone ended and whether its motors run (after the hand-back)."""
    return {
        "position": [round(float(v), 4) for v in sim.state[:3]],
        "motors": [int(m) for m in sim.firmware.motor_commands],
        "on_ground": bool(sim.vehicle.on_ground),
    }


def _firmware_after_handback(sim, clock) -> str:
    """The simulated firmware's state once the handback has settled (lockstep only).

    The firmware's 2 s landed hysteresis decides between Landed and Locked after the
    radio stops streaming, so a lockstep flight runs the simulator on to show which.
    """
    if clock.lockstep:
        sim.step_to(sim.t + 2.5)
    return sim.firmware.supervisor_state


@contextlib.contextmanager
def _sim_backend(cfg: Config) -> Iterator[tuple]:
    """The simulated Crazyflie behind the real cflib path: sim:// driver, simulated mocap, a clock,
    and the configured faults installed around them."""
    from cfknode.mocap.simulated import SimulatedMocap
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.faults import install_faults
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
    from cfknode.sim_backend.realtime import RealtimeStepper

    sim = SimCrazyflie(cfg)
    faults = install_faults(sim, cfg)
    mocap = SimulatedMocap.from_config(sim, cfg.sim, outages=faults.mocap_outages)
    register_simulator(cfg.radio.uri, sim)
    clock: WallClock | SimClock = WallClock() if cfg.sim.realtime else SimClock(sim)
    radio = CflibRadio.from_config(
        cfg.radio,
        lockstep=clock.lockstep,
        clock=clock.now,
        # In lockstep the shutdown's zero stream must span simulated time, so the radio steps the sim.
        advance=sim.step_to if clock.lockstep else None,
        rw_cache=str(default_cache_dir() / "cflib"),  # TOC cache, as on hardware
    )
    stepper = None
    try:
        radio.connect()
        if cfg.sim.realtime:
            stepper = RealtimeStepper(sim, clock.now).start()
        yield sim, mocap, radio, clock, faults
    finally:
        radio.shutdown()
        if stepper is not None:
            stepper.stop()
        mocap.close()
        unregister_simulator(cfg.radio.uri)
