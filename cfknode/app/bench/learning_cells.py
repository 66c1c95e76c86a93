"""The cells of ``cfknode bench learning``: manoeuvres on the realistic plant where a learned residual has
something to learn that the fast layer's 0.5-1 Hz offset cannot follow.

- loops: small fast circles, the rotor drag and the speed-dependent fast force turning with the velocity
  once per lap (0.3-1 Hz here), at or above the layer's 0.5 Hz horizontal filters;
- vertical: an up-and-down oscillation, where the inflow term (thrust lost per climb rate) reverses
  every half period;
- surface: a back-and-forth line a few cm over the floor, in ground effect (which the layer does not see:
  it freezes below ``flight.adaptation.loop.GROUND_MARGIN``), the online learner's training floor lowered;
- downwash crossing: two drones, one hovering 0.2-0.5 m over the centre of the other's back-and-forth line,
  so the lower one passes through the wake ten times: the error around each pass, and pass 10 against pass 1
  (a learner should have learned the wake by then; a layer forgets it between passes);
- stacked pair: two drones on one circle, the upper one's wake on the lower one (fleet online learning).

A cell is a set of config overrides; every controller row adds its own (``CONTROLLERS``). What the
Crazyflie cannot fly (``refusal``) is refused with the reason, never flown into the clamp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

# Rows: label -> overrides. The layer rows name no adaptation kind: they fly whatever the configuration
# says (dob by default), so a new layer is benched by re-running, not by editing this table.
CONTROLLERS: dict[str, dict[str, Any]] = {
    "nominal": {"controller.kind": "mpc", "controller.adaptation": "none", "online.enabled": False},
    "layer": {"controller.kind": "mpc", "online.enabled": False},
    "online+layer": {"controller.kind": "mpc", "online.enabled": True},
    "online": {"controller.kind": "mpc", "controller.adaptation": "none", "online.enabled": True},  # the paper's
    # The ceiling: the layer beside the plant's own air terms as the model (sim.air_model), the best any model
    # of the state could learn; in a fleet it takes the drone above's position, as the learner's networks do.
    "air+layer": {"controller.kind": "mpc", "online.enabled": False, "sim.air_model": True,
                  "fleet.neighbour_input": True},
    # The ceiling of a model of the wake alone (fleet.wake_only): the plant's wake, the drone's own air left to
    # the layer. Flown in the fleet cells only (a drone with none above has no wake).
    "wake+layer": {"controller.kind": "mpc", "online.enabled": False, "sim.air_model": True,
                   "sim.air_model_terms": "wake", "fleet.neighbour_input": True},
}
FLEET_ONLY = frozenset({"wake+layer"})
LABELS = {
    "nominal": "nominal MPC",
    "layer": "MPC + layer",
    "online+layer": "KNODE-MPC-Online + layer",
    "online": "KNODE-MPC-Online (paper)",
    "air+layer": "MPC + layer + the plant's air (ceiling)",
    "wake+layer": "MPC + layer + the plant's wake (a wake model's ceiling)",
}
TILT_MARGIN_DEG = 10.0  # the MPC may tilt this much more than the pattern needs: room to correct errors
MAX_PLANNED_TILT_DEG = 50.0  # deg: 10 under the supervisor's tumble limit (safety.max_tilt_deg, 60)
SURFACE_MIN_HEIGHT = 0.02  # m: the surface cells' training floor (online.min_height), under their 4-8 cm
TRAINER_START_S = 900.0  # s: a trainer start under a load of 40 processes on 2 cores took over 120
PASS_HALF_WINDOW_S = 0.3  # s either side of a pass: the window its error is measured over


@dataclass(frozen=True)
class LearnCell:
    """One manoeuvre. ``kind``/``radius``/``speed``/``height`` are the trajectory's; ``fleet`` > 1 flies a
    stacked fleet (``spacing`` m apart) and reports the lowest drone, the one in the wake."""

    name: str
    group: str
    kind: str
    radius: float
    speed: float
    height: float = 1.0
    duration: float = 8.0
    fleet: int = 1
    spacing: float = 0.5
    layout: str = "stack"  # a fleet's: stack (same pattern, higher) or crossing (hovering over a line's centre)
    overrides: tuple[tuple[str, Any], ...] = ()

    @property
    def peak_acceleration(self) -> float:
        """m/s^2 the pattern asks for at full speed: v^2/r on a circle, r w^2 = v^2/r at a line's or an
        oscillation's ends."""
        return self.speed * self.speed / self.radius

    @property
    def frequency_hz(self) -> float:
        """Laps (circle) or periods (line, vertical) per second at full speed."""
        return self.speed / (2.0 * math.pi * self.radius)

    def config(self, controller: str, seed: int, log_dir: str, duration: float | None = None) -> dict[str, Any]:
        """Every override of one flight of this cell with ``controller``'s row."""
        d = self.duration if duration is None else duration
        span = self.radius + 1.5
        top = self.height + (self.radius if self.kind == "vertical" else 0.0) + (self.fleet - 1) * self.spacing
        climb = max(1.0, 2.0 * top)  # s of take-off and landing: the lab circle's 2 s per metre, at least 1 s
        base: dict[str, Any] = {
            "sim.aero": "realistic",
            "trajectory.kind": self.kind,
            "trajectory.radius": self.radius,
            "trajectory.speed": self.speed,
            "trajectory.height": self.height,
            "trajectory.duration": d,
            "trajectory.ramp_duration": min(1.0, 0.25 * d),
            "trajectory.takeoff_duration": climb,
            "trajectory.settle_duration": 0.5,
            "trajectory.land_duration": climb,
            # A bench, not people: a wide fence and tracking limit let every controller show its error.
            "safety.fence_min": [-span, -span, -0.2],
            "safety.fence_max": [span, span, max(3.0, top + 1.0)],
            "safety.max_tracking_error": 3.0,
            # Lockstep waits for its trainer, so a slow start on a loaded machine delays a flight, not its numbers.
            "online.trainer_start_timeout": TRAINER_START_S,
            "sim.seed": seed,
            "log.dir": log_dir,
            "dashboard.enabled": False,
        }
        tilt = required_tilt_deg(self.peak_acceleration if self.kind in ("circle", "line") else 0.0)
        if tilt + TILT_MARGIN_DEG > 30.0:
            base["controller.max_tilt_deg"] = min(MAX_PLANNED_TILT_DEG, math.ceil(tilt + TILT_MARGIN_DEG))
        if self.fleet > 1:
            # The cell is about flying close under another drone: the fleet's keep-apart rule at half the spacing.
            # Each drone's model also sees where the drone above is (docs/fleet.md#neighbour-input).
            base.update({"fleet.size": self.fleet, "fleet.layout": self.layout, "fleet.stack_spacing": self.spacing,
                         "fleet.min_separation": min(0.3, 0.5 * self.spacing), "fleet.neighbour_input": True})
        return {**base, **dict(self.overrides), **CONTROLLERS[controller]}


