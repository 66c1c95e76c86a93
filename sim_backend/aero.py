"""The realistic plant's aerodynamic terms, as pure functions on plain floats (the plant's hot path).

Each term and its source: docs/hardware.md#simulator. In short:

- rotor drag and inflow: a force against the airspeed, ``c_drag`` per m/s in the rotor plane and
  ``c_inflow`` per m/s along the rotor axis (a climbing rotor loses thrust), both per unit of
  nominal mass at hover rotor speed and proportional to the summed rotor speeds, as in
  Förster's identification of the Crazyflie 2.0 (F = -k_d * sum(omega) * v);
- ground effect: extra thrust near the floor, interpolated in the values Neural-Swarm2's learned
  ground model gives for a Crazyflie;
- downwash: the wake of a drone above, by vertical gap, as Neural-Swarm2's learned interaction
  model gives it, with a Gaussian lateral profile.
"""

from __future__ import annotations

import math
from typing import Sequence

# Height of the vehicle above the floor [m] -> extra thrust / thrust. Neural-Swarm2's learned ground
# model on a 29 g Crazyflie: +3.1 g at 3 cm, +2.9 g at 5 cm, +2.1 g at 10 cm, about 0 above 0.12-0.15 m.
GROUND_EFFECT_TABLE: tuple[tuple[float, float], ...] = (
    (0.0, 3.1 / 29.0), (0.03, 3.1 / 29.0), (0.05, 2.9 / 29.0), (0.10, 2.1 / 29.0), (0.15, 0.0),
)
# Vertical gap below the upper drone [m] -> downward force on the lower one / the upper one's thrust.
# Neural-Swarm2's learned interaction model between two hovering 29 g Crazyflies (gram-force / 29 g);
# the ramp from 0 at no gap and the taper beyond 1 m to 1.5 m are this simulator's assumptions.
DOWNWASH_TABLE: tuple[tuple[float, float], ...] = (
    (0.0, 0.0), (0.10, 6.4 / 29.0), (0.15, 7.7 / 29.0), (0.20, 8.2 / 29.0), (0.25, 8.4 / 29.0),
    (0.30, 8.3 / 29.0), (0.40, 7.3 / 29.0), (0.50, 5.9 / 29.0), (0.60, 4.2 / 29.0), (0.80, 2.5 / 29.0),
    (1.00, 2.2 / 29.0), (1.50, 0.0),
)


def interpolate(table: Sequence[tuple[float, float]], x: float) -> float:
    """Piecewise-linear in ``table`` (ascending x), held at the first value below it and at the last above."""
    if x <= table[0][0]:
        return table[0][1]
    for (x0, y0), (x1, y1) in zip(table, table[1:]):
        if x < x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return table[-1][1]


def ground_effect_fraction(height: float, scale: float) -> float:
    """Extra thrust / thrust at ``height`` m over the floor (0 above the table's last height)."""
    if scale == 0.0 or height >= GROUND_EFFECT_TABLE[-1][0]:
        return 0.0
    return scale * interpolate(GROUND_EFFECT_TABLE, height)


def rotor_speed_ratio(f1: float, f2: float, f3: float, f4: float, hover_force: float) -> float:
    """Summed rotor speeds / their sum at hover: thrust goes with speed squared, so sqrt of each force."""
    roots = math.sqrt(max(f1, 0.0)) + math.sqrt(max(f2, 0.0)) + math.sqrt(max(f3, 0.0)) + math.sqrt(max(f4, 0.0))
    return roots / (4.0 * math.sqrt(hover_force))


def rotor_and_ground_force(x: Sequence[float], wind: Sequence[float], k_drag: float, k_inflow: float,
                           ground_scale: float) -> tuple[float, float, float]:
    """World force [N] of the air on the rotors of the 17-state ``x`` (p, v, q wxyz, w, motor forces):

    - ``-k_drag`` per m/s of the airspeed (velocity minus ``wind``) in the rotor plane and
      ``-k_inflow`` per m/s along the rotor axis (N s/m; the plant scales them with
      ``rotor_speed_ratio``);
    - the ground effect's extra thrust along the rotor axis at height x[2].

    One function on plain floats: it runs four times per plant step.
    """
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    bx, by, bz = 2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)
    vx, vy, vz = x[3] - wind[0], x[4] - wind[1], x[5] - wind[2]
    along = vx * bx + vy * by + vz * bz
    # Along the axis: the inflow loss against the axial airspeed, plus the ground effect's lift.
    axial = -k_inflow * along
    if x[2] < GROUND_EFFECT_TABLE[-1][0] and ground_scale != 0.0:
        axial += (x[13] + x[14] + x[15] + x[16]) * ground_effect_fraction(x[2], ground_scale)
    kd = k_drag
    return (-kd * (vx - along * bx) + axial * bx, -kd * (vy - along * by) + axial * by,
            -kd * (vz - along * bz) + axial * bz)


def measured_downwash_force_z(lower: Sequence[float], upper: Sequence[float], upper_thrust: float,
                              scale: float, width: float) -> float:
    """Vertical force [N] (<= 0) the wake of the drone at ``upper`` puts on the drone at ``lower``:
    ``DOWNWASH_TABLE`` by gap, times a Gaussian of standard deviation ``width`` in horizontal offset."""
    dz = upper[2] - lower[2]
    if dz <= 0.0 or dz >= DOWNWASH_TABLE[-1][0] or upper_thrust <= 0.0 or scale == 0.0:
        return 0.0
    dx, dy = upper[0] - lower[0], upper[1] - lower[1]
    lateral = math.exp(-(dx * dx + dy * dy) / (2.0 * width * width))
    return -scale * upper_thrust * interpolate(DOWNWASH_TABLE, dz) * lateral


__all__ = [
    "DOWNWASH_TABLE", "GROUND_EFFECT_TABLE", "ground_effect_fraction", "interpolate", "measured_downwash_force_z",
    "rotor_and_ground_force", "rotor_speed_ratio",
]
