"""Each network is held to where it saw data: the bounds a round stores, and the queue that keeps to them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cfknode.models.input_bounds import BOUNDS_KEY, FLOOR_U, FLOOR_V, WIDEN, data_bounds, queue_bounds, stored_bounds
from cfknode.models.modelfile import ModelFileError, load_model, save_model
from cfknode.models.residual_np import ResidualQueue
from test_online_gate import linear_residual_model

# A network fitted on a take-off: it learned the climb's thrust loss (r_z = -0.4 v_z) and, where no horizontal
# motion constrained it, a slope in v_x that is not there.
SPURIOUS = np.zeros((3, 3))
SPURIOUS[2, 2], SPURIOUS[2, 0] = -0.4, -0.3


def take_off_inputs(n: int = 400) -> np.ndarray:
    """(v, u) of a climb from rest to 0.5 m/s, hardly any horizontal motion."""
    rng = np.random.default_rng(0)
    z = np.zeros((n, 6))
    z[:, 0:2] = rng.normal(scale=0.01, size=(n, 2))
    z[:, 2] = np.linspace(0.0, 0.5, n)
    z[:, 5] = 0.3 * np.sin(np.linspace(0.0, np.pi, n))
    return z


def bounded(mf, z: np.ndarray):
    return replace(mf, extra={**mf.extra, BOUNDS_KEY: queue_bounds(None, 0, data_bounds(z), len(mf.networks))})


def test_the_bounds_cover_the_data_widened_by_a_quarter_of_its_range_and_at_least_the_floors() -> None:
    z = take_off_inputs()
    lo, hi = (np.array(b) for b in data_bounds(z))
    assert np.all(lo < z.min(axis=0)) and np.all(hi > z.max(axis=0))
    assert hi[2] == pytest.approx(0.5 + WIDEN * 0.5) and lo[2] == pytest.approx(-WIDEN * 0.5)  # v_z: its own range
    assert hi[0] - z[:, 0].max() == pytest.approx(FLOOR_V)  # v_x hardly moved: the floor
    assert hi[3] == pytest.approx(FLOOR_U) and lo[3] == pytest.approx(-FLOOR_U)  # u_x never moved


def test_a_queue_keeps_its_networks_bounds_newest_last_and_drops_the_oldest_with_its_network() -> None:
    a, b, c = ([[-k] * 6, [k] * 6] for k in (1.0, 2.0, 3.0))
    first = queue_bounds(None, 0, (a[0], a[1]), 1)
    assert first == [a]
    two = queue_bounds({BOUNDS_KEY: first}, 1, (b[0], b[1]), 2)
    assert two == [a, b]
    three = queue_bounds({BOUNDS_KEY: two}, 2, (c[0], c[1]), 2)  # a queue of two: the oldest goes
    assert three == [b, c]
    # A base stored without bounds (an older file): its networks stay unbounded, the new one is held.
    mixed = queue_bounds({}, 1, (b[0], b[1]), 2)
    assert mixed == [None, b]
    held = stored_bounds({BOUNDS_KEY: mixed}, 2)
    assert np.all(np.isinf(held[0])) and np.all(held[1, 1] == 2.0)


def test_outside_its_data_a_network_holds_the_edge_value_and_has_no_slope_there() -> None:
    mf = linear_residual_model(SPURIOUS, np.zeros((3, 3)))
    free, held = ResidualQueue.from_model_file(mf), ResidualQueue.from_model_file(bounded(mf, take_off_inputs()))
    # Inside the take-off's data the two are the same model.
    x = np.zeros((4, 6))
    x[:, 3] = [-0.02, 0.0, 0.01, 0.02]
    x[:, 5] = [0.1, 0.2, 0.3, 0.4]
    u = np.zeros((4, 3))
    assert np.allclose(held.evaluate(x, u), free.evaluate(x, u), atol=1e-9)
    # On a circle at 0.4 m/s the unbounded network extrapolates its spurious slope; the bounded one does not.
    x, u = np.zeros((3, 6)), np.zeros((3, 3))
    x[:, 3] = [-0.4, 0.0, 0.4]
    assert np.ptp(free.evaluate(x, u)[:, 2]) == pytest.approx(0.24, rel=1e-3)
    assert np.ptp(held.evaluate(x, u)[:, 2]) < 0.25 * 0.24  # only the slope across the take-off's own +-8 cm/s
    c, jx, ju = held.linearise(x, u)
    assert jx[0, 2, 3] == 0.0 and jx[2, 2, 3] == 0.0  # clamped: no slope along v_x for the MPC
    assert jx[1, 2, 3] == pytest.approx(-0.3, rel=1e-3)  # inside: the network's own slope
    assert jx[0, 2, 5] == pytest.approx(-0.4, rel=1e-3)  # v_z is inside its range on every node
    affine = c + np.einsum("nij,nj->ni", jx, x) + np.einsum("nij,nj->ni", ju, u)
    assert np.allclose(affine, held.evaluate(x, u), atol=1e-12)


def test_bounds_survive_the_model_file_and_bad_ones_are_a_one_line_error(tmp_path) -> None:
    mf = bounded(linear_residual_model(SPURIOUS, np.zeros((3, 3))), take_off_inputs())
    path = save_model(tmp_path / "m.safetensors", mf)
    assert load_model(path).extra[BOUNDS_KEY] == mf.extra[BOUNDS_KEY]
    for bad in ([[[0.0] * 6, [-1.0] * 6]], [None, None], "wide", [[[0.0] * 6]]):
        path = save_model(tmp_path / "bad.safetensors", replace(mf, extra={BOUNDS_KEY: bad}))
        with pytest.raises(ModelFileError, match="input_bounds") as err:
            load_model(path)
        assert "\n" not in str(err.value)


def test_beside_the_layer_a_training_round_stores_the_bounds_of_what_it_trained_on() -> None:
    from cfknode.app.config import load_config
    from cfknode.app.learning import trainer_settings
    from cfknode.models.trainer_process import TrainRequest, Window, _train

    rng = np.random.default_rng(1)
    t = np.arange(200) / 400.0
    u = np.stack([0.2 * np.sin(5 * t), np.zeros_like(t), 0.5 * np.cos(3 * t)], axis=1)
    v = np.cumsum(u + [0.0, 0.0, -0.3], axis=0) / 400.0
    x = np.concatenate((np.cumsum(v, axis=0) / 400.0, v + rng.normal(scale=1e-4, size=v.shape)), axis=1)
    request = TrainRequest(1, 1, Window(1, t, x, u, 0), (), None, 0.0)
    for on in (False, True):
        cfg = load_config(overrides={"online.enabled": True, "online.epochs": 2, "online.layer_input_bounds": on})
        model = _train(request, trainer_settings(cfg)).model
        assert (BOUNDS_KEY in model.extra) is on
    lo, hi = (np.array(b) for b in model.extra[BOUNDS_KEY][0])
    assert lo[2] < v[:, 2].min() and hi[2] > v[:, 2].max() and hi[3] > 0.2 and lo[4] == pytest.approx(-FLOOR_U)
    # Without a layer (the paper's method) a round stores none, whatever the key says.
    cfg = load_config(overrides={"online.enabled": True, "online.epochs": 2, "controller.adaptation": "none"})
    assert BOUNDS_KEY not in _train(request, trainer_settings(cfg)).model.extra
