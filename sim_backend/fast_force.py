"""The fast unmodelled force of the realistic plant: band-limited noise whose RMS grows with airspeed.

What a real Crazyflie's measured acceleration keeps beyond any model of its state (turbulence,
rotor and frame vibration, blade flapping): essentially zero-mean, mostly faster than 1 Hz, and
larger the faster the vehicle flies (docs/hardware.md#simulator). Per world axis, unit white
noise drawn once per plant step passes two first-order low-passes at the band's upper edge (so
little is left a few times above it), then a first-order high-pass at its lower edge (so it has
no mean and little below it), is scaled to unit variance and multiplied by

    rms(v) = rms_hover + rms_per_speed2 * v^2        (v: airspeed, m/s; rms in m/s^2)

a floor for vibration plus a part that grows with dynamic pressure. Each filter's pole is
exp(-2 pi f dt), its continuous one's over a step. The noise comes from
its own stream of the simulator's seed, so a seed repeats the flight and the mocap, IMU and
scenario streams are untouched.
"""

from __future__ import annotations

import math

import numpy as np

_STREAM_KEY = 0x414552  # "AER": independent of the mocap's and the accelerometer's streams
_BLOCK = 1536  # normals drawn at a time (3 axes x 512 steps): one small draw per second of flight


def band_step(a_low: float, a_high: float, state: tuple[float, float, float],
              noise: float) -> tuple[float, float, float]:
    """One step of the band filter: two low-passes (pole ``a_low``) then a high-pass (pole ``a_high``).
    ``state`` = (first low-pass, second low-pass, high-pass) outputs; returns the new state."""
    first, second, high = state
    b = 1.0 - a_low
    first_new = a_low * first + b * noise
    second_new = a_low * second + b * first_new
    return first_new, second_new, a_high * (high + second_new - second)


def unit_variance_gain(a_low: float, a_high: float) -> float:
    """1 / the stationary standard deviation of ``band_step`` driven by unit white noise, from its
    impulse response."""
    state = band_step(a_low, a_high, (0.0, 0.0, 0.0), 1.0)
    total = state[2] * state[2]
    # The responses decay geometrically: stop once the slowest is below 1e-13 of its start.
    slowest = max(a_low, a_high)
    steps = 2 * int(math.ceil(math.log(1e-13) / math.log(slowest))) + 2 if slowest > 0.0 else 2
    for _ in range(steps):
        state = band_step(a_low, a_high, state, 0.0)
        total += state[2] * state[2]
    return 1.0 / math.sqrt(total)


class FastForce:
    """The fast force's state (three axes of filters); ``step(airspeed)`` once per plant step."""

    def __init__(self, seed: int, dt: float, band_hz: tuple[float, float], rms_hover: float,
                 rms_per_speed2: float) -> None:
        low_hz, high_hz = band_hz
        if not 0.0 < low_hz < high_hz:
            raise ValueError(f"fast force band must be 0 < low < high Hz, got {band_hz}")
        self._a_low = math.exp(-2.0 * math.pi * high_hz * dt)  # the low-passes set the upper edge
        self._a_high = math.exp(-2.0 * math.pi * low_hz * dt)
        self._gain = unit_variance_gain(self._a_low, self._a_high)
        self._rms0 = rms_hover
        self._rms2 = rms_per_speed2
        self._rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_STREAM_KEY,)))
        self._noise: list[float] = []
        self._i = 0
        zero = (0.0, 0.0, 0.0)
        self._state = (zero, zero, zero)  # band_step's state, per axis

    def rms(self, airspeed: float) -> float:
        """Per-axis RMS [m/s^2] at ``airspeed`` m/s."""
        return self._rms0 + self._rms2 * airspeed * airspeed

    def step(self, airspeed: float) -> tuple[float, float, float]:
        """Advance the filters one plant step; the acceleration [m/s^2] to hold over that step."""
        if self._i >= len(self._noise):
            self._noise = self._rng.standard_normal(_BLOCK).tolist()
            self._i = 0
        i = self._i
        self._i = i + 3
        noise, a_low, a_high = self._noise, self._a_low, self._a_high
        sx, sy, sz = self._state
        sx = band_step(a_low, a_high, sx, noise[i])
        sy = band_step(a_low, a_high, sy, noise[i + 1])
        sz = band_step(a_low, a_high, sz, noise[i + 2])
        self._state = (sx, sy, sz)
        scale = self._gain * self.rms(airspeed)
        return scale * sx[2], scale * sy[2], scale * sz[2]


__all__ = ["FastForce", "band_step", "unit_variance_gain"]
