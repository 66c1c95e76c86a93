"""The mass fitted to the mocap frames around a detected step: exact on clean data, silent without a step,
and in the fast layer, known within a few frames of the alarm without ringing."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from cfknode.app.config import load_config
from cfknode.flight.adaptation import FastAdaptation, settings_from_controller
from cfknode.flight.step_fit import StepFit, fit_step

G = 9.81
RATE = 400.0
FRAME_TICKS = 4  # 100 Hz mocap under a 400 Hz loop


def test_fit_step_recovers_the_change_of_a_known_law() -> None:
    t = np.arange(-0.1, 0.05, 0.01)
    drive = np.where(t > 0.0, 0.5 * 9.0 * t * t, 0.0)  # a_T = 9 m/s^2 from the onset
    z = 1.0 + 0.2 * t + 0.35 * drive  # theta grew by 0.35 at the onset
    dtheta, sse, se = fit_step(t, z, np.zeros_like(t), drive)
    assert abs(dtheta - 0.35) < 1e-9 and sse < 1e-18
    assert dtheta / se > 10.0  # its standard error counts the mocap noise floor, not the perfect fit
    assert fit_step(t[t <= 0.0], z[t <= 0.0], np.zeros(np.sum(t <= 0.0)), np.zeros(np.sum(t <= 0.0))) is None


def _fly(theta_at: Callable[[float], float], thrust_at: Callable[[float], float], seconds: float, noise: float,
         seed: int) -> StepFit:
    """A vertical point mass under a known thrust history; frames of its height every 4th tick, with noise."""
    rng = np.random.default_rng(seed)
    fit = StepFit(RATE)
    z, v, dt = 1.0, 0.0, 1.0 / RATE
    for i in range(int(seconds * RATE)):
        t = i * dt
        a_t = thrust_at(t)
        fresh = i % FRAME_TICKS == 0
        fit.tick(t, z + (noise * rng.standard_normal() if fresh else 0.0), a_t, -G, 1.0, 0.0, fresh)
        a = theta_at(t) * a_t - G
        z += dt * v + 0.5 * dt * dt * a
        v += dt * a
    return fit


def test_the_fit_tells_a_mass_step_from_none_under_mocap_noise() -> None:
    onset = 1.0

    def thrust(t: float) -> float:  # a controller reacting after the step: the thrust changes under the fit
        return G * (1.0 if t < onset + 0.02 else 0.6 + 0.2 * np.sin(40.0 * t))

    step = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.045, 3e-4, seed=1)  # mass 0.5x
    got = step.estimate(onset, 0.01)
    assert got is not None and got[2]  # significant
    assert abs(got[0] - 2.0) < 0.15  # within 8 % after four frames
    quiet = _fly(lambda t: 1.0, thrust, onset + 0.045, 3e-4, seed=1)
    got = quiet.estimate(onset, 0.01)
    assert got is not None and not got[2] and got[0] == 1.0  # no step the frames can tell: the old mass stands


def layer(**kw: Any) -> FastAdaptation:
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    return FastAdaptation(dataclasses.replace(settings_from_controller(cfg.controller), **kw), RATE)


def hover(lay: FastAdaptation, seconds: float, theta_at: Callable[[float], float], noise: float,
          seed: int) -> dict[str, Any]:
    """The layer holding a vertical point mass at 1 m (a PD on the frames, thrust from the estimated mass);
    the layer sees mocap heights at 100 Hz with ``noise`` m and a velocity differenced from them."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE
    z, v = 1.0, 0.0
    seen_z, seen_v, last_z = 1.0, 0.0, 1.0
    alarms, scales, heights = [], [], []
    for i in range(int(seconds * RATE)):
        t = (i + 1) * dt
        e = lay.estimate
        u = float(np.clip(-25.0 * (seen_z - 1.0) - 10.0 * seen_v - e.offset[2], -8.0, 8.0))
        a = (e.thrust_scale / theta_at(t)) * (u + G) - G  # thrust s m (u + g) on the true mass
        z += dt * v + 0.5 * dt * dt * a
        v += dt * a
        fresh = i % FRAME_TICKS == 0
        if fresh:
            measured = z + noise * rng.standard_normal()
            seen_v = 0.5 * seen_v + 0.5 * (measured - last_z) / (FRAME_TICKS * dt)
            seen_z = last_z = measured
        else:
            seen_z += dt * seen_v
        before = lay.steps
        cmd = np.array([0.0, 0.0, u])
        lay.update(t, np.array([0.0, 0.0, seen_v]), np.array([0.0, 0.0, seen_z, 0.0, 0.0, seen_v]), cmd, cmd,
                   (False, False), fresh)
        if lay.steps > before:
            alarms.append(t)
        scales.append(lay.estimate.thrust_scale)
        heights.append(z)
    return {"alarms": alarms, "scale": np.array(scales), "z": np.array(heights)}


def test_the_layer_knows_the_mass_within_frames_of_a_step_and_does_not_ring() -> None:
    step_t = 3.0
    res = hover(layer(), 4.0, lambda t: 1.0 if t < step_t else 0.5, 3e-4, seed=4)
    assert len(res["alarms"]) == 1 and step_t < res["alarms"][0] < step_t + 0.05
    after = res["scale"][int((res["alarms"][0] + 0.03) * RATE):int((step_t + 0.6) * RATE)]
    assert np.all(np.abs(after - 0.5) < 0.06)  # from 30 ms after the alarm on, within 12 %: no ringing
    assert res["alarms"][0] - step_t < 0.05 and float(np.max(res["z"])) - 1.0 < 0.04


def test_a_false_alarm_on_mocap_noise_leaves_the_mass_alone() -> None:
    for noise in (3e-4, 2e-3):  # Vicon-like and a poor mocap
        res = hover(layer(), 20.0, lambda t: 1.0, noise, seed=1)
        assert len(res["alarms"]) <= 2, noise  # the flown threshold fires now and then on noise ...
        assert float(np.max(np.abs(res["scale"] - 1.0))) < 0.01, noise  # ... and the fit then keeps the mass
        assert float(np.max(np.abs(res["z"] - 1.0))) < 0.005, noise
