"""The fast layer in quiet flight: the published offset is the observer's estimate behind a second low-pass pole
and a significance shrink, so the velocity estimate's noise and a few mm/s^2 of unmodelled dynamics do not
reach the MPC, while a real disturbance, a thrust-scale transfer and a tracked step pass as before."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.logs.writer import read_log
from cfknode.app.mission import run_flight
from cfknode.flight.adaptation import FastAdaptation, settings_from_controller, shrink, smooth_step

G = 9.81
RATE = 400.0


def ticks(seconds: float) -> int:
    return int(seconds * RATE)


def layer(**kw: Any) -> FastAdaptation:
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    kw = {"step_threshold": 0.0, **kw}  # velocities only, no heights: the step detector is tested in test_step_fit.py
    return FastAdaptation(dataclasses.replace(settings_from_controller(cfg.controller), **kw), RATE, G)


def hover(lay: FastAdaptation, seconds: float, d: np.ndarray, v_noise: float, seed: int = 0,
          t0: float = 0.0, v0: np.ndarray | None = None) -> np.ndarray:
    """A point mass at rest plus the disturbance ``d``, flown on the layer's offset (the MPC cancels it); the
    layer sees the velocity with white noise ``v_noise`` m/s (a velocity estimate's error). Returns the offsets."""
    rng = np.random.default_rng(seed)
    dt, v = 1.0 / RATE, np.zeros(3) if v0 is None else v0
    out = np.zeros((int(seconds * RATE), 3))
    for i in range(out.shape[0]):
        u = -lay.estimate.offset
        v = v + dt * (u + d)
        lay.update(t0 + (i + 1) * dt, v + v_noise * rng.standard_normal(3), None, u, u)
        out[i] = lay.estimate.offset
    return out


def test_smooth_step_passes_through_at_infinity_and_low_passes_otherwise() -> None:
    out, sigma = np.zeros(3), np.array([1.0, -2.0, 0.5])
    assert np.array_equal(smooth_step(out, sigma, np.full(3, np.inf), 0.0025), sigma)
    once = smooth_step(out, sigma, np.full(3, 2 * np.pi), 0.0025)
    assert np.allclose(once, sigma * 2 * np.pi * 0.0025)


def test_shrink_silences_small_offsets_and_passes_large_ones() -> None:
    d = np.array([0.002, -0.3, 1.0])
    s = shrink(d, 0.02)
    assert abs(s[0]) < 0.01 * abs(d[0])  # a quiet flight's few mm/s^2
    assert s[1] == pytest.approx(-0.3, abs=0.002) and s[2] == pytest.approx(1.0, abs=0.001)
    assert np.array_equal(shrink(-d, 0.02), -s)  # odd: no direction is preferred
    assert np.array_equal(shrink(d, 0.0), d)


def test_velocity_noise_no_longer_reaches_the_offset() -> None:
    """With the sigma published raw, the offset is omega times the velocity noise (the observer's direct path)."""
    raw = hover(layer(output_bandwidth_hz=0.0, output_bandwidth_xy_hz=0.0, offset_deadband=0.0), 6.0,
                np.zeros(3), 0.01)[ticks(2):]
    quiet = hover(layer(), 6.0, np.zeros(3), 0.01)[ticks(2):]
    raw_rms, quiet_rms = np.sqrt((raw ** 2).mean(axis=0)), np.sqrt((quiet ** 2).mean(axis=0))
    assert raw_rms[0] == pytest.approx(2 * np.pi * 0.5 * 0.01, rel=0.3)  # omega_xy x 1 cm/s
    assert np.all(quiet_rms < 0.05 * raw_rms)


def test_a_disturbance_still_reaches_the_offset() -> None:
    d = np.array([0.34, -0.17, 0.0])  # the robustness bench's wind through drag on 29 g
    offsets = hover(layer(), 4.0, d, 0.01)
    assert np.allclose(offsets[-ticks(0.5):, :2].mean(axis=0), d[:2], atol=0.01)


def test_a_tracked_step_is_published_without_the_extra_pole() -> None:
    """While a detected step is tracked the vertical offset is the fast estimate itself (no heights: the
    observer tracks it; the detector at the threshold that path is tuned for)."""
    lay = layer(step_threshold=5.0)
    hover(lay, 2.0, np.zeros(3), 0.0)
    offsets = hover(lay, 0.3, np.array([0.0, 0.0, -2.0]), 0.0, t0=2.0)
    assert lay.steps == 1
    assert lay.estimate.stepping
    assert offsets[-1, 2] < -1.5  # most of the step within 0.3 s (a 0.5 Hz pair would give ~0.6)


def test_quiet_hover_flight_offset_is_small(tmp_path: Any) -> None:
    cfg = load_config(overrides={
        "trajectory.kind": "hover", "trajectory.duration": 3.0, "trajectory.takeoff_duration": 1.5,
        "trajectory.settle_duration": 0.5, "trajectory.land_duration": 1.5, "dashboard.enabled": False,
        "controller.codegen": False, "controller.adaptation": "dob", "log.dir": str(tmp_path)})
    res = run_flight(cfg, name_hint="quiet")
    assert res.outcome.message.startswith("flight complete")
    msgs = read_log(res.summary.log_path).topic("/adaptation")
    hovering = np.array([m["offset"] for m in msgs if 3.0 <= m["t"] <= 5.0])
    assert np.sqrt((hovering[:, :2] ** 2).mean()) < 0.005  # raw sigma: ~0.03 m/s^2 of velocity noise


def test_only_the_horizontal_offset_is_shrunk() -> None:
    """A small vertical error stays (the mass transfer keeps it small; a ramp must not lag behind a shrink)."""
    lay = layer(thrust_rate=0.0)
    offsets = hover(lay, 5.0, np.array([0.006, 0.0, 0.006]), 0.0)
    assert abs(offsets[-1, 0]) < 0.001  # well under the 0.02 m/s^2 band: not applied
    assert offsets[-1, 2] == pytest.approx(0.006, abs=5e-4)
