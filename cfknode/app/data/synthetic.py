"""A synthetic flight table with a known state-dependent residual and a known fast noise.

For checking ``cfknode model check`` and training against the truth: the vehicle flies smooth
manoeuvres (sums of sines) commanded as u(t), and flies v' = u + r, where r = climb_gain v_z
(vertical) + a band-limited noise above ``Noise.hz[0]``, which no command contains (as a gust or a
rotor's unsteady flow): the recorded thrust and attitude are those of u.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _bandlimited(rng: np.random.Generator, t: np.ndarray, rms: float, low_hz: float, high_hz: float) -> np.ndarray:
    """A sum of random sines between ``low_hz`` and ``high_hz``, scaled to ``rms`` per axis, (n, 3)."""
    freqs = rng.uniform(low_hz, high_hz, (24, 3))
    phases = rng.uniform(0, 2 * np.pi, (24, 3))
    x = np.sin(2 * np.pi * freqs[None] * t[:, None, None] + phases[None]).sum(axis=1)
    return x * (rms / np.sqrt(np.mean(x**2, axis=0)))


def _fly(t: np.ndarray, u: np.ndarray, noise: np.ndarray, climb_gain: float, substeps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Integrate p' = v, v' = u + noise + climb_gain v_z e3 (u and the noise held per sample), from rest at 1 m."""
    p, v = np.zeros((t.size, 3)), np.zeros((t.size, 3))
    pk, vk = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    h = float(np.median(np.diff(t))) / substeps
    for i in range(t.size):
        p[i], v[i] = pk, vk
        for _ in range(substeps):
            a = u[i] + noise[i]
            a[2] += climb_gain * vk[2]
            pk = pk + h * vk + 0.5 * h * h * a
            vk = vk + h * a
    return p, v


@dataclass(frozen=True)
class Noise:
    """The table's fast noise: ``rms`` m/s^2, band-limited to ``hz`` (low, high)."""

    rms: float = 0.3
    hz: tuple[float, float] = (1.5, 4.0)


def flight_table(seed: int = 0, manoeuvres: int = 4, seconds: float = 30.0, rate_hz: float = 100.0,
                 climb_gain: float = -0.4, noise: Noise = Noise(),
                 mass: float = 0.034, gravity: float = 9.81) -> dict[str, np.ndarray]:
    """Columns of the documented schema (``thrust`` input), manoeuvre by manoeuvre, end to end in time."""
    rng = np.random.default_rng(seed)
    cols: dict[str, list[np.ndarray]] = {}
    t0 = 0.0
    for k in range(manoeuvres):
        t = t0 + np.arange(int(seconds * rate_hz)) / rate_hz
        tau = t - t0
        u = np.zeros((t.size, 3))
        for axis, amp in enumerate((0.8, 0.8, 0.4)):
            for _ in range(3):  # each manoeuvre its own mix of slow sines (0.1-0.6 Hz), as accelerations
                w = 2 * np.pi * rng.uniform(0.1, 0.6)
                c, ph = amp * rng.uniform(0.3, 1.0) / 3, rng.uniform(0, 2 * np.pi)
                u[:, axis] -= c * w * w * np.sin(w * tau + ph)
        fast = _bandlimited(rng, t, noise.rms, *noise.hz)
        p, v = _fly(t, u, fast, climb_gain)
        f = u + np.array([0.0, 0.0, gravity])
        thrust = mass * np.linalg.norm(f, axis=1)
        z = f / np.linalg.norm(f, axis=1, keepdims=True)
        # The attitude with that body z and zero yaw: a rotation about (-z_y, z_x, 0) by acos(z_z).
        half = 0.5 * np.arccos(np.clip(z[:, 2], -1, 1))
        axis_norm = np.maximum(np.hypot(z[:, 0], z[:, 1]), 1e-12)
        q = np.stack((np.cos(half), -z[:, 1] / axis_norm * np.sin(half), z[:, 0] / axis_norm * np.sin(half),
                      np.zeros(t.size)), axis=1)
        parts = {"t": t, "px": p[:, 0], "py": p[:, 1], "pz": p[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
                 "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3], "thrust": thrust,
                 "manoeuvre": np.full(t.size, f"m{k}")}
        for name, col in parts.items():
            cols.setdefault(name, []).append(col)
        t0 = t[-1] + 1.0 / rate_hz
    return {name: np.concatenate(parts) for name, parts in cols.items()}
