"""The accelerometer's fast path: what no model predicts, measured directly and added to the layer's offset.

The accelerometer reads the specific force f (body frame): R f = a + g e_z, so R f - g e_z is the vehicle's
acceleration in the world, measured at 100 Hz with no differentiation of mocap positions. Less the model's
acceleration for the thrust acting when it was measured (thrust along the measured body axis, plus the model's
residual) it is the residual acceleration d the layer estimates, sample by sample. The frames-only observer
sees d only through differences of noisy positions, so it is filtered at 0.5-1 Hz and misses the fast part.

The fast path is complementary: d low-passed at the cutoff (a second-order Butterworth, as the firmware filters
the accelerometer for INDI) less d through the frames observer's own two poles (observer and output filter).
Added to the observer's offset, the sum follows d up to the cutoff, while below the observer's band the
accelerometer contributes nothing: its bias, a thrust map's or the mass estimate's error, which the mocap
measures better, cancel in the difference.

Pure functions on a frozen state; ``accel_step`` once per new sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The Crazyflie 2.1's BMI088 runs at +-24 g (docs/hardware.md#imu-log). A sample at its range measured the
# clip, not the force; 2 % below it the reading is already suspect (the firmware's 30 Hz filter smears a clip).
ACCEL_RANGE = 0.98 * 24.0 * 9.81  # m/s^2


@dataclass(frozen=True)
class Biquad:
    """A second-order filter's coefficients, y = (b0 + b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2) x."""

    b0: float
    b1: float
    b2: float
    a1: float
    a2: float


def butterworth2(cutoff_hz: float, dt: float) -> Biquad:
    """The second-order Butterworth low-pass at ``cutoff_hz`` for samples ``dt`` apart (bilinear transform with
    the cutoff pre-warped, so the -3 dB point is at the cutoff exactly; DC gain 1)."""
    k = math.tan(math.pi * cutoff_hz * dt)
    q = math.sqrt(2.0)
    norm = 1.0 / (1.0 + q * k + k * k)
    b0 = k * k * norm
    return Biquad(b0, 2.0 * b0, b0, 2.0 * (k * k - 1.0) * norm, (1.0 - q * k + k * k) * norm)


def biquad_rest(c: Biquad, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The transposed direct form's state when ``x`` has been the input forever (output ``x``: DC gain 1)."""
    s2 = (c.b2 - c.a2) * x
    return (c.b1 - c.a1) * x + s2, s2


def biquad_step(c: Biquad, state: tuple[np.ndarray, np.ndarray], x: np.ndarray
                ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """One sample through the filter (transposed direct form II, per axis). Returns (output, new state)."""
    s1, s2 = state
    y = c.b0 * x + s1
    return y, (c.b1 * x - c.a1 * y + s2, c.b2 * x - c.a2 * y)


def pole_step(y: np.ndarray, x: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """A first-order low-pass at ``omega`` rad/s (per axis; inf passes ``x``), exact for ``x`` held over ``dt``."""
    return y + (1.0 - np.exp(-omega * dt)) * (x - y)


def world_residual(q: np.ndarray, f_body: np.ndarray, gravity: float, model_acc: np.ndarray) -> np.ndarray:
    """R(q) f - g e_z - ``model_acc``: the measured acceleration in the world less the model's (m/s^2).
    ``q`` (w, x, y, z) rotates body to world, as the estimate's attitude."""
    w, x, y, z = (float(v) for v in q)
    fx, fy, fz = (float(v) for v in f_body)
    world = np.array([
        (1.0 - 2.0 * (y * y + z * z)) * fx + 2.0 * (x * y - w * z) * fy + 2.0 * (x * z + w * y) * fz,
        2.0 * (x * y + w * z) * fx + (1.0 - 2.0 * (x * x + z * z)) * fy + 2.0 * (y * z - w * x) * fz,
        2.0 * (x * z - w * y) * fx + 2.0 * (y * z + w * x) * fy + (1.0 - 2.0 * (x * x + y * y)) * fz - gravity,
    ])
    return world - model_acc


def saturated(f_body: np.ndarray, limit: float = ACCEL_RANGE) -> bool:
    """Whether a sample is at the sensor's range on any axis (or not a number): it is not the force."""
    return not all(math.isfinite(v) and abs(v) < limit for v in np.asarray(f_body, dtype=float).tolist())


@dataclass(frozen=True)
class AccelTuning:
    """The fast path's constants: the cutoff, the frames observer's poles it complements (rad/s per axis;
    inf: no such pole), the bound on what it adds, and how old the newest sample may be."""

    cutoff_hz: float
    omega_observer: np.ndarray
    omega_output: np.ndarray
    bound: float
    stale_s: float


@dataclass(frozen=True)
class AccelState:
    """The filters after the sample at ``t``; ``part`` is what the fast path adds to the offset (m/s^2)."""

    t: float
    fast: tuple[np.ndarray, np.ndarray]  # the Butterworth's state
    slow: tuple[np.ndarray, np.ndarray]  # the observer's pole, then the output filter's
    part: np.ndarray


def accel_start(t: float, d: np.ndarray, tuning: AccelTuning) -> AccelState:
    """The filters at rest on the residual ``d`` (the first sample, or the first after a gap): part 0."""
    c = butterworth2(tuning.cutoff_hz, 0.01)  # the rest state of DC gain 1 is the same for every dt
    return AccelState(t, biquad_rest(c, d), (d.copy(), d.copy()), np.zeros(3))


def accel_step(state: AccelState | None, t: float, d: np.ndarray, tuning: AccelTuning) -> AccelState | None:
    """The fast path after a new sample at ``t`` with residual ``d``. A first sample, or one after more than
    ``stale_s`` without any, restarts the filters at rest (integrating across a gap would read the motion in it
    as a disturbance); a residual that is not a number leaves the state as it was (frozen)."""
    if not math.isfinite(float(d.sum())):
        return state
    if state is None or t - state.t > tuning.stale_s:
        return accel_start(t, d, tuning)
    dt = t - state.t
    if dt <= 0.0:
        return state
    fast, fast_state = biquad_step(butterworth2(tuning.cutoff_hz, dt), state.fast, d)
    first = pole_step(state.slow[0], d, tuning.omega_observer, dt)
    second = pole_step(state.slow[1], first, tuning.omega_output, dt)
    part = np.clip(fast - second, -tuning.bound, tuning.bound)
    return AccelState(t, fast_state, (first, second), part)


def accel_part(state: AccelState | None, now: float, tuning: AccelTuning) -> np.ndarray | None:
    """What the fast path adds at ``now``: the newest sample's part, held between samples; None once the newest
    sample is older than ``stale_s`` (a stalled log, a saturated sensor): the path is then withdrawn, not held."""
    if state is None or now - state.t > tuning.stale_s:
        return None
    return state.part


__all__ = ["ACCEL_RANGE", "AccelState", "AccelTuning", "Biquad", "accel_part", "accel_start", "accel_step",
           "biquad_rest", "biquad_step", "butterworth2", "pole_step", "saturated", "world_residual"]
