"""``SimCrazyflie``: the plant, the onboard firmware, the scenario and the battery, stepped together.

One plant step (``sim.dt``, 2 ms) = one firmware stabilizer iteration on the state at the
start of the step (500 Hz, motor commands held over the step), the step's mass from the
scenario, one RK4 step of the plant, one battery update, then the step observers.
Sim time is ``k * dt`` for an integer step count ``k``, never a running float sum.
"""

from __future__ import annotations

import threading
from typing import Callable

import numpy as np

from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.battery import Battery
from cfknode.sim_backend.firmware import Firmware
from cfknode.sim_backend.plant import thrust_scale_at
from cfknode.sim_backend.scenario import MassSchedule
from cfknode.sim_backend.settings import SimConfig
from cfknode.sim_backend.aero_vehicle import make_vehicle

StepObserver = Callable[[float, np.ndarray], None]


class SimCrazyflie:
    """A simulated Crazyflie 2.1, deterministic for a given config (``sim.seed``).

    ``lock`` (re-entrant, so a step observer may call back into the firmware) guards stepping
    and every firmware input: in ``--realtime`` the cflib driver thread and the stepping thread
    differ. ``rng`` is the simulator's seeded generator for stochastic scenario elements.
    """

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig) -> None:
        """``vehicle``: the airframe the firmware and plant are built for; ``sim``: the plant and scenario."""
        self.vehicle_config = vehicle
        self.sim_config = sim
        self.dt = sim.dt
        self.lock = threading.RLock()
        self.rng = np.random.default_rng(sim.seed)
        self.vehicle = make_vehicle(vehicle, sim)
        self.firmware = Firmware(vehicle, self.dt, lock=self.lock, attitude_gain=sim.attitude_gain,
                                 yaw_gain=sim.yaw_gain)
        self.battery = Battery(sim.battery_voltage)
        self._nominal_mass = vehicle.mass
        self._mass_schedule = MassSchedule(self._nominal_mass, sim.mass_changes)
        self._mass = self._mass_schedule.at(0.0)
        self._k = 0
        self._observers: list[StepObserver] = []
        self.failure: str | None = None  # why the plant stopped (it raised); time still advances
        self._firmware_runs = True  # while frozen: until the firmware itself raises

    @property
    def t(self) -> float:
        """Sim time [s]."""
        return self._k * self.dt

    @property
    def steps(self) -> int:
        return self._k

    @property
    def state(self) -> np.ndarray:
        """True rigid-body state (13): p, v, q (w, x, y, z), body rates."""
        return self.vehicle.state

    @property
    def mass(self) -> float:
        """True mass [kg] used by the latest plant step."""
        return self._mass

    @property
    def motor_forces(self) -> np.ndarray:
        """Current motor forces [N], m1..m4."""
        return self.vehicle.motor_forces

    @property
    def battery_voltage(self) -> float:
        """Terminal voltage under the current load [V] (what ``pm.vbat`` reports)."""
        return self.battery.voltage

    def add_step_observer(self, cb: StepObserver) -> None:
        """``cb(t, state13)`` after every plant step, with the time at the end of the step."""
        with self.lock:
            self._observers.append(cb)

    def step_to(self, t_target: float) -> None:
        """Advance in ``dt`` steps until ``t >= t_target - 1e-12``.

        A step that raises (a zero mass, a broken scenario) raises once and freezes the plant
        where it was: later calls advance the time and the firmware (so the flight's stop and
        the radio's hand-back, which wait on simulated time, finish, and the firmware shows
        what it made of them), but not the vehicle. ``failure`` says why.
        """
        with self.lock:
            if self.failure is not None:
                self._step_frozen(t_target)
                return
            try:
                self._step_to(t_target)
            except Exception as exc:
                self.failure = f"{type(exc).__name__}: {exc} at t = {self.t:.3f} s"
                raise

    def _step_frozen(self, t_target: float) -> None:
        x = self.vehicle.state_list()
        while self._k * self.dt < t_target - 1e-12:
            if self._firmware_runs:
                try:
                    self.firmware.step(self._k * self.dt, x)
                except Exception:  # noqa: BLE001 - the firmware was what failed: it stays where it is
                    self._firmware_runs = False
            self._k += 1

    def _step_to(self, t_target: float) -> None:
        dt = self.dt
        vehicle = self.vehicle
        firmware = self.firmware
        battery = self.battery
        sag = self.sim_config.battery_sag_per_s > 0.0
        while self._k * dt < t_target - 1e-12:
            t = self._k * dt
            x = vehicle.state_list()
            motors = firmware.step(t, x)
            self._mass = mass = self._mass_schedule.at(t)
            if sag:
                vehicle.set_thrust_scale(thrust_scale_at(t, self.sim_config))
            vehicle.step(motors, mass)
            self._k += 1
            battery.update(vehicle.state_list()[13:], dt)
            if self._observers:
                t_new = self._k * dt
                state = vehicle.state
                for cb in self._observers:
                    cb(t_new, state)