def required_tilt_deg(horizontal_acceleration: float, gravity: float = 9.81) -> float:
    return math.degrees(math.atan2(horizontal_acceleration, gravity))


def refusal(cell: LearnCell, vehicle: Any, min_thrust_fraction: float, max_thrust_fraction: float) -> str | None:
    """Why the Crazyflie ``vehicle`` cannot fly ``cell`` (None: it can): the pattern's peak acceleration
    against the thrust at the clamp the MPC may plan with, and against the least thrust it keeps."""
    g = vehicle.gravity
    a = cell.peak_acceleration
    top = max_thrust_fraction * vehicle.max_thrust / vehicle.mass  # m/s^2 of specific thrust at the clamp
    if cell.kind in ("circle", "line"):
        need = math.hypot(a, g)
        if need > top:
            return (f"{cell.name}: needs {a:.1f} m/s^2 horizontally, {need:.1f} m/s^2 of thrust; the Crazyflie "
                    f"gives {top:.1f} at its clamp (at most {math.sqrt(max(top * top - g * g, 0.0)):.1f} horizontally)")
        if required_tilt_deg(a, g) > MAX_PLANNED_TILT_DEG - TILT_MARGIN_DEG:
            return (f"{cell.name}: needs {required_tilt_deg(a, g):.0f} deg of tilt; the bench plans up to "
                    f"{MAX_PLANNED_TILT_DEG:g} with {TILT_MARGIN_DEG:g} to spare")
    elif cell.kind == "vertical":
        if a > top - g:
            return f"{cell.name}: needs {a:.1f} m/s^2 up; the Crazyflie gives {top - g:.1f} at its clamp"
        if a > (1.0 - min_thrust_fraction) * g:
            return (f"{cell.name}: needs {a:.1f} m/s^2 down; the MPC keeps {min_thrust_fraction:g} of hover "
                    f"thrust (at most {(1.0 - min_thrust_fraction) * g:.1f} down)")
    return None


