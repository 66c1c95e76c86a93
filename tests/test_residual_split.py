"""The residual split (cfknode/app/logs/residual_split.py) finds the delay and the velocity slope it was given."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.app.logs.residual_split import split, velocity_slope


def _circle(delay: float, drag: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A vehicle on a circle whose acceleration is the command ``delay`` s late, less ``drag`` times its
    velocity: state at 500 Hz, commands at 400 Hz."""
    w = 3.0
    t_cmd = np.arange(0.0, 6.0, 1.0 / 400.0)
    t_state = np.arange(0.0, 6.0, 1.0 / 500.0)

    def command(t: np.ndarray) -> np.ndarray:
        return np.stack((-np.cos(w * t), -np.sin(w * t), 0.3 * np.sin(0.5 * w * t)), axis=1)

    # v' = u(t - delay) - drag v, integrated finely from rest.
    fine = np.arange(0.0, 6.0, 1e-4)
    u = command(fine - delay)
    v = np.zeros_like(u)
    for i in range(1, fine.size):
        v[i] = v[i - 1] + 1e-4 * (u[i - 1] - drag * v[i - 1])
    v_state = np.stack([np.interp(t_state, fine, v[:, k]) for k in range(3)], axis=1)
    return t_state, v_state, t_cmd, command(t_cmd)


def test_the_delay_that_explains_the_residual_is_the_plants() -> None:
    t_state, v, t_cmd, u = _circle(0.1, 0.0)
    out = split(t_state, v, t_cmd, u, (1.0, 5.5))
    assert out["best_horizontal_delay_s"] == pytest.approx(0.1)
    by_delay = np.array(out["rms_against_delayed_command"])
    best = out["delays_s"].index(0.1)
    # Against the delayed command almost nothing is left; against the command itself a lot is.
    assert by_delay[best, :2].max() < 0.05 * by_delay[0, :2].min()


def test_a_drag_is_a_velocity_slope_with_no_delay() -> None:
    t_state, v, t_cmd, u = _circle(0.0, 0.25)
    out = split(t_state, v, t_cmd, u, (1.0, 5.5))
    assert out["best_horizontal_delay_s"] == 0.0
    assert out["velocity_slope"][:2] == pytest.approx([-0.25, -0.25], abs=0.01)
    assert min(out["velocity_r2"][:2]) > 0.99


def test_velocity_slope_of_a_constant_residual_is_zero_with_no_fit() -> None:
    v = np.linspace(-1.0, 1.0, 50)[:, None] * np.ones((1, 3))
    slopes, r2 = velocity_slope(v, np.full((50, 3), 0.4))
    assert slopes == pytest.approx(np.zeros(3), abs=1e-9)
    assert r2.tolist() == [0.0, 0.0, 0.0]


def test_a_window_without_commands_is_refused() -> None:
    t_state, v, t_cmd, u = _circle(0.0, 0.0)
    with pytest.raises(ValueError, match="no commands"):
        split(t_state, v, t_cmd, u, (10.0, 11.0))
