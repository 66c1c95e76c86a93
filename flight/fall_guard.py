"""The fall guard: the thrust clamp, at once, while the vehicle falls because the thrust it is sent no longer
lifts it (a mass step past what the controller believes, a motor or battery giving out).

Why the controller needs it without a fast layer: near the thrust limit a late clamp is paid for many times
over. At thrust-to-weight 1.05 and 100 ms of motor lag a step from 0.5x to 1.33x mass sinks the vehicle
0.38 m when the clamp is commanded at the step, 0.90 m when it is commanded 50 ms later and 1.62 m at 100 ms
(``cfknode.app.bench.thrust_sag``). The nominal MPC believes the vehicle config's thrust-to-weight (1.5), so a
fall of a few tenths of a m/s looks easy to stop and it ramps the thrust up over 0.2-0.3 s; a KNODE model
fitted before the step predicts a lighter vehicle still, until the online learner's monitor drops it. Both
reached the ground from 1.5 m. The fast layer (``flight/adaptation/``) sees the step in the accelerometer and
flies the clamp through its thrust cone; this guard is the same reflex for a controller without it.

The signal is the accelerometer: its specific force along the body axis less what the thrust sent should
give the vehicle config's mass. Its usual offset (a payload, a wrong thrust map, a model's share) is followed
slowly, so only a sudden drop counts; the thrust acting is taken as the lower of the sent thrust through the
vehicle's motor lag and through ``SLOWEST_LAG_S`` (a command that rises faster than the motors follow is not
a lost thrust). Two successive samples ``level`` below the offset (or one 1.5 levels below) arm the guard
while the drop lasts. Armed, it engages once the vehicle moves down relative to its reference and could no
longer stop above the reference: its sink rate through ``SLOWEST_LAG_S`` of motor lag and then the
deceleration the clamp leaves at the mass the accelerometer implies (``stopping_distance``). A vehicle well
above its reference (the nominal MPC flies 0.35 m high at 0.5x mass) descends under its own controller, and
at thrust-to-weight 1.05 the small margin makes the guard engage high. Engaged, it holds the clamp, the thrust
leaning at most ``reserve_deg`` for horizontal tracking, until the vertical velocity has been
``RELEASE_SPEED`` above the reference's for ``RELEASE_S``. Without accelerometer samples (``state.imu``
absent or None) it never engages. Pure arithmetic per tick.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cfknode.kernel.vehicle import VehicleConfig

SLOWEST_LAG_S = 0.15  # s: the slowest motor lag the guard allows for (Crazyflie motors: 15-120 ms)
BASELINE_S = 0.5  # s: time constant of the specific force's usual offset
WARMUP_S = 0.5  # s of airborne samples before the guard may engage (the offset is learned first)
SAMPLES_TO_ENGAGE = 2  # successive samples beyond the level: one is a vibration spike ...
SINGLE_SAMPLE = 1.5  # ... unless it is this many levels beyond (10 ms sooner: ~0.1 m less sag at the limit)
# The guard lets go once the vertical velocity has been RELEASE_SPEED above the reference's for RELEASE_S. The
# velocity estimate predicts with the commanded acceleration between frames, so at the clamp it reads 0.1-0.15 m/s
# high (measured at thrust-to-weight 1.05): released at the reference's speed, the vehicle was still sinking.
RELEASE_SPEED = 0.1  # m/s
RELEASE_S = 0.05
MARGIN_S = 0.05  # s: time constant of the accelerometer's thrust-per-mass behind the stopping distance


@dataclass(frozen=True)
class FallGuardSettings:
    level: float  # m/s^2: drop of the specific force below its usual offset that is a lost thrust; 0 = off
    reserve_deg: float  # deg: the thrust may lean this far from vertical while the guard holds the clamp
    rate_hz: float  # controller tick rate


def lag_step(acting: float, sent: float, dt: float, tau: float) -> float:
    """The acting force after ``dt`` of a first-order lag ``tau`` towards ``sent`` (exact for ``sent`` held)."""
    return sent if tau <= 0.0 else sent + (acting - sent) * math.exp(-dt / tau)


def stopping_distance(sink: float, accel: float, margin: float, lag_s: float = SLOWEST_LAG_S) -> float:
    """m a vehicle still drops when the clamp is sent now: sinking at ``sink`` m/s, accelerating at ``accel``
    m/s^2 now (negative: its thrust does not hold it), the clamp leaving ``margin`` m/s^2 beyond the weight once
    the motors' first-order lag ``lag_s`` has passed; unbounded when no margin is left. Exact for the lag:
    v(t) = -sink + margin t - (margin - accel) lag (1 - exp(-t / lag)) is convex, so Newton from the right of
    its root converges monotonically."""
    if margin <= 0.0:
        return math.inf
    gap = max(margin - accel, 0.0)
    if sink <= 0.0 and accel >= 0.0:
        return 0.0
    t = lag_s + (max(sink, 0.0) + gap * lag_s) / margin  # v(t) >= 0 here: right of the root
    for _ in range(12):
        decay = math.exp(-t / lag_s) if lag_s > 0.0 else 0.0
        v = -sink + margin * t - gap * lag_s * (1.0 - decay)
        slope = margin - gap * decay
        if v <= 1e-6 or slope <= 0.0:
            break
        t -= v / slope
    decay = math.exp(-t / lag_s) if lag_s > 0.0 else 0.0
    return max(sink * t - margin * t * t / 2.0 + gap * lag_s * (t - lag_s * (1.0 - decay)), 0.0)


def guard_acceleration(acc: np.ndarray, vehicle: VehicleConfig, reserve_deg: float) -> np.ndarray:
    """The command the guard flies for the MPC's ``acc``: the thrust at the clamp, its horizontal part the MPC's
    (leaning at most ``reserve_deg``) and the rest vertical. At thrust-to-weight 1.05 every 0.1 % of the thrust
    not spent lifting is 2 % of the margin that stops the fall, so the lean is the MPC's, not the reserve's."""
    f_max = vehicle.max_thrust / vehicle.mass
    out = np.array(acc, dtype=float)
    a_xy = math.hypot(out[0], out[1])
    room = f_max * math.sin(math.radians(reserve_deg))
    if a_xy > room:
        out[:2] *= room / a_xy
        a_xy = room
    out[2] = math.sqrt(f_max * f_max - a_xy * a_xy) - vehicle.gravity
    return out


class FallGuard:
    """Per tick: ``engaged(...)`` before the command is shaped, ``sent(thrust_n)`` after it went out."""

    def __init__(self, settings: FallGuardSettings, vehicle: VehicleConfig) -> None:
        self.s = settings
        self.vehicle = vehicle
        self._dt = 1.0 / settings.rate_hz
        self.engagements = 0  # falls the guard caught this flight
        self.ticks = 0  # ticks it flew
        self.reset()

    def reset(self) -> None:
        """Off the air, or a gap in the ticks: the offset is learned again."""
        self._fast = self._slow = 0.0  # N, the thrust sent through the vehicle's lag and through SLOWEST_LAG_S
        self._have_thrust = False
        self._imu_t = -math.inf
        self._baseline = 0.0  # m/s^2, the usual specific force less the sent thrust's
        self._surprise = 0.0  # m/s^2, the newest sample's
        self._learned_s = 0.0
        self._beyond = 0
        self._level_ticks = 0  # ticks in a row the vertical velocity has been RELEASE_SPEED above the reference's
        self._per_newton = 0.0  # 1/kg: specific force per acting newton (the mass the accelerometer implies)
        self._force = 0.0  # m/s^2: the specific force along the body axis now, smoothed like _per_newton
        self.active = False

    def engaged(self, state: Any, ref_vz: float, airborne: bool, above: float = 0.0) -> bool:
        """Whether this tick flies the guard: ``state`` (p, v, q and, when the vehicle logs one, ``imu``), the
        reference's vertical velocity now, whether the vehicle is flying the pattern clear of the ground, and
        its height above the reference now (m)."""
        if not airborne or self.s.level <= 0.0:
            if self.active or self._imu_t > -math.inf:
                self.reset()
            return False
        falling = float(state.v[2]) < ref_vz
        self._level_ticks = self._level_ticks + 1 if float(state.v[2]) >= ref_vz + RELEASE_SPEED else 0
        self._sample(state)
        if self.active and self._level_ticks * self._dt >= RELEASE_S:
            # The thrust now is the new normal: only a further drop engages again. Otherwise a vehicle above its
            # reference (the nominal MPC flies 0.35 m high at 0.5x) was held there by the guard in bursts for
            # 0.8 s after the 1.33x step, until the slow offset caught up.
            self.active = False
            self._baseline, self._beyond = self._surprise, 0
        elif not self.active and falling and self._beyond >= SAMPLES_TO_ENGAGE and \
                stopping_distance(ref_vz - float(state.v[2]), self._force - self.vehicle.gravity,
                                  self.margin()) >= above:
            self.active = True
            self.engagements += 1
        self.ticks += int(self.active)
        return self.active

    def margin(self) -> float:
        """m/s^2 the clamp lifts beyond the weight at the mass the accelerometer implies (0 before a sample)."""
        return self.vehicle.max_thrust * self._per_newton - self.vehicle.gravity

    def sent(self, thrust_n: float) -> None:
        """The collective thrust [N] this tick sent."""
        if not self._have_thrust:
            self._fast = self._slow = thrust_n
            self._have_thrust = True
            return
        self._fast = lag_step(self._fast, thrust_n, self._dt, self.vehicle.motor_time_constant)
        self._slow = lag_step(self._slow, thrust_n, self._dt, SLOWEST_LAG_S)

    def _sample(self, state: Any) -> None:
        """Fold in the accelerometer's newest sample, once."""
        imu = getattr(state, "imu", None)
        if imu is None or imu.t <= self._imu_t or not self._have_thrust:
            return
        dt = 0.0 if self._imu_t == -math.inf else min(imu.t - self._imu_t, BASELINE_S)
        self._imu_t = imu.t
        acting = min(self._fast, self._slow)
        surprise = float(imu.specific_force[2]) - acting / self.vehicle.mass
        self._surprise = surprise
        drop = self._baseline - surprise if self._learned_s >= WARMUP_S else 0.0
        self._fold_margin(float(imu.specific_force[2]), dt, fresh=drop > self.s.level and self._beyond == 0)
        if self._learned_s < WARMUP_S:  # a plain mean over the first samples
            self._learned_s += dt
            self._baseline += (surprise - self._baseline) * (dt / self._learned_s if self._learned_s > 0.0 else 1.0)
            return
        if drop > SINGLE_SAMPLE * self.s.level:
            self._beyond = SAMPLES_TO_ENGAGE
        else:
            self._beyond = self._beyond + 1 if drop > self.s.level else 0
        self._baseline += (surprise - self._baseline) * (1.0 - math.exp(-dt / BASELINE_S))

    def _fold_margin(self, specific_force: float, dt: float, fresh: bool) -> None:
        """The specific force per acting newton, over the most thrust that can be acting (while the command climbs
        the mass reads high and the margin low: the guard engages early rather than late). ``fresh``: the first
        sample of a drop, which starts it over (the mass before the drop says nothing of the mass now)."""
        if self._fast <= 0.0 or self._slow <= 0.0:
            return
        per_newton = specific_force / max(self._fast, self._slow)
        keep = math.exp(-dt / MARGIN_S) if self._per_newton > 0.0 and not fresh else 0.0
        self._per_newton = keep * self._per_newton + (1.0 - keep) * per_newton
        self._force = keep * self._force + (1.0 - keep) * specific_force

__all__ = ["BASELINE_S", "FallGuard", "FallGuardSettings", "RELEASE_S", "RELEASE_SPEED", "SLOWEST_LAG_S", "guard_acceleration",
           "lag_step", "stopping_distance"]
