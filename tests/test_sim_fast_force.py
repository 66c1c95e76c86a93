"""The realistic plant's fast unmodelled force: its RMS against airspeed sized to real Crazyflie
flights, its spectrum mostly above 1 Hz and zero-mean, and its determinism by seed."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.fast_force import FastForce, unit_variance_gain

DT = 0.002
DEFAULT = load_config().sim.aero_terms


def _series(airspeed: float, seconds: float, seed: int = 0) -> np.ndarray:
    """(steps, 3) accelerations [m/s^2] of the default fast force at a constant airspeed."""
    force = FastForce(seed, DT, DEFAULT.fast_band_hz, DEFAULT.fast_rms, DEFAULT.fast_rms_per_speed2)
    return np.array([force.step(airspeed) for _ in range(round(seconds / DT))])


def test_the_unit_gain_makes_white_noise_through_the_band_unit_variance():
    # Check the impulse-response gain against the cascade's variance measured on a long run.
    force = FastForce(3, DT, (1.0, 10.0), 1.0, 0.0)
    x = np.array([force.step(0.0) for _ in range(150_000)])[5000:]
    assert np.std(x, axis=0) == pytest.approx([1.0, 1.0, 1.0], rel=0.05)
    assert unit_variance_gain(0.9, 0.99) > unit_variance_gain(0.5, 0.99)  # a narrower band passes less


# Real Crazyflie 2.x flights, residual RMS per axis by speed (docs/hardware.md#simulator).
@pytest.mark.parametrize("airspeed, low, high", [(0.0, 0.1, 0.2), (0.4, 0.1, 0.2), (1.25, 0.22, 0.38),
                                                 (1.75, 0.33, 0.47), (2.5, 0.6, 0.8)])
def test_rms_grows_with_airspeed_as_on_real_flights(airspeed, low, high):
    x = _series(airspeed, 60.0)[2500:]
    rms = np.sqrt(np.mean(x**2, axis=0))
    assert np.all((low <= rms) & (rms <= high)), rms
    assert np.all(np.abs(x.mean(axis=0)) < 0.1 * rms)  # essentially zero-mean


def test_the_force_is_mostly_above_1_hz():
    x = _series(1.0, 200.0)[2500:]
    spectrum = np.abs(np.fft.rfft(x - x.mean(axis=0), axis=0)) ** 2
    freqs = np.fft.rfftfreq(len(x), DT)
    below = spectrum[freqs < 1.0].sum() / spectrum.sum()
    assert below < 0.1
    # ... and limited above: little beyond 3x the band's upper edge.
    assert spectrum[freqs > 30.0].sum() / spectrum.sum() < 0.1


def test_it_is_deterministic_by_seed():
    np.testing.assert_array_equal(_series(1.0, 2.0, seed=7), _series(1.0, 2.0, seed=7))
    assert not np.array_equal(_series(1.0, 2.0, seed=7), _series(1.0, 2.0, seed=8))


def _hover_states(**overrides) -> np.ndarray:
    cfg = load_config(overrides={"sim.aero": "realistic", "sim.initial_position": [0.0, 0.0, 1.0], **overrides})
    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    sim.vehicle.reset(sim.state, [sim.mass * 9.81 / 4.0] * 4)
    hover = round(sim.mass * 9.81 / cfg.vehicle.newton_per_cmd)
    rows = []
    for _ in range(50):
        sim.firmware.on_rpyt(sim.t, 0.0, 0.0, 0.0, hover)
        sim.step_to(sim.t + 0.01)
        rows.append(list(sim.vehicle.state_list()))
    return np.array(rows)


def test_a_realistic_simulator_repeats_its_flight_for_a_seed_and_the_force_moves_it():
    a, b = _hover_states(**{"sim.seed": 4}), _hover_states(**{"sim.seed": 4})
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, _hover_states(**{"sim.seed": 5}))
    quiet = _hover_states(**{"sim.seed": 4, "sim.aero_terms.fast_rms": 0.0, "sim.aero_terms.fast_rms_per_speed2": 0.0})
    assert np.abs(quiet[:, 0:2]).max() < 1e-12  # level hover: nothing else pushes sideways
    assert np.abs(a[:, 0:2]).max() > 1e-5
