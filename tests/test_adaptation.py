"""Fast adaptation layer: the estimator's math, its rules (anti-windup, freeze, reset, re-base), the thrust cone
in the MPC and the Mellinger layer, and short lockstep flights through the whole stack."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.adaptation import (
    AdaptationSettings,
    FastAdaptation,
    dob_step,
    rebase_offset,
    settings_from_controller,
)
from cfknode.app.logs.writer import read_log
from cfknode.flight.mellinger import CommandShaping, shape_force
from cfknode.flight.mpc_problem import MpcParameters
from cfknode.flight.mpc import TranslationalMpc, acceleration_bounds, build_qp_problem
from cfknode.kernel.reference import RefSamples
from cfknode.flight.learning.windows import WindowRecorder
from cfknode.app.mission import run_flight

G = 9.81
RATE = 400.0


def settings(**kw: Any) -> AdaptationSettings:
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    return dataclasses.replace(settings_from_controller(cfg.controller), **kw)


def simulate(layer: FastAdaptation, seconds: float, theta: float, d: np.ndarray, u_cmd: np.ndarray,
             fresh: bool = True, saturated: tuple[bool, bool] = (False, False), t0: float = 0.0) -> np.ndarray:
    """A point mass whose true mass is ``theta`` x nominal plus a disturbance ``d``, flown with thrust from the
    layer's mass estimate and the command ``u_cmd`` minus the layer's offset (what the MPC would do)."""
    v = np.zeros(3)
    dt = 1.0 / RATE
    ez = np.array([0.0, 0.0, G])
    for i in range(int(seconds * RATE)):
        e = layer.estimate
        u = u_cmd - e.offset
        a = (e.thrust_scale / theta) * (u + ez) - ez + d  # thrust s m (u + g), true mass theta m
        v = v + dt * a
        layer.update(t0 + (i + 1) * dt, v, None, u, u, saturated, fresh)
    return v


def test_dob_step_estimates_a_constant_disturbance_without_differentiating() -> None:
    z, v, d = np.zeros(3), np.zeros(3), np.array([0.5, -1.0, 2.0])
    omega, dt = 2 * np.pi * 6.0, 1.0 / RATE
    for _ in range(400):
        v = v + dt * d  # model acceleration 0, the plant adds d
        z, sigma = dob_step(z, v, np.zeros(3), omega, dt)
    assert np.allclose(sigma, d, atol=1e-3)


def test_mass_step_moves_into_thrust_scale_and_wind_into_offset() -> None:
    layer = FastAdaptation(settings(), RATE, G)
    d = np.array([0.8, -0.4, 0.0])
    simulate(layer, 3.0, 1.33, d, np.zeros(3))  # 2 Hz offset, 2 /s into the mass: settled in 3 s
    e = layer.estimate
    assert e.thrust_scale == pytest.approx(1.33, rel=0.02)
    assert np.allclose(e.offset[:2], d[:2], atol=0.05)
    assert abs(e.offset[2]) < 0.05


def test_offset_is_held_on_a_saturated_axis_while_the_mass_estimate_learns() -> None:
    layer = FastAdaptation(settings(), RATE, G)
    simulate(layer, 0.5, 1.0, np.zeros(3), np.zeros(3))
    before = layer.estimate.offset.copy()
    simulate(layer, 1.5, 1.4, np.array([0.0, 0.0, 0.0]), np.zeros(3), saturated=(True, True), t0=0.5)
    e = layer.estimate
    assert e.saturated
    assert np.array_equal(e.offset, before)  # nothing integrated into what the MPC sees
    assert e.thrust_scale > 1.2  # the flown thrust still tells the mass


def test_frozen_while_mocap_is_stale_and_reset_on_non_finite_input() -> None:
    layer = FastAdaptation(settings(), RATE, G)
    simulate(layer, 0.5, 1.2, np.zeros(3), np.zeros(3))
    # Between 100 Hz mocap frames a 400 Hz loop has ticks without a fresh pose: only a stale pose freezes.
    simulate(layer, layer.s.stale_pose_s + 0.01, 1.2, np.zeros(3), np.zeros(3), fresh=False, t0=0.5)
    held = layer.estimate
    assert held.frozen
    simulate(layer, 0.5, 0.6, np.array([2.0, 0.0, 0.0]), np.zeros(3), fresh=False, t0=0.56)
    e = layer.estimate
    assert e.frozen
    assert e.thrust_scale == held.thrust_scale and np.array_equal(e.offset, held.offset)
    layer.update(1.1, np.array([np.nan, 0.0, 0.0]), None, np.zeros(3), np.zeros(3))
    assert layer.estimate.thrust_scale == 1.0 and not layer.estimate.offset.any()


def test_a_stalled_host_is_a_blind_spell_not_a_disturbance() -> None:
    """A real-time loop starved for 0.59 s (a loaded machine, every pose fresh again after it): the vehicle
    moved meanwhile. Integrated across the gap, that motion drove the vertical offset to its bound and the
    vehicle fell 0.34 m; now the gap freezes the layer for its tick and the observer starts from the new pose."""
    layer = FastAdaptation(settings(), RATE, G)
    v = simulate(layer, 1.0, 1.0, np.zeros(3), np.zeros(3))
    before = layer.estimate
    dt = 1.0 / RATE
    v = v + np.array([0.0, 0.0, -0.8])  # the vehicle sank during the stall
    layer.update(1.0 + 0.59, v, None, np.zeros(3), np.zeros(3))
    assert layer.estimate.frozen
    for i in range(1, int(0.5 * RATE)):  # then ticks as usual: the vehicle holds its (new) velocity
        layer.update(1.59 + i * dt, v, None, np.zeros(3), np.zeros(3))
    assert np.abs(layer.estimate.offset).max() < 0.05 and abs(layer.estimate.thrust_scale - before.thrust_scale) < 0.01


def test_rebase_keeps_model_plus_layer_continuous_and_the_model_takes_over() -> None:
    """The learner trains on a_meas - u as always; at a swap the layer keeps only what the new model misses."""
    layer = FastAdaptation(settings(), RATE, G)
    wind = np.array([1.0, 0.0, 0.0])
    simulate(layer, 3.0, 1.0, wind, np.zeros(3))  # 0.5 Hz horizontal: settled
    x, u, old, _ = layer.recent()
    assert x.shape[0] == int(round(layer.s.rebase_window_s * RATE))
    total_before = old + layer.estimate.offset
    new = old + np.array([0.7, 0.0, 0.0])  # the new model explains 0.7 of the 1.0 m/s^2
    layer.rebase(new)
    # Continuous up to the significance shrink's bias (band^2 / |offset|: 1.3e-3 at 0.3 m/s^2).
    assert np.allclose(new + layer.estimate.offset, total_before, atol=2e-3)
    assert layer.estimate.offset[0] == pytest.approx(0.3, abs=0.03)
    assert np.array_equal(rebase_offset(np.ones(3), old, np.full_like(old, np.nan), 5.0), np.ones(3))


def test_cone_in_the_mellinger_layer_keeps_vertical_and_shrinks_horizontal() -> None:
    cfg = load_config()
    veh, ctrl = cfg.vehicle, cfg.controller
    f_max = veh.max_thrust / veh.mass
    shaped = shape_force((6.0, 0.0, f_max - G - 0.5), veh, ctrl, CommandShaping())
    fx, fy, fz = shaped.force
    assert np.hypot(np.hypot(fx, fy), fz) == pytest.approx(veh.max_thrust, rel=1e-9)
    assert fz == pytest.approx(veh.mass * (f_max - 0.5))  # vertical kept
    assert shaped.tilt_saturated and not shaped.thrust_saturated
    over = shape_force((3.0, 0.0, f_max), veh, ctrl, CommandShaping(thrust_scale=1.0))
    assert over.thrust_saturated and over.force[0] == 0.0
    assert shape_force((1.0, 2.0, 0.5), veh, ctrl).force == shape_force((1.0, 2.0, 0.5), veh, ctrl, None).force


def _hover_ref(n: int, climb: float = 0.0, lateral: float = 0.0) -> RefSamples:
    p = np.zeros((n + 1, 3))
    p[:, 0] = lateral
    p[:, 2] = 1.0 + climb
    return RefSamples(np.zeros(n + 1), p, np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros(n + 1))


def test_mpc_cone_puts_altitude_first_but_keeps_a_reserve_for_tilt_near_the_clamp() -> None:
    cfg = load_config(overrides={"controller.adaptation": "dob", "controller.codegen": False})
    mpc = TranslationalMpc(cfg.controller, cfg.vehicle)
    n = mpc.horizon
    f = 1.05 * G
    reserve = f * np.sin(np.radians(cfg.controller.cone_reserve_deg))
    # 0.5 m low and 1 m to the side: there is no thrust for both. Thrust-to-weight 1.05 for the estimated mass.
    x0 = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0])
    params = MpcParameters(_hover_ref(n, lateral=1.0), thrust_limit=f)
    plans = [mpc.solve(x0, params) for _ in range(4)]  # warm-started: room from the last plan
    assert all(sol.ok for sol in plans)
    for sol in plans[2:]:  # the first plans start from a cold guess of the vertical
        u = sol.u_pred
        lift, horiz = u[:, 2] + G, np.hypot(u[:, 0], u[:, 1])
        assert u[0, 2] == pytest.approx(np.sqrt(f * f - reserve * reserve) - G, abs=1e-6)  # climbing, the reserve aside
        assert np.all(np.hypot(horiz, lift) <= f + 1e-6)  # inside the cone at every stage
        # The fixed point at the top with no tilt is gone: the reserve (octagon inscribed) is flown.
        assert horiz[0] >= np.cos(np.pi / 8) * reserve - 1e-6
    # Adaptation none: today's problem exactly (no rows, the per-axis box).
    none = load_config(overrides={"controller.adaptation": "none"}).controller
    plain = build_qp_problem(none, cfg.vehicle)
    b = acceleration_bounds(none, cfg.vehicle)
    assert plain.rows is None and np.array_equal(plain.ubw[:3], b.upper) and np.array_equal(plain.lbw[:3], b.lower)


def test_saturated_ticks_never_enter_training_windows() -> None:
    rec = WindowRecorder(t_col=0.05, rate_hz=RATE)
    est = SimpleNamespace(p=np.array([0.0, 0.0, 1.0]), v=np.zeros(3))
    rec.add(SimpleNamespace(t=0.0, est=SimpleNamespace(p=np.zeros(3), v=np.zeros(3)), acc=np.zeros(3), source="mpc",
                            model_version=0, compute_s=0.0))  # ground reference
    windows = []
    for i in range(1, 200):
        tick = SimpleNamespace(t=i / RATE, est=est, acc=np.zeros(3), source="mpc", model_version=0, compute_s=0.0,
                               saturated=(i % 50) < 10)
        w = rec.add(tick)
        if w is not None:
            windows.append(w)
    assert windows
    sat_t = {i / RATE for i in range(1, 200) if (i % 50) < 10}
    assert not any(set(np.round(w.t, 9)) & {round(t, 9) for t in sat_t} for w in windows)


# --- short lockstep flights through the whole stack ----------------------------------------------------------

HOVER = {
    "trajectory.kind": "hover",
    "trajectory.duration": 3.0,
    "trajectory.takeoff_duration": 1.5,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 1.5,
    "dashboard.enabled": False,
    "controller.codegen": False,
}


def _fly(tmp_path: Any, **overrides: Any) -> tuple[Any, list[dict[str, Any]]]:
    cfg = load_config(overrides={**HOVER, "log.dir": str(tmp_path), **overrides})
    res = run_flight(cfg, name_hint="adapt")
    return res, read_log(res.summary.log_path).topic("/adaptation")


def _at(msgs: list[dict[str, Any]], t: float) -> dict[str, Any]:
    return min(msgs, key=lambda m: abs(m["t"] - t))


def test_flight_mass_step_converges(tmp_path: Any) -> None:
    res, msgs = _fly(tmp_path, **{"controller.adaptation": "dob", "sim.mass_changes": [{"t": 2.5, "factor": 1.3}]})
    assert res.outcome.message.startswith("flight complete")
    assert _at(msgs, 4.4)["thrust_scale"] == pytest.approx(1.3, rel=0.04)
    assert res.summary.mse < 2e-3


def test_flight_constant_wind_converges(tmp_path: Any) -> None:
    drag, wind, mass = 0.03, 1.0, 0.029
    res, msgs = _fly(tmp_path, **{"controller.adaptation": "dob", "sim.wind": [wind, 0.0, 0.0],
                                  "sim.drag": [drag, drag, drag]})
    assert res.outcome.message.startswith("flight complete")
    # The default (realistic) plant's rotor drag adds its own push at hover rotor speed, 0.25 m/s^2 per m/s of air;
    # its fast force (0.23 m/s^2 RMS at 1 m/s, 1-10 Hz) leaves about 1 % in the 2 s mean (seeds 0, 1).
    plant = load_config().sim
    push = wind * (drag / mass + (plant.aero_terms.rotor_drag if plant.aero == "realistic" else 0.0))
    hover = np.array([m["offset"] for m in msgs if 3.0 <= m["t"] <= 5.0])  # mean: 6 Hz passes mocap noise
    assert hover[:, 0].mean() == pytest.approx(push, rel=0.1)
    assert np.abs(hover[:, 1:].mean(axis=0)).max() < 0.1
    assert _at(msgs, 4.4)["thrust_scale"] == pytest.approx(1.0, abs=0.03)


def test_flight_at_thrust_to_weight_1_05_after_a_mass_step_stays_up(tmp_path: Any) -> None:
    cfg = load_config()
    factor = cfg.vehicle.max_thrust / (cfg.vehicle.mass * G) / 1.05  # weight that leaves T/W 1.05 at the clamp
    res, msgs = _fly(tmp_path, **{"controller.adaptation": "dob", "sim.mass_changes": [{"t": 2.2, "factor": factor}],
                                  "trajectory.kind": "circle", "trajectory.radius": 0.5, "trajectory.speed": 0.4,
                                  "trajectory.ramp_duration": 0.5, "safety.max_tracking_error": 3.0})
    # Altitude comes first, so the circle is lost sideways (the fence may land it) but the landing is a controlled one.
    assert res.outcome.state.value == "LANDED"
    window = (res.record.t > 2.2) & (res.record.t < 5.0)
    assert res.record.p[window, 2].min() > 0.3  # 1 m reference, 0.5 m/s^2 of climb left: sags, never falls
    assert _at(msgs, 4.5)["thrust_scale"] == pytest.approx(factor, rel=0.05)


def test_a_step_tells_the_layer_a_slow_motor_and_the_mass_it_carries(tmp_path: Any) -> None:
    """A 150 ms motor 10 % weaker than the vehicle config says, which believes 15 ms: while the take-off's frames
    teach the mass they cannot tell the lag; the 0.5x step's fit can (with the flown 15 ms lag alone the
    step went unseen, and the error was 10x)."""
    # Ideal plant: one step's fit reads the lag through the rigid-body model, and the realistic plant's fast force
    # (1-10 Hz, the step response's band) moves it (seed 1 picks 80 ms, the scale 0.1 off for 0.3 s).
    res, msgs = _fly(tmp_path, **{"sim.aero": "ideal", "controller.adaptation": "dob", "sim.motor_time_constant": 0.15,
                                  "sim.thrust_map_scale": 0.9, "sim.mass_changes": [{"t": 2.5, "factor": 0.5}]})
    assert res.outcome.message.startswith("flight complete")
    assert res.summary.extra["adaptation_thrust_lag_s"] == pytest.approx(0.15)
    scale = np.array([m["thrust_scale"] for m in msgs if 2.8 <= m["t"] <= 4.4])
    assert np.all(np.abs(scale - 0.5 / 0.9) < 0.05)
    assert res.summary.mse < 1e-2


def test_adaptation_none_flies_todays_numbers(tmp_path: Any) -> None:
    """With adaptation none the settings are not read: changing them changes nothing, to the last bit."""
    a, msgs = _fly(tmp_path, **{"controller.adaptation": "none"})
    b, _ = _fly(tmp_path, **{"controller.adaptation": "none", "controller.adaptation_settings.bandwidth_hz": 1.0,
                             "controller.adaptation_settings.thrust_rate": 1.0})
    assert not msgs
    assert a.summary.mse == b.summary.mse and np.array_equal(a.record.p, b.record.p)


def test_the_ipopt_reference_flies_the_layer_with_the_box() -> None:
    """The fast layer is on by default; the converged ipopt MPC has no thrust cone and keeps its box."""
    cfg = load_config(overrides={"controller.adaptation": "dob", "controller.solver": "ipopt", "controller.codegen": False})
    mpc = TranslationalMpc(cfg.controller, cfg.vehicle)
    assert not mpc.cone and mpc.backend == "ipopt"
    limited = MpcParameters(_hover_ref(mpc.horizon), thrust_limit=1.05 * G)  # the limit is no-op without the cone
    assert mpc.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), limited).ok
