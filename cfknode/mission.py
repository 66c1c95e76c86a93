"""Wiring: build the parts a configuration asks for, fly, and summarise.

This is the one place that knows which backend is in use. The flight loop itself sees
only a clock, a pose source, a radio and a log, identical in simulation and on hardware.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from cfknode import __version__
from cfknode.config import Config, ConfigError
from cfknode.flight.clock import SimClock, WallClock
from cfknode.flight.estimator import VelocityEstimator
from cfknode.flight.flightlog import FlightLog
from cfknode.flight.mpc_codegen import default_cache_dir
from cfknode.flight.loop import FlightParts, FlightRecord, fly
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc
from cfknode.flight.radio import CflibRadio
from cfknode.flight.summary import FlightSummary, compute_summary
from cfknode.flight.trajectory import make_trajectory


class MissionError(RuntimeError):
    """A flight could not start or finish; the message is one line for the user."""


@dataclass(frozen=True)
class FlightResult:
    summary: FlightSummary
    record: FlightRecord


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


def run_flight(cfg: Config, name_hint: str = "flight") -> FlightResult:
    """Fly one mission with the configured backend and return its summary."""
    if cfg.backend != "sim":
        raise ConfigError("backend 'cf' (hardware) is not available in this version; use --backend sim")
    if not cfg.radio.uri.startswith("sim://"):
        raise ConfigError(f"config key 'radio.uri' must be a sim:// URI with backend sim, got {cfg.radio.uri!r}")
    model = build_model_slot(cfg)
    mpc = build_controller(cfg)  # built (and compiled) before the clock starts
    with _sim_backend(cfg) as (sim, mocap, radio, clock):
        trajectory = make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float))
        with FlightLog.create(cfg.log.dir, cfg.to_dict(), __version__, name_hint) as log:
            parts = FlightParts(
                clock=clock,
                mocap=mocap,
                estimator=VelocityEstimator(cfg.estimator),
                trajectory=trajectory,
                mpc=mpc,
                radio=radio,
                log=log,
                vehicle=cfg.vehicle,
                controller=cfg.controller,
                truth=lambda: sim.state,
                model=model,
            )
            record = asyncio.run(fly(parts))
            radio.shutdown()
            firmware_after = _firmware_after_handback(sim, clock)
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
                    "fallback_ticks": record.fallbacks,
                    "controller": "knode-mpc" if model is not None else cfg.controller.kind,
                    "model": cfg.controller.model or None,
                    "solver": cfg.controller.solver if mpc is not None else "none",
                    "lockstep": not cfg.sim.realtime,
                    "mocap_dropouts": mocap.stats().dropouts,
                    "firmware_after_shutdown": firmware_after,
                },
            )
            log.write("/summary", record.t[-1] if record.ticks else 0.0, summary.to_dict())
    return FlightResult(summary=summary, record=record)


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
    """The simulated Crazyflie behind the real cflib path: sim:// driver, simulated mocap, a clock."""
    from cfknode.mocap.simulated import SimulatedMocap
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
    from cfknode.sim_backend.realtime import RealtimeStepper

    sim = SimCrazyflie(cfg)
    mocap = SimulatedMocap.from_config(sim, cfg.sim)
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
        yield sim, mocap, radio, clock
    finally:
        radio.shutdown()
        if stepper is not None:
            stepper.stop()
        mocap.close()
        unregister_simulator(cfg.radio.uri)
