"""The paper's simulation protocol (Table 1): plant, actuators, reference, mass events and metric.

Everything here follows what the authors' code does (docs/paper-code.md#plant, #online-loop
and #metric), written afresh:

- plant: the 13-state Crazyflie rigid body at 500 Hz, integrated per 2 ms step by one
  Dormand-Prince 5(4) step (what ``scipy.integrate.solve_ivp(RK45, first_step=dt)`` does
  when its first step is accepted; a rejected step falls back to scipy itself), with the
  flightsim quaternion-normalisation term in q';
- actuators: the "+" mixer, rotor speeds clipped to [0, 2500] rad/s, mapped back to (T, M);
  instantaneous motors;
- reference: a 550-vertex chord polygon of the circle followed at constant speed, z = 0;
- events: the mass steps by -15 g after the plant step at 2 s and +25 g after the one at 5 s
  (effective from the next step; matched on the step index, never by float equality);
- metric: the mean over all samples and the three axes of the squared position error.

States are cfknode's: scalar-first quaternions ``(w, x, y, z)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from cfknode.app.bench.paper.vehicle import PAPER_ROTORS, PAPER_VEHICLE, PaperRotors, plus_mixer
from cfknode.kernel.vehicle import VehicleConfig


@dataclass(frozen=True)
class MassEvent:
    time: float  # s: the mass changes after the plant step that ends here
    delta: float  # kg


@dataclass(frozen=True)
class PaperProtocol:
    """One cell of Table 1 and the simulation settings shared by every controller."""

    radius: float = 2.0  # m
    speed: float = 0.8  # m/s
    duration: float = 8.0  # s
    plant_hz: int = 500
    control_hz: int = 20  # MPC rate; the plant holds the input in between
    events: tuple[MassEvent, ...] = (MassEvent(2.0, -0.015), MassEvent(5.0, 0.025))
    integrator: str = "rk45"  # "rk45" (the paper's solve_ivp) or "rk4" (fixed step, for comparison)
    waypoints: int = 550
    extra_angle: float = 10.0  # rad of polygon past the run's duration: th = linspace(0, duration + 10, 550)
    vehicle: VehicleConfig = PAPER_VEHICLE
    rotors: PaperRotors = PAPER_ROTORS

    def __post_init__(self) -> None:
        if self.plant_hz % self.control_hz:
            raise ValueError(f"plant_hz {self.plant_hz} must be a multiple of control_hz {self.control_hz}")
        if self.integrator not in ("rk45", "rk4"):
            raise ValueError(f"integrator must be 'rk45' or 'rk4', got {self.integrator!r}")

    @property
    def plant_dt(self) -> float:
        return 1.0 / self.plant_hz

    @property
    def steps(self) -> int:
        return int(round(self.duration * self.plant_hz))

    @property
    def hold(self) -> int:
        """Plant steps per control tick (25)."""
        return self.plant_hz // self.control_hz

    def event_steps(self) -> dict[int, float]:
        """Plant step index after which each mass change applies -> delta (kg)."""
        out: dict[int, float] = {}
        for ev in self.events:
            k = int(round(ev.time * self.plant_hz))
            out[k] = out.get(k, 0.0) + ev.delta
        return out

    def initial_state(self) -> np.ndarray:
        """At rest at (r, 0, 0), level."""
        x = np.zeros(13)
        x[0] = self.radius
        x[6] = 1.0
        return x


class ChordCircle:
    """The paper's circle: a polygon of ``waypoints`` vertices at angles linspace(0, T + 10, n),
    counter-clockwise about the origin at z = 0, followed along the chords at constant speed."""

    def __init__(self, protocol: PaperProtocol) -> None:
        th = np.linspace(0.0, protocol.duration + protocol.extra_angle, protocol.waypoints)
        r = protocol.radius
        self.points = np.stack((r * np.cos(th), r * np.sin(th), np.zeros_like(th)), axis=1)
        seg = np.diff(self.points, axis=0)
        length = np.linalg.norm(seg, axis=1)
        self.speed = protocol.speed
        self.velocity = protocol.speed * seg / length[:, None]  # (n-1, 3): constant on each chord
        self.end_times = np.cumsum(length / protocol.speed)  # chord i ends at end_times[i]

    def sample(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity at time(s) t: (..., 3) each.  Past the last vertex: hold it."""
        tt = np.asarray(t, dtype=float)
        i = np.searchsorted(self.end_times, tt, side="left")  # first chord ending at or after t
        beyond = i >= self.end_times.shape[0]
        i = np.minimum(i, self.end_times.shape[0] - 1)
        v = self.velocity[i]
        p = self.points[i + 1] + v * (tt - self.end_times[i])[..., None]
        if np.any(beyond):
            p = np.where(beyond[..., None], self.points[-1], p)
            v = np.where(beyond[..., None], 0.0, v)
        return p, v


# --- actuators -------------------------------------------------------------------------


@dataclass
class Actuators:
    """The "+" mixer with rotor-speed clipping, as the paper's controller applies it.

    ``reproduce_fallback``: the original replaces a negative rotor force by
    ``k_t * (previous force)^2`` (about 1e-10 N) instead of 0; with False it is clipped to 0.
    """

    vehicle: VehicleConfig = PAPER_VEHICLE
    rotors: PaperRotors = PAPER_ROTORS
    reproduce_fallback: bool = True
    _previous: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._mixer = plus_mixer(self.vehicle)
        self._unmix = np.linalg.inv(self._mixer)
        self.reset()

    def reset(self) -> None:
        self._previous = np.full(4, self.rotors.k_t * self.rotors.trim_rotor_speed**2)

    def apply(self, u: np.ndarray) -> np.ndarray:
        """Commanded (T, Mx, My, Mz) -> what four clipped rotors actually produce."""
        k_t = self.rotors.k_t
        forces = self._unmix @ np.asarray(u, dtype=float)
        negative = forces < 0.0
        if self.reproduce_fallback:
            forces[negative] = k_t * self._previous[negative] ** 2
        else:
            forces[negative] = 0.0
        self._previous = forces.copy()
        speeds = np.clip(np.sqrt(forces / k_t), self.rotors.rotor_min, self.rotors.rotor_max)
        return self._mixer @ (k_t * speeds * speeds)


