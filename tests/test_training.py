"""KNODE training with torchdiffeq on a synthetic double-integrator plant with a model error."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cfknode.app.config import load_config
from cfknode.models import training
from cfknode.models.knode import KnodeQueue, from_torch_queue, residual_numpy, to_torch_queue
from cfknode.models.modelfile import load_model, save_model
from cfknode.models.training import (
    Segment,
    fit_normalisation,
    make_dataset,
    nominal_prediction,
    one_step_rmse,
    train,
    train_new_model,
)

G = 9.81


def plant_segment(
    n: int = 600,
    rate: float = 400.0,
    mass_factor: float = 1.3,
    bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    noise_v: float = 0.003,
    seed: int = 0,
) -> Segment:
    """A double integrator flown by a PD tracker of random sinusoids (numpy "plant").

    The command u is the world acceleration the nominal model assumes; the plant realises
    (u + g e3) / mass_factor - g e3 + bias, i.e. a vehicle mass_factor times heavier than
    nominal, and the recorded velocities carry white noise like finite-differenced mocap.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate
    t = np.arange(n) * dt
    w = 2 * np.pi * rng.uniform(1.0, 2.0, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    amp = rng.uniform(1.0, 2.5, 3) / w**2
    e3 = np.array([0.0, 0.0, 1.0])
    x = np.zeros((n, 6))
    u = np.zeros((n, 3))
    x[0, 0:3], x[0, 3:6] = amp * np.sin(ph), amp * w * np.cos(ph)
    for i in range(n):
        s = w * t[i] + ph
        u[i] = -amp * w * w * np.sin(s) + 25.0 * (amp * np.sin(s) - x[i, 0:3]) + 10.0 * (amp * w * np.cos(s) - x[i, 3:6])
        if i + 1 < n:
            a = (u[i] + G * e3) / mass_factor - G * e3 + np.asarray(bias)
            x[i + 1, 3:6] = x[i, 3:6] + dt * a
            x[i + 1, 0:3] = x[i, 0:3] + dt * x[i, 3:6] + 0.5 * dt * dt * a
    measured = x.copy()
    measured[:, 3:6] += noise_v * rng.standard_normal((n, 3))
    return Segment(t, measured, u, source=f"plant{seed}")


def training_config(**overrides):
    return load_config(overrides={f"training.{k}": v for k, v in overrides.items()}).training


KNODE = load_config(overrides={"knode.hidden": [32, 32]}).knode


@pytest.fixture(scope="module")
def heavy_dataset():
    return make_dataset([plant_segment(seed=s) for s in range(3)], filter_hz=8.0, validation_fraction=0.2)


def test_training_halves_held_out_error_for_a_heavier_vehicle(heavy_dataset) -> None:
    _, result = train_new_model(heavy_dataset, KNODE, training_config(epochs=60))
    assert result.val_rmse_model <= 0.5 * result.val_rmse_nominal, result
    assert result.train_rmse_model <= 0.5 * result.train_rmse_nominal
    assert result.history[-1] < 0.1 * result.history[0]
    assert 0.0 < result.max_abs_residual < KNODE.max_residual


def true_heavy_residual(u: np.ndarray, mass_factor: float = 1.3) -> np.ndarray:
    """What the 1.3x plant adds to v' = u: (u + g e3) / 1.3 - g e3 - u."""
    return -(1.0 - 1.0 / mass_factor) * (u + np.array([0.0, 0.0, G]))


def test_regularised_training_recovers_the_physical_residual(heavy_dataset) -> None:
    # With the loss in (m/s^2)^2, weight decay 1e-2 keeps the net simple enough to generalise
    # from correlated flight inputs to held-out ones (1e-6 fits the training pairs as well but
    # extrapolates worse); about -0.3 g on z at hover, scaling with the command.
    queue, result = train_new_model(heavy_dataset, KNODE, training_config(epochs=100, weight_decay=1e-2))
    assert result.val_rmse_model <= 0.25 * result.val_rmse_nominal, result
    val = heavy_dataset.val
    err = residual_numpy(queue, val.x0, val.u) - true_heavy_residual(val.u)
    assert np.all(np.sqrt(np.mean(err**2, axis=0)) < 0.5), np.sqrt(np.mean(err**2, axis=0))


def test_training_learns_a_constant_bias() -> None:
    bias = (0.6, -0.4, -1.0)
    ds = make_dataset([plant_segment(mass_factor=1.0, bias=bias, seed=s) for s in range(3)], 8.0, 0.2)
    queue, result = train_new_model(ds, KNODE, training_config(epochs=60, weight_decay=1e-2))
    assert result.val_rmse_model <= 0.2 * result.val_rmse_nominal, result
    mean_residual = residual_numpy(queue, ds.val.x0, ds.val.u).mean(axis=0)
    np.testing.assert_allclose(mean_residual, bias, atol=0.1)


def test_the_online_prior_does_not_shrink_a_small_constant_offset() -> None:
    # Online rounds use weight decay 1.0 against slopes a short window cannot identify; a 4 % mass
    # error at hover (-0.4 m/s^2 on z) must still be learned at full size: the output bias is not decayed.
    bias = (0.0, 0.0, -0.4)
    ds = make_dataset([plant_segment(n=200, mass_factor=1.0, bias=bias, seed=4)], 8.0, 0.2)
    queue, _ = train_new_model(ds, KNODE, training_config(epochs=150, lr=0.01, weight_decay=1.0))
    mean_residual = residual_numpy(queue, ds.val.x0, ds.val.u).mean(axis=0)
    np.testing.assert_allclose(mean_residual, bias, atol=0.06)


def test_euler_and_rk4_learn_the_same_residual_on_control_rate_pairs(heavy_dataset) -> None:
    # Online rounds use euler: over 2.5 ms pairs rk4's extra stages change the fit by about 3 %.
    fits = {}
    for method in ("rk4", "euler"):
        queue, _ = train_new_model(heavy_dataset, KNODE, training_config(epochs=60, method=method))
        fits[method] = residual_numpy(queue, heavy_dataset.val.x0, heavy_dataset.val.u)
    assert np.sqrt(np.mean((fits["euler"] - fits["rk4"]) ** 2)) < 0.05 * np.sqrt(np.mean(fits["rk4"] ** 2))


def test_rk4_path_is_one_batched_odeint_call_per_epoch(heavy_dataset, monkeypatch) -> None:
    calls = []
    real = training.odeint

    def counting(func, y0, t, **kwargs):
        calls.append((tuple(y0.shape), tuple(t.shape), kwargs.get("method"), torch.is_grad_enabled()))
        return real(func, y0, t, **kwargs)

    monkeypatch.setattr(training, "odeint", counting)
    queue = KnodeQueue.from_config(KNODE, fit_normalisation(heavy_dataset))
    queue.push()
    train(queue, heavy_dataset, training_config(epochs=4))
    m = len(heavy_dataset.train)
    training_calls = [c for c in calls if c[3]]
    assert training_calls == [((m, 6), (2,), "rk4", True)] * 4
    # After training: one no-grad call each for the training and validation metrics.
    assert [c[0] for c in calls if not c[3]] == [(m, 6), (len(heavy_dataset.val), 6)]


def test_unequal_intervals_share_one_call_and_integrate_exactly() -> None:
    # A fresh (zero) network leaves the exact nominal flow, which rk4 integrates exactly;
    # so the prediction must equal the closed form for every pair's own dt.
    seg = plant_segment(n=200, seed=4)
    jitter = np.random.default_rng(0).uniform(-0.4, 0.4, 200) / 400.0
    t = seg.t + np.concatenate(([0.0], jitter[1:]))
    ds = make_dataset([Segment(t, seg.x, seg.u)], filter_hz=0.0, validation_fraction=0.0)
    assert np.ptp(ds.train.dt) > 1e-3
    queue = KnodeQueue.from_config(KNODE)
    queue.push()
    batch = training._batch(queue, ds.train)
    with torch.no_grad():
        pred = training._integrate(batch, "rk4", False, 1.0, list(queue.trainable_parameters())).numpy()
    np.testing.assert_allclose(pred, nominal_prediction(ds.train), rtol=0.0, atol=1e-12)


@pytest.mark.parametrize(("method", "adjoint"), [("dopri5", False), ("rk4", True), ("dopri5", True), ("euler", False)])
def test_dopri5_and_adjoint_paths_train(heavy_dataset, method: str, adjoint: bool) -> None:
    small = make_dataset([plant_segment(n=120, seed=s) for s in range(2)], 8.0, 0.2)
    _, result = train_new_model(small, KNODE, training_config(epochs=5, method=method, adjoint=adjoint))
    assert result.history[-1] < result.history[0]
    assert math.isfinite(result.val_rmse_model) and result.val_rmse_model < result.val_rmse_nominal


def test_adjoint_gradient_matches_backprop() -> None:
    ds = make_dataset([plant_segment(n=120, seed=9)], 8.0, 0.2)
    queue = KnodeQueue.from_config(KNODE, fit_normalisation(ds), seed=1)
    queue.push()
    with torch.no_grad():
        queue.newest.layers[-1].weight.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(2))
    params = list(queue.trainable_parameters())
    batch = training._batch(queue, ds.train)
    grads = []
    for adjoint in (False, True):
        loss = training._data_loss(training._integrate(batch, "rk4", adjoint, 1.0, params), batch, 0.0)
        grads.append(torch.autograd.grad(loss, params))
    for a, b in zip(*grads):
        np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-4, atol=1e-8 * float(a.abs().max()))


