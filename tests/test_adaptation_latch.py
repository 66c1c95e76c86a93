"""The fast layer never latches: a step is tracked for a bounded time, and later steps are still taken.

While a step is tracked the vertical estimate is pinned to the step's fit, so an error the fit does not
explain (here a 2 Hz vertical vibration the model lacks) kept raising alarms that each extended the
tracking: the layer stayed "tracking a step" for the rest of the flight and held its mass through the
paper's 0.5x and 1.33x steps.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import pytest

import cfknode
from cfknode.app.config import load_config
from cfknode.flight.adaptation import FastAdaptation, settings_from_controller

G = 9.81
RATE = 400.0
FRAME_TICKS = 4  # 100 Hz mocap under the 400 Hz loop
STEPS = ((2.0, 0.5), (4.0, 1.33))  # the paper's mass steps (t s, mass / nominal)


def vibration(t: float) -> float:
    """m/s^2: a vertical 2 Hz oscillation the model does not have (rotor / frame dynamics)."""
    return math.sin(2.0 * math.pi * 2.0 * t)


def mass_at(t: float) -> float:
    factor = 1.0
    for at, f in STEPS:
        factor = f if t >= at else factor
    return factor


def hover_layer(seconds: float, disturbance: Callable[[float], float], seed: int = 0) -> dict[str, Any]:
    """A vertical point mass hovering on the layer's thrust, mass ``mass_at``, plus ``disturbance``; the layer sees
    heights and velocities at 100 Hz frames with 0.3 mm of noise."""
    cfg = load_config()
    lay = FastAdaptation(settings_from_controller(cfg.controller), RATE)
    rng = np.random.default_rng(seed)
    dt, z, v = 1.0 / RATE, 1.0, 0.0
    seen_z = seen_v = 0.0
    rows = []
    for i in range(int(seconds * RATE)):
        t = (i + 1) * dt
        e = lay.estimate
        u = -e.offset
        v += dt * ((e.thrust_scale / mass_at(t)) * (u[2] + G) - G + disturbance(t))
        z += dt * v
        fresh = i % FRAME_TICKS == 0
        if fresh:
            seen_z, seen_v = z + 3e-4 * rng.standard_normal(), v + 6e-3 * rng.standard_normal()
        else:  # between frames the estimator predicts with the commanded acceleration
            seen_v += dt * u[2]
        lay.update(t, np.array([0.0, 0.0, seen_v]), np.array([0.0, 0.0, seen_z, 0.0, 0.0, seen_v]), u, u,
                   (False, False), fresh)
        rows.append((t, lay.tracker.tracked_s(t), lay.estimate.thrust_scale))
    out = np.array(rows)
    return {"layer": lay, "t": out[:, 0], "tracked": out[:, 1], "scale": out[:, 2]}


def scale_after(res: dict[str, Any], t0: float, t1: float) -> float:
    window = (res["t"] >= t0) & (res["t"] < t1)
    return float(np.median(res["scale"][window]))


def test_a_vibration_the_fit_cannot_explain_does_not_hold_the_tracking_for_ever() -> None:
    res = hover_layer(6.0, lambda t: vibration(t) if t > 0.8 else 0.0)
    layer = res["layer"]
    assert res["tracked"].max() <= layer.s.step_max_s  # each step is tracked a bounded time ...
    assert layer.tracker.capped >= 1  # ... though the vibration raised alarm after alarm
    assert np.mean(res["tracked"] > 0.0) < 0.5
    assert scale_after(res, 3.5, 4.0) == pytest.approx(0.5, abs=0.05)  # both steps taken
    assert scale_after(res, 5.5, 6.0) == pytest.approx(1.33, abs=0.08)


def embedded_flight(seconds: float, seed: int = 0) -> dict[str, Any]:
    """The controller embedded in a plant of one's own, as a new user would: 70 ms motors and rotor drag (the
    simulator's ``sim.motor_time_constant`` and ``sim.drag``), the vibration, the paper's mass steps; the
    vehicle starts at rest in the air while the reference already moves at 1.2 m/s. Mocap: 100 Hz frames."""
    cfg = load_config(overrides={"controller.codegen": False, "sim.motor_time_constant": 0.07,
                                 "sim.drag": [0.0135, 0.0135, 0.0]})
    vehicle, dt = cfg.vehicle, 1.0 / cfg.controller.rate_hz
    tau, drag = float(cfg.sim.motor_time_constant), np.asarray(cfg.sim.drag, dtype=float)
    circle = cfknode.Circle(radius=2.0, speed=1.2, height=1.5)
    p, v = circle.sample(np.zeros(1)).p[0].copy(), np.zeros(3)
    q, yaw = np.array([1.0, 0.0, 0.0, 0.0]), 0.0
    seen_p, seen_v = p.copy(), v.copy()
    controller = cfknode.Controller(cfg.controller, vehicle, ground_z=0.0)
    thrust, rng, rows = vehicle.mass * vehicle.gravity, np.random.default_rng(seed), []
    for k in range(int(seconds / dt)):
        t = k * dt
        fresh = k % FRAME_TICKS == 0
        if fresh:
            seen_p, seen_v = p + 3e-4 * rng.standard_normal(3), v + 6e-3 * rng.standard_normal(3)
        command = controller.step(t, cfknode.StateEstimate(t, seen_p, seen_v, q, yaw), circle, pose_fresh=fresh)
        target = cfknode.read_setpoint(command.setpoint, vehicle, yaw, dt)
        q, yaw = np.array(target.quaternion), target.yaw
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                           1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        thrust += (1.0 - math.exp(-dt / tau)) * (target.thrust_n - thrust)
        mass = mass_at(t) * vehicle.mass
        v = v + dt * (thrust / mass * body_z - drag * v / mass - [0.0, 0.0, vehicle.gravity - vibration(t)])
        p = p + dt * v
        rows.append((t, command.layer.stepping, command.layer.thrust_scale))
    out = np.array(rows, dtype=float)
    return {"controller": controller, "t": out[:, 0], "stepping": out[:, 1].astype(bool), "scale": out[:, 2]}


def test_embedded_flight_from_rest_at_1_2_m_s_takes_both_mass_steps() -> None:
    res = embedded_flight(6.0)
    adaptation = res["controller"].adaptation
    state = adaptation.summary()["adaptation_state"]
    # Each step is tracked a bounded time, and the layer is not tracking most of the flight.
    assert state["longest_step_s"] <= adaptation.layer.s.step_max_s
    assert state["stepping_ticks"] == int(res["stepping"].sum()) < 0.5 * res["t"].size
    assert scale_after(res, 3.5, 4.0) == pytest.approx(0.5, abs=0.05)
    assert scale_after(res, 5.5, 6.0) == pytest.approx(1.33, abs=0.08)
