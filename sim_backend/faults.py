"""Fault injection for the simulator (``faults:`` in the config; ``cfknode/scenarios/*.yaml``).

Each fault is a wrapper around a part that already exists, so the parts themselves stay
fault-free and the flight path is the one that flies on hardware:

- radio outages: the simulator's firmware behind a proxy that loses every packet from the
  host (``on_*`` inputs) inside the windows. As cflib's radio driver does, 100 lost packets
  in a row end the link for good ("Too many packets lost"): from then on nothing arrives,
  and the firmware's own watchdog takes over (docs/hardware.md#commander-watchdog). ``link_status`` is what the host's
  link statistics would show: the silence since the last acknowledged packet, and the loss.
- gusts: a ``Vehicle`` whose wind follows the gust schedule (it acts through ``sim.drag``, and on
  the realistic plant through the rotors' drag too).
- battery drop: the cell's open-circuit voltage falls to a value at a time (a failing cell);
  the battery model's sag under load then does the rest.
- solver failures: the MPC's answer is replaced by a failed one inside the windows.
- NaN model: at a time, the KNODE slot is swapped (the online learner's path) to a model
  whose residual is NaN, so the MPC reports a non-finite input and the fallback flies.
- SIGINT: the flight sends itself the real signal at the given flight times.
- mocap outages are a ``SimulatedMocap`` option (``outages``), wired in the mission.

A trainer crash is injected by online learning itself (``online.inject``), not here.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from cfknode.kernel.errors import ConfigError
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.settings import FaultsConfig, FaultWindow, Gust, SimConfig
from cfknode.kernel.link import LinkStatus
from cfknode.sim_backend.aero_vehicle import AeroVehicle
from cfknode.sim_backend.scenario import wind_at
from cfknode.sim_backend.timed_swap import SwapAt
from cfknode.sim_backend.vehicle import Vehicle

_TIME_EPS = 1e-9
LINK_LOST_AFTER = 100  # cflib radiodriver: consecutive failed transactions before link_error_callback
LINK_LOST_MESSAGE = "Too many packets lost"


def _in_windows(t: float, windows: Sequence[tuple[float, float]]) -> bool:
    return any(t0 - _TIME_EPS <= t < t1 - _TIME_EPS for t0, t1 in windows)


def _spans(windows: Sequence[FaultWindow]) -> tuple[tuple[float, float], ...]:
    return tuple((w.t, w.t + w.duration) for w in windows)


def check_faults(faults: FaultsConfig, sim: SimConfig, controller_kind: str, backend: str) -> None:
    """Refuse fault settings that cannot be injected; one-line ``ConfigError``."""
    for key in ("mocap_outages", "radio_outages", "solver_failures", "gusts"):
        for i, window in enumerate(getattr(faults, key)):
            if window.t < 0 or window.duration <= 0:
                raise ConfigError(f"config key 'faults.{key}[{i}]' needs t >= 0 and duration > 0, got {window}")
    if faults.gusts and not any(c > 0 for c in sim.drag):
        raise ConfigError("config key 'faults.gusts' needs 'sim.drag' > 0: wind acts on the drone through drag")
    if faults.nan_model_at >= 0 and controller_kind == "geometric":
        raise ConfigError("config key 'faults.nan_model_at' needs an MPC controller; geometric uses no model")
    if backend != "sim" and (faults != dataclasses.replace(faults, **_NO_FAULTS)):
        raise ConfigError("config section 'faults' injects faults into the simulator; it needs backend sim")


_NO_FAULTS: dict[str, Any] = {
    "mocap_outages": (), "radio_outages": (), "solver_failures": (), "nan_model_at": -1.0,
    "battery_drop_at": -1.0, "gusts": (), "sigint_at": (),
}


# --- radio ---------------------------------------------------------------------------------------


class RadioBlackout:
    """Loses the host's packets inside the windows, and after 100 in a row, for good."""

    def __init__(self, sim: Any, windows: Sequence[FaultWindow]) -> None:
        self._windows = _spans(windows)
        self._run = 0
        self._last_ok = 0.0
        self.lost: str | None = None
        self.dropped = 0
        sim.firmware = _LossyFirmware(sim.firmware, self)

    def drops(self, t: float) -> bool:
        """Whether a packet arriving at sim time ``t`` is lost."""
        if self.lost is None and not _in_windows(t, self._windows):
            self._run = 0
            self._last_ok = t
            return False
        self.dropped += 1
        self._run += 1
        if self._run >= LINK_LOST_AFTER and self.lost is None:
            self.lost = LINK_LOST_MESSAGE
        return True

    def link_status(self, now: float) -> LinkStatus:
        silent = self.lost is not None or _in_windows(now, self._windows)
        return LinkStatus(lost=self.lost, silence_s=now - self._last_ok if silent else 0.0)


class _LossyFirmware:
    """The firmware as the radio reaches it: every ``on_*`` input (a packet) may be lost."""

    def __init__(self, inner: Any, blackout: RadioBlackout) -> None:
        self._inner = inner
        self._blackout = blackout
        self.step = inner.step  # the simulator's hot path: no proxy lookup per plant step

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if not (name.startswith("on_") and callable(attr)):
            return attr
        blackout = self._blackout

        def packet(t: float, *args: Any, **kwargs: Any) -> Any:
            if blackout.drops(t):
                return None
            return attr(t, *args, **kwargs)

        return packet


# --- wind ----------------------------------------------------------------------------------------


