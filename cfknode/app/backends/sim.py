"""The simulator backend: a simulated Crazyflie behind the real cflib path.

The simulator is registered behind cflib's ``sim://`` driver, so the stock ``Crazyflie`` and
``Commander`` encode every setpoint the simulated firmware decodes; mocap is sampled from
the plant with noise, latency and dropouts; the clock is lockstep (the loop steps the
simulator) or the wall clock (``--realtime``); configured faults are installed around it.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator

import numpy as np

from cfknode.app.backends.radio import CflibRadio, LinkSafety
from cfknode.app.backends.stale_setpoint import StalePolicy
from cfknode.app.config import Config
from cfknode.flight.mpc_codegen import default_cache_dir
from cfknode.kernel.clock import SimClock, WallClock
from cfknode.kernel.link import LinkStatus
from cfknode.mocap.simulated import SimulatedMocap
from cfknode.safety.watchdogs import radio_link_status, worst_link
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.faults import SimFaults, install_faults
from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
from cfknode.sim_backend.realtime import RealtimeStepper


class SimulatorBackend:
    """``Backend`` for ``--backend sim``; open it with ``SimulatorBackend.open(cfg)``."""

    events: tuple[dict[str, Any], ...] = ()

    def __init__(self, cfg: Config, sim: SimCrazyflie, faults: SimFaults, mocap: SimulatedMocap,
                 clock: WallClock | SimClock, radio: CflibRadio) -> None:
        self.config, self.sim, self.faults = cfg, sim, faults
        self.mocap, self.clock, self.radio = mocap, clock, radio
        self.imu = radio.imu  # the accelerometer through the real log path (None: radio.imu_log off, or no TOC)
        if radio.imu_note is not None:
            self.events = ({"level": "warning", "text": radio.imu_note, "source": "radio"},)
        self.start_position = np.asarray(cfg.sim.initial_position, dtype=float)
        link = radio_link_status(radio)
        self._link = worst_link(link, faults.link_status) if faults.link_status is not None else link

    @classmethod
    @contextlib.contextmanager
    def open(cls, cfg: Config) -> Iterator["SimulatorBackend"]:
        sim = SimCrazyflie(cfg.vehicle, cfg.sim)
        faults = install_faults(sim, cfg.faults)
        mocap = SimulatedMocap.from_config(sim, cfg.sim, outages=faults.mocap_outages)
        register_simulator(cfg.radio.uri, sim)
        clock: WallClock | SimClock = WallClock() if cfg.sim.realtime else SimClock(sim)
        # In lockstep the shutdown's zero stream must span simulated time, so the radio steps the sim.
        radio = sim_radio(cfg, clock.now, sim.step_to if clock.lockstep else None)
        stepper = None
        try:
            radio.connect()
            if cfg.sim.realtime:
                stepper = RealtimeStepper(sim, clock.now).start()
            yield cls(cfg, sim, faults, mocap, clock, radio)
        finally:
            radio.shutdown()
            if stepper is not None:
                stepper.stop()
            mocap.close()
            unregister_simulator(cfg.radio.uri)

    def truth(self) -> np.ndarray:
        return self.sim.state

    def true_mass(self) -> float:
        return self.sim.mass

    def battery_voltage(self) -> float | None:
        return self.sim.battery_voltage

    def link_status(self, now: float) -> LinkStatus:
        return self._link(now)

    def wrap_solver(self, solver: Any) -> Any:
        return self.faults.controller(solver, self.clock.now)

    def fault_observers(self, model: Any) -> list[Any]:
        return self.faults.observers(model)

    def after_handback(self) -> dict[str, Any]:
        return {"firmware_after_shutdown": firmware_after_handback(self.sim, self.clock.lockstep),
                "vehicle_after_shutdown": vehicle_after(self.sim)}


def sim_radio(cfg: Config, clock: Callable[[], float], advance: Callable[[float], None] | None) -> CflibRadio:
    """A simulated drone's link, the stock cflib path as on hardware: lockstep when given ``advance`` (what steps
    its simulator, or a fleet's world); one builder, so a single flight's and a fleet drone's links stay alike."""
    return CflibRadio(
        cfg.radio.uri,
        tx_rate_hz=cfg.radio.tx_rate_hz,
        lockstep=advance is not None,
        clock=clock,
        advance=advance,
        rw_cache=str(default_cache_dir() / "cflib"),  # TOC cache, as on hardware
        imu_log=cfg.radio.imu_log,
        safety=LinkSafety(stale=stale_policy(cfg)),
    )


def stale_policy(cfg: Config) -> StalePolicy:
    """When the radio takes a setpoint for stale (threaded radios: the loop stalled)."""
    return StalePolicy(cfg.radio.stale_hold_slots, cfg.radio.stale_stop_s)


def vehicle_after(sim: SimCrazyflie) -> dict[str, Any]:
    """Where the simulated drone ended and whether its motors run (after the hand-back)."""
    return {
        "position": [round(float(v), 4) for v in sim.state[:3]],
        "motors": [int(m) for m in sim.firmware.motor_commands],
        "on_ground": bool(sim.vehicle.on_ground),
    }


def firmware_after_handback(sim: SimCrazyflie, lockstep: bool) -> str:
    """The simulated firmware's state once the handback has settled.

    The firmware's 2 s landed hysteresis decides between Landed and Locked after the radio
    stops streaming, so a lockstep flight runs the simulator on to show which.
    """
    if lockstep:
        sim.step_to(sim.t + 2.5)
    return sim.firmware.supervisor_state


__all__ = ["SimulatorBackend", "firmware_after_handback", "sim_radio", "stale_policy", "vehicle_after"]
