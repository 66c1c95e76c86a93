"""The model monitor: a flying model the world changed under is recognised within a tenth of a second."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.learning.monitor import ModelMonitor, MonitorSettings, mean_acceleration_error

RATE = 400.0
_O = load_config().online
SETTINGS = MonitorSettings(_O.monitor_window_s, _O.monitor_every_ticks, _O.monitor_margin, _O.monitor_floor)  # defaults


class Constant:
    """A residual model r(v, u) = r."""

    def __init__(self, r: np.ndarray) -> None:
        self.r = np.asarray(r, dtype=float)

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.r, (x.shape[0], 3))


def flown(residual: np.ndarray, n: int = 41, noise: float = 0.0, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Ticks of v' = u + residual under a wandering command (velocity estimates with noise)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    u = np.stack([np.sin(7 * t), 0.5 * np.cos(5 * t), 2.0 + np.sin(3 * t)], axis=1)
    v = np.zeros((n, 3))
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + residual) / RATE
    return t, v + rng.normal(scale=noise, size=v.shape), u


def test_the_mean_acceleration_error_is_the_unexplained_residual() -> None:
    truth = np.array([0.3, -0.2, -2.4])
    t, v, u = flown(truth)
    assert np.allclose(mean_acceleration_error(None, t, v, u), truth, atol=1e-9)
    assert np.allclose(mean_acceleration_error(Constant(truth), t, v, u), 0.0, atol=1e-9)
    assert np.allclose(mean_acceleration_error(Constant(np.zeros(3)), t, v, u), truth, atol=1e-9)


def test_checks_start_when_the_window_is_full_and_come_every_few_ticks() -> None:
    monitor = ModelMonitor(SETTINGS, RATE)
    t, v, u = flown(np.zeros(3), n=80)
    due = [i for i in range(80) if monitor.add(t[i], v[i], u[i])]
    assert due == [40, 50, 60, 70]  # 41 ticks span 0.1 s; then one check per 10 ticks
    monitor.reset()
    assert not any(monitor.add(t[i], v[i], u[i]) for i in range(40))


@pytest.mark.parametrize(("model_r", "drop"), [
    ((0.0, 0.0, -2.4), False),  # right
    ((0.0, 0.0, -1.6), False),  # a third off, still better than nominal
    ((0.0, 0.0, 4.9), True),  # fitted to half the mass, now 1.33x: much worse than nominal
])
def test_a_model_is_dropped_only_when_clearly_worse_than_nominal(model_r, drop) -> None:
    monitor = ModelMonitor(SETTINGS, RATE)
    t, v, u = flown(np.array([0.0, 0.0, -2.4]), noise=0.002)
    for i in range(41):
        due = monitor.add(t[i], v[i], u[i])
    assert due
    verdict = monitor.judge(Constant(np.array(model_r)))
    assert verdict.drop is drop and verdict.ticks == 41
    assert verdict.error_nominal == pytest.approx(2.4, abs=0.1)


def test_estimator_noise_alone_never_drops_a_model() -> None:
    monitor = ModelMonitor(SETTINGS, RATE)
    for seed in range(20):
        t, v, u = flown(np.zeros(3), noise=0.005, seed=seed)  # 5 mm/s: worse than the Kalman filter's
        monitor.reset()
        for i in range(41):
            monitor.add(t[i], v[i], u[i])
        assert not monitor.judge(Constant(np.array([0.2, -0.2, 0.2]))).drop
