"""The fast layer's float math gives the numbers its former numpy expressions gave, to the last bit."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from cfknode.flight.adaptation.layer import finite_sum
from cfknode.flight.adaptation.loop import body_z, body_z_floats, measured_state
from cfknode.flight.adaptation.observer import (
    dob_step, dob_step_floats, sigma_after_transfer, sigma_after_transfer_floats, smooth_step, smooth_step_floats,
)
from cfknode.flight.adaptation.thrust_lag import ThrustLagBank, first_argmin


def vectors(rng: np.random.Generator, n: int, scale: float = 3.0) -> list[np.ndarray]:
    """``n`` 3-vectors whose magnitudes span many decades (the last bits differ there if the order differs)."""
    return [rng.normal(0.0, scale, 3) * 10.0 ** rng.integers(-6, 3, 3) for _ in range(n)]


def same(floats: tuple[float, ...], array: np.ndarray) -> bool:
    return np.array(floats).tobytes() == np.asarray(array, dtype=float).tobytes()


def test_the_observers_float_twins_are_bit_identical() -> None:
    rng = np.random.default_rng(0)
    for _ in range(2000):
        z, v, a, sigma, out, u = vectors(rng, 6)
        omega = np.abs(vectors(rng, 1, 10.0)[0])
        dt = float(rng.uniform(1e-4, 0.05))
        # References: the numpy expressions the layer ran on arrays before the float rewrite.
        s_ref = omega * (v - z)
        z_ref = z + dt * (a + s_ref)
        zf, sf = dob_step_floats(z.tolist(), v.tolist(), a.tolist(), omega.tolist(), dt)
        assert same(zf, z_ref) and same(sf, s_ref)
        z_new, s_new = dob_step(z, v, a, omega, dt)  # the array face gives the same
        assert same(tuple(z_new), z_ref) and same(tuple(s_new), s_ref)
        omega_out = np.array([omega[0], math.inf, omega[2] * 1e3])  # inf passes sigma; a large pole clips at 1
        out_ref = out + np.minimum(1.0, omega_out * dt) * (sigma - out)
        assert same(smooth_step_floats(out.tolist(), sigma.tolist(), omega_out.tolist(), dt), out_ref)
        assert same(tuple(smooth_step(out, sigma, omega_out, dt)), out_ref)
        s_old, s_new_scale = float(rng.uniform(0.4, 2.0)), float(rng.uniform(0.4, 2.0))
        force = u + sigma
        force[2] = (u[2] + 9.81) + sigma[2]
        moved_ref = sigma + (s_new_scale / s_old - 1.0) * force
        assert same(sigma_after_transfer_floats(sigma.tolist(), u.tolist(), 9.81, s_old, s_new_scale), moved_ref)
        assert same(tuple(sigma_after_transfer(sigma.copy(), u, 9.81, s_old, s_new_scale)), moved_ref)


def test_finite_sum_is_the_summed_arrays_finiteness() -> None:
    rng = np.random.default_rng(1)
    for _ in range(2000):
        vs = vectors(rng, 3)
        if rng.random() < 0.3:
            vs[int(rng.integers(3))][int(rng.integers(3))] = rng.choice([math.nan, math.inf, -math.inf])
        assert finite_sum(*vs) == math.isfinite(float(vs[0].sum() + vs[1].sum() + vs[2].sum()))
    assert not finite_sum(np.full(3, 1e308), np.zeros(3), np.zeros(3))  # an overflow is not finite either


def test_the_body_axis_and_the_measured_state_as_floats() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        assert same(body_z_floats(q), body_z(q))
        p, v, frame_p = vectors(rng, 3)
        est = SimpleNamespace(t=float(rng.uniform(0, 10)), p=p, v=v, frame=None)
        assert same(tuple(measured_state(est)), np.concatenate((p, v)))
        est.frame = (est.t - float(rng.uniform(0, 0.02)), frame_p)
        assert same(tuple(measured_state(est)), np.concatenate((frame_p + (est.t - est.frame[0]) * v, v)))


def test_first_argmin_is_numpys_argmin() -> None:
    rng = np.random.default_rng(3)
    for _ in range(500):
        values = rng.normal(size=int(rng.integers(1, 6)))
        values[rng.random(values.size) < 0.15] = math.nan
        values[rng.random(values.size) < 0.2] = values[0]  # ties: the first wins
        assert first_argmin(values.tolist()) == int(np.argmin(values))


def test_the_lag_banks_scaled_thrusts_are_the_arrays() -> None:
    bank = ThrustLagBank((0.015, 0.04, 0.08, 0.15), 0.015, 400.0)
    assert bank.acting_scaled(0.99, 0.033) is None
    for thrust in (0.3, 0.45, 0.2, 0.31):
        bank.sent(thrust)
    acting = bank.acting_all()
    assert acting is not None
    scaled = bank.acting_scaled(0.987654321, 0.0321)
    assert scaled is not None and scaled.tobytes() == (acting * 0.987654321 / 0.0321).tobytes()