# --- plant ---------------------------------------------------------------------------------


def plant_rhs(x: np.ndarray, u: np.ndarray, mass: float, inertia: tuple[float, float, float], g: float) -> np.ndarray:
    """The paper's plant: rigid body plus flightsim's q' normalisation term -(|q|^2 - 1) 2q.

    Written on Python floats: for one 13-vector that is several times faster than numpy ops.
    """
    _, _, _, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = x.tolist()
    thrust, mx, my, mz = u
    jx, jy, jz = inertia
    s = thrust / mass
    err = 2.0 * (qw * qw + qx * qx + qy * qy + qz * qz - 1.0)
    return np.array(
        (
            vx,
            vy,
            vz,
            s * 2.0 * (qx * qz + qw * qy),
            s * 2.0 * (qy * qz - qw * qx),
            s * (1.0 - 2.0 * (qx * qx + qy * qy)) - g,
            -0.5 * (qx * wx + qy * wy + qz * wz) - err * qw,
            0.5 * (qw * wx + qy * wz - qz * wy) - err * qx,
            0.5 * (qw * wy + qz * wx - qx * wz) - err * qy,
            0.5 * (qw * wz + qx * wy - qy * wx) - err * qz,
            (mx - (jz - jy) * wy * wz) / jx,
            (my - (jx - jz) * wz * wx) / jy,
            (mz - (jy - jx) * wx * wy) / jz,
        )
    )


# Dormand-Prince 5(4) tableau (the one scipy's RK45 uses).
_DP_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0)
_DP_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
)
_DP_B = np.array([35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84])
_DP_E = np.array([-71 / 57600, 0.0, 71 / 16695, -71 / 1920, 17253 / 339200, -22 / 525, 1 / 40])
_RTOL, _ATOL = 1e-3, 1e-6  # solve_ivp's defaults


def _dp45_step(f, x: np.ndarray, h: float) -> tuple[np.ndarray, float]:
    """One Dormand-Prince step and scipy's error norm for it (accepted when < 1)."""
    k = np.empty((7, x.shape[0]))
    k[0] = f(x)
    for s in range(1, 6):
        k[s] = f(x + h * (np.asarray(_DP_A[s]) @ k[:s]))
    x_new = x + h * (_DP_B @ k[:6])
    k[6] = f(x_new)
    scale = _ATOL + np.maximum(np.abs(x), np.abs(x_new)) * _RTOL
    err = (h * (_DP_E @ k)) / scale
    return x_new, float(np.sqrt(np.mean(err * err)))


class PaperPlant:
    """The simulated Crazyflie of the paper's protocol; ``step(u)`` advances one plant step."""

    def __init__(self, protocol: PaperProtocol) -> None:
        self.protocol = protocol
        self.dt = protocol.plant_dt
        self._events = protocol.event_steps()
        self.reset()

    def reset(self) -> None:
        self.state = self.protocol.initial_state()
        self.mass = self.protocol.vehicle.mass
        self.step_index = 0  # number of completed plant steps
        self.fallbacks = 0  # RK45 steps whose first try was rejected (solved by scipy itself)

    @property
    def t(self) -> float:
        return self.step_index * self.dt

    def step(self, u: np.ndarray) -> np.ndarray:
        """Advance one plant step with ``u`` = (T, Mx, My, Mz) held; apply mass events after it."""
        veh = self.protocol.vehicle
        mass, inertia, g = self.mass, veh.inertia, veh.gravity
        uu = tuple(float(a) for a in u)

        def f(x: np.ndarray) -> np.ndarray:
            return plant_rhs(x, uu, mass, inertia, g)

        if self.protocol.integrator == "rk4":
            k1 = f(self.state)
            k2 = f(self.state + 0.5 * self.dt * k1)
            k3 = f(self.state + 0.5 * self.dt * k2)
            k4 = f(self.state + self.dt * k3)
            new = self.state + (self.dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        else:
            new, err = _dp45_step(f, self.state, self.dt)
            if not err < 1.0:
                self.fallbacks += 1
                sol = solve_ivp(lambda _t, x: f(x), (0.0, self.dt), self.state, first_step=self.dt)
                new = sol.y[:, -1]
        self.state = new
        delta = self._events.get(self.step_index)
        if delta is not None:
            self.mass += delta
        self.step_index += 1
        return self.state


# --- metric ---------------------------------------------------------------------------------


def position_mse(positions: np.ndarray, reference: np.ndarray) -> float:
    """Table 1's MSE: mean over all samples and the three axes of the squared position error (m^2)."""
    return float(np.mean(np.square(np.asarray(reference) - np.asarray(positions))))


def per_axis_mse(positions: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.mean(np.square(np.asarray(reference) - np.asarray(positions)), axis=0)


def improvement_percent(baseline: float, ours: float) -> float:
    """The paper's "outperforms by X %": (baseline - ours) / baseline."""
    return 100.0 * (baseline - ours) / baseline if baseline > 0 and math.isfinite(baseline) else math.nan