class GustVehicle(Vehicle):
    """The plant with the configured wind replaced by each gust's wind while it blows."""

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig, gusts: Sequence[Gust]) -> None:
        super().__init__(vehicle, sim)
        self._calm = tuple(sim.wind)
        self._gusts = tuple(gusts)
        self._steps = 0

    def step(self, motor_commands: Sequence[float], mass: float) -> None:
        # Called once per plant step (SimCrazyflie.step_to), so the step count is sim time.
        t = self._steps * self.dt
        self._steps += 1
        self._wind = wind_at(t, self._calm, self._gusts)
        super().step(motor_commands, mass)


# --- battery -------------------------------------------------------------------------------------


class _BatteryDrop:
    """Step observer: at ``t`` the cell's open-circuit voltage falls to ``volts``."""

    def __init__(self, battery: Any, t: float, volts: float) -> None:
        self._battery = battery
        self._t = t
        self._volts = volts
        self.done = False

    def __call__(self, t: float, state: np.ndarray) -> None:
        if self.done or t < self._t - _TIME_EPS:
            return
        p = self._battery.params
        self._battery.soc = min(max((self._volts - p.v_empty) / (p.v_full - p.v_empty), 0.0), 1.0)
        self.done = True


# --- controller and model ------------------------------------------------------------------------


class FailingSolver:
    """An MPC whose answers inside the windows are failures (the solve still runs, as it would)."""

    def __init__(self, inner: Any, windows: Sequence[FaultWindow], now: Callable[[], float]) -> None:
        self._inner = inner
        self._windows = _spans(windows)
        self._now = now
        self.injected = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)  # the rest of the MPC (its stats, backend, ...) passes through

    def solve(self, x0: np.ndarray, params: Any, residual: Any = None) -> Any:
        sol = self._inner.solve(x0, params, residual)
        if not _in_windows(self._now(), self._windows):
            return sol
        self.injected += 1
        return dataclasses.replace(sol, acc=np.zeros(3), ok=False, status="injected_failure",
                                   x_pred=np.full_like(sol.x_pred, np.nan), u_pred=np.full_like(sol.u_pred, np.nan))


class NanResidual:
    """A KNODE model gone bad: its residual is NaN everywhere (``Linearisable``)."""

    def linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = x_nodes.shape[0]
        return np.full((n, 3), np.nan), np.zeros((n, 3, x_nodes.shape[1])), np.zeros((n, 3, u_nodes.shape[1]))

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.full(np.shape(x)[:-1] + (3,), np.nan)


@dataclass
class _SelfInterrupt:
    """Tick observer: sends this process SIGINT at each of ``times`` (the real signal)."""

    times: tuple[float, ...]
    sent: int = 0
    pid: int = field(default_factory=os.getpid)

    def on_tick(self, tick: Any) -> None:
        if self.sent < len(self.times) and tick.t >= self.times[self.sent] - _TIME_EPS:
            self.sent += 1
            os.kill(self.pid, signal.SIGINT)


# --- all of them ---------------------------------------------------------------------------------


@dataclass
class SimFaults:
    """The faults installed on one simulator, and the wrappers the mission puts around its parts."""

    config: FaultsConfig
    blackout: RadioBlackout | None = None
    battery_drop: _BatteryDrop | None = None

    @property
    def link_status(self) -> Callable[[float], LinkStatus] | None:
        return self.blackout.link_status if self.blackout is not None else None

    def controller(self, mpc: Any, now: Callable[[], float]) -> Any:
        """``mpc``, failing inside ``faults.solver_failures``."""
        windows = self.config.solver_failures
        return FailingSolver(mpc, windows, now) if windows and mpc is not None else mpc

    def observers(self, model_slot: Any) -> list[Any]:
        faults = self.config
        out: list[Any] = []
        if faults.nan_model_at >= 0:
            if model_slot is None:
                raise ValueError("faults.nan_model_at needs a model slot to swap into")
            out.append(SwapAt(model_slot, NanResidual(), faults.nan_model_at))
        if faults.sigint_at:
            if threading.current_thread() is not threading.main_thread():
                # Only the main thread's flight can catch SIGINT; elsewhere it would hit the main thread.
                raise ConfigError("config key 'faults.sigint_at' needs the flight in the main thread")
            out.append(_SelfInterrupt(tuple(sorted(faults.sigint_at))))
        return out

    @property
    def mocap_outages(self) -> tuple[tuple[float, float], ...]:
        return tuple((w.t, w.duration) for w in self.config.mocap_outages)


def install_faults(sim: Any, faults: FaultsConfig) -> SimFaults:
    """Install ``faults`` on a fresh ``SimCrazyflie`` (before its first step)."""
    installed = SimFaults(faults)
    if faults.gusts:
        if sim.steps != 0:
            raise RuntimeError("gusts must be installed before the simulator's first step")
        if sim.sim_config.aero == "realistic":
            sim.vehicle = AeroVehicle(sim.vehicle_config, sim.sim_config, faults.gusts)
        else:
            sim.vehicle = GustVehicle(sim.vehicle_config, sim.sim_config, faults.gusts)
    if faults.radio_outages:
        installed.blackout = RadioBlackout(sim, faults.radio_outages)
    if faults.battery_drop_at >= 0:
        installed.battery_drop = _BatteryDrop(sim.battery, faults.battery_drop_at, faults.battery_drop_to)
        sim.add_step_observer(installed.battery_drop)
    return installed


__all__ = [
    "FailingSolver", "GustVehicle", "LINK_LOST_AFTER", "NanResidual", "RadioBlackout", "SimFaults",
    "check_faults", "install_faults",
]
