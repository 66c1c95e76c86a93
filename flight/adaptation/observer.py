"""The fast layer's estimator as pure functions: observer, output filter, and the moves between its estimates.

Each takes arrays and returns new ones (no state). The weights of a learned model's residual beside the
constant offset are fitted in ``composite.py``. The math of the observer step, the output filter and the
thrust transfer is written once, on three floats (``*_floats``): the layer runs those every tick, where numpy's
per-call cost on 3-vectors (~1 us an operation) was most of the work; the array functions wrap them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, TypeVar

import numpy as np

FloatOrArray = TypeVar("FloatOrArray", float, np.ndarray)


def dob_step(z: np.ndarray, v: np.ndarray, a_model: np.ndarray, omega: np.ndarray | float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """First-order disturbance observer: sigma = omega (v - z), z' = a_model + sigma.

    sigma is the low-pass (cut-off omega) of v' - a_model without differentiating v. Returns (z, sigma)."""
    w = np.broadcast_to(np.asarray(omega, dtype=float), (3,)).tolist()
    z_new, sigma = dob_step_floats(z.tolist(), v.tolist(), a_model.tolist(), w, dt)
    return np.array(z_new), np.array(sigma)


Floats3 = tuple[float, float, float]


def dob_step_floats(z: Sequence[float], v: Sequence[float], a_model: Sequence[float], omega: Sequence[float],
                    dt: float) -> tuple[Floats3, Floats3]:
    """``dob_step`` on three floats per argument (``omega`` per axis). Returns (z, sigma)."""
    s0, s1, s2 = (w * (vi - zi) for w, vi, zi in zip(omega, v, z))
    return (z[0] + dt * (a_model[0] + s0), z[1] + dt * (a_model[1] + s1), z[2] + dt * (a_model[2] + s2)), (s0, s1, s2)


@dataclass(frozen=True)
class L1Gains:
    """The L1 law's constants: predictor gain, adaptation gain, and the projection box's half-width."""

    k_pred: float
    gamma: float
    bound: float


def l1_step(
    v_hat: np.ndarray, sigma_hat: np.ndarray, sigma_f: np.ndarray, v: np.ndarray, a_model: np.ndarray,
    gains: L1Gains, omega: np.ndarray | float, dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """L1-style: velocity predictor, gradient adaptive law with projection (a box), low-pass output filter."""
    k_pred, gamma, bound = gains.k_pred, gains.gamma, gains.bound
    err = v_hat - v
    sigma_hat = np.clip(sigma_hat - dt * gamma * err, -bound, bound)
    v_hat = v_hat + dt * (a_model + sigma_hat - k_pred * err)
    sigma_f = sigma_f + np.minimum(1.0, dt * omega) * (sigma_hat - sigma_f)
    return v_hat, sigma_hat, sigma_f


def smooth_step(out: np.ndarray, sigma: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """The published offset: ``sigma`` low-passed at ``omega`` (rad/s per axis; inf passes sigma through).

    The observer's sigma = omega (v - z) carries the velocity estimate's noise at gain omega, unfiltered: in
    quiet flight it is that noise, almost all of it far above the observer's band (docs/history.md).
    Behind this second pole it rolls off as 1/f."""
    w = np.broadcast_to(np.asarray(omega, dtype=float), (3,)).tolist()
    return np.array(smooth_step_floats(out.tolist(), sigma.tolist(), w, dt))


def smooth_step_floats(out: Sequence[float], sigma: Sequence[float], omega: Sequence[float], dt: float) -> Floats3:
    """``smooth_step`` on three floats per argument (``omega`` finite or inf, never NaN)."""
    o0, o1, o2 = ((o + min(1.0, w * dt) * (s - o)) for o, s, w in zip(out, sigma, omega))
    return o0, o1, o2


def shrink(offset: FloatOrArray, band: float) -> FloatOrArray:
    """``offset`` with what is not clearly above ``band`` (m/s^2) taken out, smoothly: d^3 / (d^2 + band^2).

    Below the band the value falls off as d^3 (a quiet flight's few mm/s^2 of residual dynamics and noise do
    not reach the MPC); well above it the value passes with a bias of band^2 / d. A float or an array."""
    if band <= 0.0:
        return offset
    sq = offset * offset
    return offset * sq / (sq + band * band)


def thrust_transfer(sigma_z: float, u_z: float, g: float, scale: float, rate: float, dt: float,
                    bounds: tuple[float, float]) -> float:
    """New thrust scale, moved toward the one that explains the vertical error ``sigma_z`` at command ``u_z``.

    With thrust from s m, the plant gives a_z + g = (s / theta)(u_z + g); sigma_z = 0 at s = theta."""
    lift = u_z + g
    if lift < 0.3 * g:  # too little thrust to tell a mass from an offset
        return scale
    target = scale * lift / max(lift + sigma_z, 0.1 * g)
    step = min(1.0, rate * dt)
    return float(min(max(scale + step * (target - scale), bounds[0]), bounds[1]))


def axis_transfer(sigma_xy: float, u_xy: float, gain: float, rate: float, dt: float,
                  bounds: tuple[float, float], u_min: float = 0.5) -> float:
    """New axis gain from the part of ``sigma_xy`` proportional to the command ``u_xy`` (normalised gradient)."""
    if abs(u_xy) < u_min:  # no excitation: an offset there is wind, not effectiveness
        return gain
    target = gain * (u_xy + sigma_xy) / u_xy
    step = min(1.0, rate * dt)
    return float(min(max(gain + step * (target - gain), bounds[0]), bounds[1]))  # np.clip's number, 8x cheaper


def sigma_after_transfer(sigma: np.ndarray, u: np.ndarray, g: float, s_old: float, s_new: float) -> np.ndarray:
    """sigma once the thrust scale changed, so model + layer predicts the same acceleration.

    A larger s sends more thrust for the same u (the plant does more): sigma grows by (ds / s)(u + g e_z + sigma)."""
    return np.array(sigma_after_transfer_floats(sigma.tolist(), u.tolist(), g, s_old, s_new))


def sigma_after_transfer_floats(sigma: Sequence[float], u: Sequence[float], g: float, s_old: float,
                                s_new: float) -> Floats3:
    """``sigma_after_transfer`` on three floats per vector."""
    k = s_new / s_old - 1.0
    return sigma[0] + k * (u[0] + sigma[0]), sigma[1] + k * (u[1] + sigma[1]), sigma[2] + k * ((u[2] + g) + sigma[2])


def rebase_offset(offset: np.ndarray, old_acc: np.ndarray, new_acc: np.ndarray, bound: float) -> np.ndarray:
    """Offset after a model swap: shifted by the mean of (old - new) model acceleration over recent ticks,
    so the sum model + offset is unchanged on average where the vehicle just flew."""
    if old_acc.shape[0] == 0:
        return offset
    shift = np.mean(old_acc - new_acc, axis=0)
    if not np.all(np.isfinite(shift)):
        return offset
    return np.clip(offset + shift, -bound, bound)


__all__ = ["axis_transfer", "dob_step", "dob_step_floats", "l1_step", "rebase_offset", "shrink",
           "sigma_after_transfer", "sigma_after_transfer_floats", "smooth_step", "smooth_step_floats",
           "thrust_transfer"]