def test_only_the_newest_network_changes(heavy_dataset) -> None:
    queue = KnodeQueue.from_config(KNODE, fit_normalisation(heavy_dataset))
    for _ in range(3):
        queue.push()
        with torch.no_grad():
            queue.newest.layers[-1].weight.fill_(0.01)
    frozen = [{k: v.clone() for k, v in net.state_dict().items()} for net in list(queue.networks)[:2]]
    newest_before = queue.newest.layers[-1].weight.detach().clone()
    train(queue, heavy_dataset, training_config(epochs=3))
    for net, state in zip(list(queue.networks)[:2], frozen):
        for k, v in net.state_dict().items():
            assert torch.equal(v, state[k]), k
    assert not torch.equal(queue.newest.layers[-1].weight, newest_before)


def test_training_is_reproducible_and_reports_progress(heavy_dataset) -> None:
    seen: list[tuple[int, float]] = []
    cfg = training_config(epochs=5, seed=3)
    q1, r1 = train_new_model(heavy_dataset, KNODE, cfg, progress=lambda e, loss: seen.append((e, loss)))
    q2, r2 = train_new_model(heavy_dataset, KNODE, cfg)
    assert r1.history == r2.history
    assert [e for e, _ in seen] == [1, 2, 3, 4, 5] and [loss for _, loss in seen] == list(r1.history)
    x, u = heavy_dataset.val.x0, heavy_dataset.val.u
    np.testing.assert_array_equal(residual_numpy(q1, x, u), residual_numpy(q2, x, u))
    _, r3 = train_new_model(heavy_dataset, KNODE, training_config(epochs=5, seed=4))
    assert r3.history != r1.history


