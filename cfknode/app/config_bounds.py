"""Physical bounds on every numeric config key, and checks that relate keys to each other.

A value that parses but makes the controller or the safety layer unsafe (a 1 Hz loop, negative
gravity, a zero time constant, a landing voltage above the take-off voltage) is refused when
the configuration loads, with one line naming the key, the bound and the unit.

``BOUNDS`` maps a dotted key to its range, read from the key's declaration (``setting`` on its field
in the layer's settings module; docs/configuration.md lists them). A key whose value is a list
(``vehicle.inertia``) bounds every element; a key through a list of records
(``sim.mass_changes.factor``) bounds that field of every record. ``CROSS_CHECKS`` are small pure
functions of the whole config that return a one-line problem or ``None``. The ranges are for a
Crazyflie 2.x class quadrotor (about 30 g, 1S LiPo) flown indoors on Earth; their reasons are in
docs/history.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from cfknode.app.declarations import declared
from cfknode.app.settings import Config
from cfknode.kernel.errors import ConfigError

INF = math.inf


@dataclass(frozen=True)
class Bound:
    """``low`` .. ``high`` in ``unit``; an open end excludes the end itself."""

    low: float
    high: float
    unit: str = ""
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.high == INF:
            return f"{'above' if self.low_open else 'at least'} {self.low:g}{unit}"
        if self.low == -INF:
            return f"{'below' if self.high_open else 'at most'} {self.high:g}{unit}"
        if not self.low_open and not self.high_open:
            return f"{self.low:g} to {self.high:g}{unit}"
        low = f"above {self.low:g}" if self.low_open else f"at least {self.low:g}"
        high = f"below {self.high:g}" if self.high_open else f"at most {self.high:g}"
        return f"{low} and {high}{unit}"


def _bounds() -> dict[str, Bound]:
    """Each declared key's range (``setting(low=..., high=...)`` on its field), in declaration order."""
    out = {}
    for d in declared():
        if d.bounds is not None:
            low, high, open_low, open_high = d.bounds
            out[d.key] = Bound(low, high, d.unit, open_low, open_high)
    return out


BOUNDS: dict[str, Bound] = _bounds()


def leaves(cfg: Any, dotted: str) -> Iterator[tuple[str, Any]]:
    """(label, value) for every number a bounds key addresses: list elements and record fields."""
    found: list[tuple[str, Any]] = [("", cfg)]
    parts = dotted.split(".")
    for n, part in enumerate(parts):
        nxt: list[tuple[str, Any]] = []
        for label, obj in found:
            value = getattr(obj, part)
            label = f"{label}.{part}" if label else part
            if isinstance(value, tuple) and n < len(parts) - 1:  # a list of records: each one's field
                nxt.extend((f"{label}[{i}]", v) for i, v in enumerate(value))
            else:
                nxt.append((label, value))
        found = nxt
    for label, value in found:
        if isinstance(value, tuple):
            yield from ((f"{label}[{i}]", v) for i, v in enumerate(value))
        else:
            yield label, value


