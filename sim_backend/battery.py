"""A small 1S LiPo model so the simulator can serve ``pm.vbat``.

    V = V_oc(SoC) - R * I,        V_oc = V_empty + (V_full - V_empty) * SoC,   SoC' = -I / C

- ``V_oc`` is linear in the state of charge between ``v_empty`` and ``v_full``; the start SoC
  is the one whose open-circuit voltage is ``sim.battery_voltage``.
- ``I`` is the avionics' idle current plus the motors' electrical power over the terminal
  voltage. The motors' power comes from momentum theory, ``P = F^1.5 / sqrt(2 rho A)`` per
  rotor, divided by an overall efficiency fitted so that a 29 g Crazyflie 2.1 hovers on about
  2 A (250 mAh lasts ~7 min), which also gives the typical ~0.3 V sag from idle to hover.
- The firmware compensates thrust for the battery voltage (docs/hardware.md#thrust-map), so the voltage does not
  feed back into the motor forces here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable


@dataclass(frozen=True)
class BatteryParams:
    capacity_ah: float = 0.250  # Crazyflie 2.1 stock LiPo
    v_full: float = 4.2  # V, open circuit at 100 %
    v_empty: float = 3.0  # V, open circuit at 0 % (firmware pm.criticalLowVoltage)
    internal_resistance: float = 0.15  # ohm, cell + connector + wiring
    idle_current: float = 0.1  # A, avionics and radio
    rotor_disk_area: float = 1.59e-3  # m^2, 45 mm propeller
    air_density: float = 1.225  # kg/m^3
    efficiency: float = 0.16  # ideal induced power / electrical power (motor, ESC, figure of merit)


class Battery:
    """State of charge and terminal voltage under the motors' load; ``update`` once per plant step."""

    def __init__(self, initial_voltage: float, params: BatteryParams = BatteryParams()) -> None:
        self.params = params
        span = params.v_full - params.v_empty
        self.soc = min(max((initial_voltage - params.v_empty) / span, 0.0), 1.0)
        self.current = params.idle_current
        self.charge_drawn = 0.0  # Ah
        # P = sum F_i^1.5 * k_power per rotor.
        self._k_power = 1.0 / (params.efficiency * math.sqrt(2.0 * params.air_density * params.rotor_disk_area))
        self.voltage = self._terminal_voltage(self.current)

    @property
    def open_circuit_voltage(self) -> float:
        p = self.params
        return p.v_empty + (p.v_full - p.v_empty) * self.soc

    def electrical_power(self, motor_forces: Iterable[float]) -> float:
        """Electrical power [W] the motors draw to produce ``motor_forces`` [N]."""
        return self._k_power * sum(f * math.sqrt(f) for f in motor_forces if f > 0.0)

    def update(self, motor_forces: Iterable[float], dt: float) -> float:
        """Draw the load for ``dt`` seconds; returns the new terminal voltage."""
        p = self.params
        power = self.electrical_power(motor_forces)
        v_oc = self.open_circuit_voltage
        # Constant-power load on a source with internal resistance: solve V = V_oc - R P / V - R I0
        # for the upper root (V = V_oc - R I with I = I0 + P / V).
        b = v_oc - p.internal_resistance * p.idle_current
        disc = b * b - 4.0 * p.internal_resistance * power
        v = 0.5 * (b + math.sqrt(disc)) if disc > 0.0 else 0.5 * b
        self.current = p.idle_current + power / v
        drawn = self.current * dt / 3600.0
        self.charge_drawn += drawn
        self.soc = max(self.soc - drawn / p.capacity_ah, 0.0)
        self.voltage = v
        return v

    def _terminal_voltage(self, current: float) -> float:
        return self.open_circuit_voltage - self.params.internal_resistance * current