def test_weight_decay_shrinks_the_weights(heavy_dataset) -> None:
    def norm(wd: float) -> float:
        q, _ = train_new_model(heavy_dataset, KNODE, training_config(epochs=30, weight_decay=wd))
        return float(sum((p.detach() ** 2).sum() for p in q.trainable_parameters()))

    assert norm(1.0) < 0.5 * norm(0.0)


def test_warm_start_from_a_model_file(heavy_dataset, tmp_path) -> None:
    queue, result = train_new_model(heavy_dataset, KNODE, training_config(epochs=20))
    path = save_model(tmp_path / "m.safetensors", from_torch_queue(queue, training=result.training_info(heavy_dataset)))
    mf = load_model(path)
    assert mf.training.sources == ("plant0", "plant1", "plant2")
    assert mf.training.val_rmse_model == pytest.approx(result.val_rmse_model)
    assert mf.training.t0 == 0.0 and mf.training.t1 == pytest.approx(599 / 400.0)
    x, u = heavy_dataset.val.x0, heavy_dataset.val.u
    before = residual_numpy(queue, x, u)
    # A warm-started copy joins with weight 1 while its original drops to e^-1 (the paper's weights).
    copied = to_torch_queue(mf)
    copied.push(copy_from_newest=True)
    np.testing.assert_allclose(residual_numpy(copied, x, u), (1.0 + math.exp(-1.0)) * before, rtol=1e-12, atol=1e-12)
    q2, r2 = train_new_model(heavy_dataset, KNODE, training_config(epochs=5), initial=mf, warm_start=True)
    assert len(q2) == 2 and r2.history[-1] < r2.history[0]
    np.testing.assert_array_equal(q2.networks[0].layers[0].weight.detach().numpy(), mf.networks[0].layers[0][0])