def _fmt(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def out_of_bounds(cfg: Config) -> str | None:
    """The first value outside its bound, as one line, or None."""
    for key, bound in BOUNDS.items():
        for label, value in leaves(cfg, key):
            if value is not None and not bound.contains(value):  # null: the key is not set (``X | None``)
                return f"{label} = {_fmt(value)} is out of range: must be {bound.describe()}"
    return None


# --- checks across keys: each a pure function returning a one-line problem or None -----------


def hover_authority(cfg: Config) -> str | None:
    """The thrust the MPC may plan must lift the vehicle, or it falls however it is commanded."""
    v, f = cfg.vehicle, cfg.controller.max_thrust_fraction
    lift = f * v.thrust_cmd_clamp * 4.0 * v.thrust_max_per_motor / 65535.0
    weight = v.mass * v.gravity
    if lift <= weight:
        return (f"vehicle cannot hover: controller.max_thrust_fraction x thrust at vehicle.thrust_cmd_clamp = "
                f"{lift:.3g} N is not above its weight {weight:.3g} N (vehicle.mass x vehicle.gravity)")
    return None


def battery_order(cfg: Config) -> str | None:
    s = cfg.safety
    if s.battery_land_v >= s.battery_takeoff_min_v:
        return (f"safety.battery_land_v = {s.battery_land_v:g} V must be below "
                f"safety.battery_takeoff_min_v = {s.battery_takeoff_min_v:g} V")
    return None


def radio_rate(cfg: Config) -> str | None:
    """More setpoints than control ticks would resend stale ones."""
    if cfg.radio.tx_rate_hz > cfg.controller.rate_hz:
        return (f"radio.tx_rate_hz = {cfg.radio.tx_rate_hz:g} Hz must be at most "
                f"controller.rate_hz = {cfg.controller.rate_hz:g} Hz")
    return None


def stale_order(cfg: Config) -> str | None:
    """The radio's hold on a stale setpoint must begin before its stop."""
    r = cfg.radio
    hold_s = r.stale_hold_slots / r.tx_rate_hz
    if hold_s >= r.stale_stop_s:
        return (f"radio.stale_stop_s = {r.stale_stop_s:g} s must be longer than radio.stale_hold_slots / "
                f"radio.tx_rate_hz = {hold_s:g} s")
    return None


def mpc_timing(cfg: Config) -> str | None:
    """Nodes no closer than a tick, and a horizon that sees the near future but not beyond reason."""
    c = cfg.controller
    tick = 1.0 / c.rate_hz
    if c.dt < tick:
        return f"controller.dt = {c.dt:g} s must be at least one control tick (1 / controller.rate_hz = {tick:g} s)"
    span = c.horizon * c.dt
    if not 0.1 <= span <= 10.0:
        return f"controller.horizon x controller.dt = {span:g} s is out of range: must be 0.1 to 10 s"
    return None


def solve_deadline(cfg: Config) -> str | None:
    tick = 1.0 / cfg.controller.rate_hz
    if cfg.safety.solve_deadline_s > tick:
        return (f"safety.solve_deadline_s = {cfg.safety.solve_deadline_s:g} s must be at most one control tick "
                f"(1 / controller.rate_hz = {tick:g} s)")
    return None


def tilt_order(cfg: Config) -> str | None:
    """A commanded tilt the tumble detector calls a tumble would stop the motors mid-manoeuvre."""
    if cfg.controller.max_tilt_deg >= cfg.safety.max_tilt_deg:
        return (f"controller.max_tilt_deg = {cfg.controller.max_tilt_deg:g} deg must be below "
                f"safety.max_tilt_deg = {cfg.safety.max_tilt_deg:g} deg (the tumble limit)")
    if cfg.safety.fence_brake_tilt_deg >= cfg.safety.max_tilt_deg:
        return (f"safety.fence_brake_tilt_deg = {cfg.safety.fence_brake_tilt_deg:g} deg must be below "
                f"safety.max_tilt_deg = {cfg.safety.max_tilt_deg:g} deg (the tumble limit)")
    return None


def fence_order(cfg: Config) -> str | None:
    s = cfg.safety
    for axis, lo, hi in zip("xyz", s.fence_min, s.fence_max):
        if lo >= hi:
            return f"safety.fence_min {axis} = {lo:g} m must be below safety.fence_max {axis} = {hi:g} m"
    return None


def touchdown_below_flight(cfg: Config) -> str | None:
    """A touchdown height at or above the flight height would cut the motors in the air."""
    if cfg.safety.touchdown_height >= cfg.trajectory.height:
        return (f"safety.touchdown_height = {cfg.safety.touchdown_height:g} m must be below "
                f"trajectory.height = {cfg.trajectory.height:g} m")
    return None


def rollback_order(cfg: Config) -> str | None:
    o = cfg.online
    if o.rollback_fallbacks > o.rollback_ticks:
        return (f"online.rollback_fallbacks = {o.rollback_fallbacks} must be at most "
                f"online.rollback_ticks = {o.rollback_ticks} (they are counted in that window)")
    return None


def fast_force_band(cfg: Config) -> str | None:
    """The fast force's band must be a band, and its upper edge well inside the plant's step rate."""
    (low, high), dt = cfg.sim.aero_terms.fast_band_hz, cfg.sim.dt
    if low >= high:
        return f"sim.aero_terms.fast_band_hz = [{low:g}, {high:g}] Hz must have its low edge below its high edge"
    if high > 0.25 / dt:
        return (f"sim.aero_terms.fast_band_hz high edge {high:g} Hz must be at most a quarter of the plant's "
                f"step rate (0.25 / sim.dt = {0.25 / dt:g} Hz)")
    return None


def one_wake(cfg: Config) -> str | None:
    """The realistic plant brings its own, measured wake: two wake models at once would add up."""
    if cfg.sim.aero == "realistic" and cfg.sim.downwash.enabled:
        return ("sim.downwash.enabled is the ideal plant's wake; with sim.aero = realistic the wake is "
                "sim.aero_terms.downwash (0 turns it off)")
    return None


CROSS_CHECKS: tuple[Callable[[Config], str | None], ...] = (
    hover_authority, battery_order, radio_rate, stale_order, mpc_timing, solve_deadline, tilt_order, fence_order,
    touchdown_below_flight, rollback_order, fast_force_band, one_wake,
)


def check_bounds(cfg: Config, where: str = "") -> None:
    """Raise ``ConfigError`` (one line; ``where`` prefixes it) at the first bound or cross-key problem."""
    problem = out_of_bounds(cfg)
    for check in CROSS_CHECKS:
        if problem is not None:
            break
        problem = check(cfg)
    if problem is not None:
        raise ConfigError(f"{where}{problem}")