def _loops() -> tuple[LearnCell, ...]:
    # r = 0.3 m at 2 m/s needs 13.3 m/s^2, past the Crazyflie's clamp (refused); 1.5 m/s is the fastest
    # small loop it flies with a margin.
    # Names carry no comma: --cells is a comma-separated list.
    return tuple(LearnCell(f"circle r={r:g} v={v:g}", "loops", "circle", r, v)
                 for r, v in ((0.3, 1.0), (0.3, 1.5), (0.3, 2.0), (0.5, 1.0), (0.5, 2.0)))


def _vertical() -> tuple[LearnCell, ...]:
    # Amplitude A at f Hz: peak climb rate 2 pi f A (the inflow term's input), peak acceleration (2 pi f)^2 A.
    out = []
    # The pre-flight check leaves 14.09 m/s^2 of thrust for the reference, 4.3 up: 0.5 m at 0.5 Hz (4.9) and
    # 0.3 m at 1 Hz (11.8) are refused, listed to show where the limit is.
    for amp, hz in ((0.3, 0.5), (0.4, 0.5), (0.25, 0.65), (0.5, 0.5), (0.3, 1.0)):
        out.append(LearnCell(f"vertical A={amp:g} f={hz:g}", "vertical", "vertical", amp, 2.0 * math.pi * hz * amp))
    return tuple(out)


def _surface() -> tuple[LearnCell, ...]:
    # Take-off and landing straight up and down at the line's centre; the training floor under the transit.
    floor = (("online.min_height", SURFACE_MIN_HEIGHT),)
    return tuple(LearnCell(f"surface h={h * 100:g} cm v={v:g}", "surface", "line", 0.6, v, height=h, overrides=floor)
                 for h, v in ((0.06, 0.5), (0.06, 1.0)))


def line_duration(radius: float, speed: float, passes: int, ramp: float = 1.0) -> float:
    """s of a line pattern that crosses its centre ``passes`` times (and ends half a swing later): the phase
    w (duration - ramp) = (passes + 1/2) pi, w = speed / radius."""
    return ramp + (passes + 0.5) * math.pi * radius / speed


CROSSING_PASSES = 10
CROSSING_RADIUS = 0.3  # m: 5 wake widths (sim.aero_terms.downwash_width) either side of the centre


def _crossing() -> tuple[LearnCell, ...]:
    return tuple(LearnCell(f"crossing dz={dz:g} v={v:g}", "crossing", "line", CROSSING_RADIUS, v, height=1.0,
                           duration=line_duration(CROSSING_RADIUS, v, CROSSING_PASSES), fleet=2, spacing=dz,
                           layout="crossing")
                 for dz in (0.2, 0.3, 0.5) for v in (0.5, 1.0, 1.5))


def _stack() -> tuple[LearnCell, ...]:
    return (LearnCell("stacked pair dz=0.5 r=0.5 v=0.4", "stack", "circle", 0.5, 0.4, fleet=2, spacing=0.5),)


CELLS: tuple[LearnCell, ...] = _loops() + _vertical() + _surface() + _crossing() + _stack()
GROUPS = ("loops", "vertical", "surface", "crossing", "stack")
QUICK_CELLS = ("circle r=0.5 v=1",)  # one small cell: the smoke test of the whole path
QUICK_DURATION = 4.0  # s of pattern with --quick


def pass_errors(t: np.ndarray, err2: np.ndarray, pass_times: np.ndarray,
                half: float = PASS_HALF_WINDOW_S) -> np.ndarray:
    """Mean squared error (per sample, ``err2``: squared position error) in the window
    [t_pass - half, t_pass + half] of each pass; NaN for a window without samples."""
    out = np.full(len(pass_times), np.nan)
    for i, tp in enumerate(pass_times):
        lo, hi = np.searchsorted(t, tp - half, side="left"), np.searchsorted(t, tp + half, side="right")
        if hi > lo:
            out[i] = float(np.mean(err2[lo:hi]))
    return out


def ground_threshold(cell: LearnCell) -> float:
    """m: below this during the pattern counts as a fall (half the height of a surface transit)."""
    return min(0.05, 0.5 * cell.height)


__all__ = ["CELLS", "CONTROLLERS", "GROUPS", "LABELS", "LearnCell", "MAX_PLANNED_TILT_DEG", "PASS_HALF_WINDOW_S", "QUICK_CELLS",
           "QUICK_DURATION", "SURFACE_MIN_HEIGHT", "CROSSING_PASSES", "line_duration", "ground_threshold", "pass_errors", "refusal", "required_tilt_deg"]