def test_make_dataset_drops_gaps_and_splits_each_segment() -> None:
    seg = plant_segment(n=400, seed=1)
    t = seg.t.copy()
    t[200:] += 0.5  # a 0.5 s dropout between samples 199 and 200
    ds = make_dataset([Segment(t, seg.x, seg.u, "a"), plant_segment(n=101, seed=2)], filter_hz=0.0, validation_fraction=0.25)
    assert len(ds.train) + len(ds.val) == 398 + 100
    assert np.all(ds.train.dt < 0.01) and np.all(ds.val.dt < 0.01)
    # Each segment's last quarter is held out: 398 pairs -> 100, 100 pairs -> 25.
    assert len(ds.val) == 125
    assert ds.val.t0[:100].min() > ds.train.t0[:298].max()
    assert ds.sources == ("a", "plant2") and ds.t0 == 0.0 and ds.t1 == pytest.approx(t[-1])


def test_pairs_follow_the_command_convention() -> None:
    seg = plant_segment(n=50, noise_v=0.0, mass_factor=1.0, seed=3)
    ds = make_dataset([seg], filter_hz=0.0, validation_fraction=0.0)
    # u[i] is held from t[i] to t[i+1]: the exact nominal plant makes the nominal prediction exact.
    np.testing.assert_allclose(nominal_prediction(ds.train), ds.train.x1, atol=1e-12)
    np.testing.assert_array_equal(ds.train.u, seg.u[:-1])


def test_velocity_filter_removes_measurement_noise() -> None:
    clean = plant_segment(n=800, noise_v=0.0, seed=5)
    noisy = plant_segment(n=800, noise_v=0.01, seed=5)
    raw = make_dataset([noisy], filter_hz=0.0, validation_fraction=0.0).train
    filtered = make_dataset([noisy], filter_hz=8.0, validation_fraction=0.0).train
    truth = make_dataset([clean], filter_hz=0.0, validation_fraction=0.0).train
    inner = slice(100, -100)
    err_raw = np.sqrt(np.mean((raw.x0[inner, 3:6] - truth.x0[inner, 3:6]) ** 2))
    err_filtered = np.sqrt(np.mean((filtered.x0[inner, 3:6] - truth.x0[inner, 3:6]) ** 2))
    assert err_filtered < 0.3 * err_raw
    # ...and the filter is zero-phase: a clean signal passes almost unchanged.
    passed = make_dataset([clean], filter_hz=8.0, validation_fraction=0.0).train
    assert np.max(np.abs(passed.x0[inner, 3:6] - truth.x0[inner, 3:6])) < 0.02


def test_make_dataset_rejects_bad_input() -> None:
    seg = plant_segment(n=50)
    with pytest.raises(ValueError, match="segment 0"):
        make_dataset([Segment(seg.t, seg.x[:, :5], seg.u)], 8.0)
    bad = seg.x.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        make_dataset([Segment(seg.t, bad, seg.u)], 8.0)
    with pytest.raises(ValueError, match="no usable"):
        make_dataset([Segment(seg.t[:1], seg.x[:1], seg.u[:1])], 8.0)


def test_fit_normalisation_has_floors() -> None:
    hover = Segment(np.arange(200) / 400.0, np.zeros((200, 6)), np.zeros((200, 3)))
    norm = fit_normalisation(make_dataset([hover], 0.0, 0.2))
    np.testing.assert_array_equal(norm.input_scale, [training.VELOCITY_SCALE_FLOOR] * 3 + [training.ACCELERATION_SCALE_FLOOR] * 3)
    np.testing.assert_array_equal(norm.output_scale, training.OUTPUT_SCALE_FLOOR)


def test_training_needs_a_trainable_network(heavy_dataset) -> None:
    with pytest.raises(ValueError, match="push"):
        train(KnodeQueue.from_config(KNODE), heavy_dataset, training_config(epochs=1))


def test_one_step_rmse_compares_models_on_the_same_pairs(heavy_dataset) -> None:
    queue, result = train_new_model(heavy_dataset, KNODE, training_config(epochs=10))
    assert one_step_rmse(queue, heavy_dataset.val) == pytest.approx(result.val_rmse_model, rel=1e-12)
    empty = KnodeQueue.from_config(KNODE)
    assert one_step_rmse(empty, heavy_dataset.val) == pytest.approx(result.val_rmse_nominal, rel=1e-12)
    assert one_step_rmse(queue, heavy_dataset.val, method="dopri5") == pytest.approx(result.val_rmse_model, rel=1e-6)
