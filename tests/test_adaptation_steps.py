"""The fast layer's vertical step detector: quiet under mocap noise, fast on a mass step; the late oracle."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from cfknode.app.config import load_config
from cfknode.flight.adaptation import FastAdaptation, cusum_step, settings_from_controller
from cfknode.flight.adaptation import OracleAdaptation

G = 9.81
RATE = 400.0
FRAME_TICKS = 4  # 100 Hz mocap under a 400 Hz loop


# These flights give the layer velocities only, no heights, so a step cannot be fitted and the observer tracks
# it at the step bandwidth. That path needs a detector that stays silent on noise: threshold 5. The flown
# threshold is lower because with heights a false alarm is harmless (test_step_fit.py).
NO_HEIGHTS_THRESHOLD = 5.0


def layer(**kw: Any) -> FastAdaptation:
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    kw = {"step_threshold": NO_HEIGHTS_THRESHOLD, **kw}
    return FastAdaptation(dataclasses.replace(settings_from_controller(cfg.controller), **kw), RATE)


def fly(lay: FastAdaptation, seconds: float, theta_at: Any, v_noise: float, seed: int = 0) -> dict[str, Any]:
    """A vertical point mass hovering on the layer's thrust (true mass ``theta_at(t)`` x nominal); the layer sees
    its velocity only at 100 Hz frames, with white noise ``v_noise`` m/s on each frame (a filtered mocap)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE
    v = 0.0
    seen = np.zeros(3)
    alarms, scales = [], []
    for i in range(int(seconds * RATE)):
        t = (i + 1) * dt
        e = lay.estimate
        u = -e.offset  # hover: the MPC cancels the offset
        a = (e.thrust_scale / theta_at(t)) * (u[2] + G) - G  # thrust s m (u + g) on the true mass
        v += dt * a
        fresh = i % FRAME_TICKS == 0
        if fresh:
            seen = np.array([0.0, 0.0, v + v_noise * rng.standard_normal()])
        else:  # between frames the estimator predicts with the commanded acceleration: no news
            seen = seen + dt * u
        before = lay.steps
        lay.update(t, seen, None, u, u, (False, False), fresh)
        if lay.steps > before:
            alarms.append(t)
        scales.append(lay.estimate.thrust_scale)
    return {"alarms": alarms, "scale": np.array(scales), "v": v}


def test_cusum_accumulates_a_bias_and_forgets_noise() -> None:
    g = (0.0, 0.0)
    for z in (0.3, -0.4, 0.2, -0.1):
        g = cusum_step(g, z)
    assert g == (0.0, 0.0)  # below the drift nothing builds up
    for _ in range(4):
        g = cusum_step(g, 2.0)
    assert g[0] == 6.0 and g[1] == 0.0
    assert cusum_step((0.0, 3.0), -1.5) == (0.0, 4.0)


def test_no_alarm_on_noise_at_either_mocap_noise_level() -> None:
    for v_noise in (0.007, 0.05):  # frame velocity noise at about 0.3 mm and 2 mm of mocap noise
        res = fly(layer(), 20.0, lambda t: 1.0, v_noise, seed=1)
        assert res["alarms"] == [], v_noise
        assert abs(float(np.mean(res["scale"][-400:])) - 1.0) < 0.05


def test_a_mass_step_is_seen_within_a_few_frames_and_the_mass_follows_fast() -> None:
    step_t = 5.0
    res = fly(layer(), 6.0, lambda t: 1.0 if t < step_t else 1.33, 0.007, seed=2)
    assert len(res["alarms"]) == 1
    assert step_t < res["alarms"][0] < step_t + 0.08  # within eight frames (the simulated flights: 3-5)
    i = int((step_t + 0.1) * RATE)
    assert abs(res["scale"][i] - 1.33) < 0.1  # 0.1 s after the step the mass is known
    slow = fly(layer(step_threshold=0.0), 6.0, lambda t: 1.0 if t < step_t else 1.33, 0.007, seed=2)
    assert abs(slow["scale"][i] - 1.33) > 0.15  # without the detector, the 2 Hz estimate is still on its way


def test_the_late_oracle_hears_the_true_mass_after_its_delay() -> None:
    cfg = load_config(overrides={"controller.adaptation": "oracle",
                                 "controller.adaptation_settings.oracle_delay_s": 0.02})
    mass = {"m": cfg.vehicle.mass}
    oracle = OracleAdaptation(cfg.controller, cfg.vehicle, lambda: mass["m"])
    scales = []
    for i in range(40):
        t = i / RATE
        if i == 10:
            mass["m"] = 1.33 * cfg.vehicle.mass
        scales.append(oracle.before_solve(t, None, True, "TRACK", None).thrust_scale)
    assert scales[10 + 7] == 1.0 and abs(scales[10 + 8] - 1.33) < 1e-9  # 20 ms = 8 ticks late


def test_the_lag_bank_picks_the_motor_lag_that_explains_the_climb() -> None:
    from cfknode.flight.adaptation import ThrustLagBank

    rng = np.random.default_rng(3)
    mass, dt = 0.03, 1.0 / RATE
    bank = ThrustLagBank((0.015, 0.04, 0.08, 0.15), 0.015, RATE)
    true_lag, acting, v = 0.08, mass * G, 0.0
    for i in range(int(6.0 * RATE)):
        sent = mass * G * (1.0 + 0.2 * np.sign(np.sin(2.0 * np.pi * 1.5 * i * dt)))  # a climbing and sinking square
        bank.sent(sent)
        acting += (1.0 - np.exp(-dt / true_lag)) * (sent - acting)
        v += dt * (acting / mass - G)
        fresh = i % FRAME_TICKS == 0
        bank.observe(v + (0.005 * rng.standard_normal() if fresh else 0.0), 1.0, mass, G, 0.0, fresh)
    assert bank.lag_s == 0.08
    assert bank.switches >= 1


def test_the_accelerometer_tells_the_lag_where_the_frames_cannot() -> None:
    """A quiet hover's thrust jitter: frame-to-frame velocity misses are noise for every lag, but the specific
    force reads the acting thrust itself (0.3 m/s^2 of noise per sample), so the 150 ms motor is found and a
    15 ms one kept."""
    from cfknode.flight.adaptation import ThrustLagBank

    for true_lag in (0.15, 0.015):
        rng = np.random.default_rng(5)
        mass, dt = 0.03, 1.0 / RATE
        bank = ThrustLagBank((0.015, 0.04, 0.08, 0.15), 0.015, RATE)
        acting, v, jitter = mass * G, 0.0, 0.0
        for i in range(int(4.0 * RATE)):
            jitter = 0.9 * jitter + 0.03 * rng.standard_normal()  # a controller answering mocap noise
            sent = mass * G * (1.0 + jitter)
            bank.sent(sent)
            acting += (1.0 - np.exp(-dt / true_lag)) * (sent - acting)
            v += dt * (acting / mass - G)
            fresh = i % FRAME_TICKS == 0
            bank.observe(v + (0.01 * rng.standard_normal() if fresh else 0.0), 1.0, mass, G, 0.0, fresh)
            if i % FRAME_TICKS == 2:
                bank.observe_specific_force(acting / mass + 0.3 * rng.standard_normal(), 1.0, mass)
        assert bank.lag_s == true_lag, true_lag
