"""Training the newest KNODE network with torchdiffeq (the paper's eq. 1-2, one-step-ahead loss).

Data: segments of (t, x = (p, v), u) at the control rate; u[i] is the command held from
t[i] to t[i+1], so the pair (x[i], u[i]) -> x[i+1] is one sample (the paper's code pairs a
command with the wrong interval once per hold; we do not).  Pairs across a gap (dt more
than ``gap_factor`` times the median) are dropped.  The last ``validation_fraction`` of each
segment's pairs is held out.

Loss: every pair is integrated from x[i] over its own dt_i with the hybrid model
(nominal + residual on v'), all pairs in ONE batched ``odeint`` call: the ODE is written in
normalised time s in [0, 1] and multiplied by each pair's dt_i, so unequal intervals share one
time grid.  The error is measured in acceleration units (velocity error / dt, position error
* 2 / dt^2): the loss then does not depend on the sampling rate, and ``weight_decay`` on
||theta||^2 keeps one meaning at 100 Hz and at 400 Hz.  In these units a weight decay of
about 1e-2 generalised best to held-out synthetic flight data (1e-6 fits the training pairs
as well but extrapolates worse); the paper's 5e-8 on raw 2 ms state errors is of that order.
The output bias (a constant acceleration offset) is not decayed: the prior is against slopes.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
from scipy.signal import butter, filtfilt
from torch import nn
from torchdiffeq import odeint, odeint_adjoint

from cfknode.models.settings import KnodeConfig, TrainingConfig
from cfknode.models.knode import KnodeQueue, TrainingResidual, to_torch_queue
from cfknode.models.input_layouts import NEIGHBOUR_SCALE_FLOOR
from cfknode.models.modelfile import ModelFile, Normalisation, TrainingInfo

# Floors on the fitted input scales: a hover window has velocity spread of mm/s, and
# standardising by that would turn sensor noise into inputs of order one.
VELOCITY_SCALE_FLOOR = 0.25  # m/s
ACCELERATION_SCALE_FLOOR = 0.5  # m/s^2
# The neighbour's relative position has NEIGHBOUR_SCALE_FLOOR: a wake about 6 cm wide must stay resolvable
# (docs/fleet.md#neighbour-input).
OUTPUT_SCALE_FLOOR = 0.5  # m/s^2
FILTER_ORDER = 2  # Butterworth order; filtfilt doubles it


@dataclass(frozen=True)
class Segment:
    """A contiguous recording: t (n,), x (n, 6) = (p, v), u (n, 3) held from t[i] to t[i+1]; or u (n, 6)
    with the neighbour's relative position beside the command (the neighbour input, docs/fleet.md#neighbour-input)."""

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    source: str = ""


@dataclass(frozen=True)
class Pairs:
    """One-step samples: x0 --(u held for dt)--> x1."""

    t0: np.ndarray  # (m,)
    x0: np.ndarray  # (m, 6)
    u: np.ndarray  # (m, 3)
    dt: np.ndarray  # (m,)
    x1: np.ndarray  # (m, 6)

    def __len__(self) -> int:
        return int(self.dt.shape[0])

    @staticmethod
    def concat(parts: Sequence[Pairs]) -> Pairs:
        if not parts:
            return Pairs(np.zeros(0), np.zeros((0, 6)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 6)))
        return Pairs(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t0", "x0", "u", "dt", "x1")))


@dataclass(frozen=True)
class Dataset:
    train: Pairs
    val: Pairs
    t0: float  # first sample time over all segments
    t1: float  # last sample time
    sources: tuple[str, ...]


@dataclass(frozen=True)
class TrainResult:
    loss: float  # final data loss, mean squared acceleration-equivalent error, (m/s^2)^2
    objective: float  # loss + weight_decay * ||theta||^2 (theta: all but the output bias)
    epochs: int
    wall_time: float  # s
    train_rmse_nominal: float  # one-step velocity RMSE on the training pairs, m/s
    train_rmse_model: float
    val_rmse_nominal: float  # the same on the held-out pairs (NaN when there are none)
    val_rmse_model: float
    max_abs_residual: float  # m/s^2, largest residual component over all inputs seen
    history: tuple[float, ...]  # data loss at each epoch (before its step)

    def training_info(self, dataset: Dataset) -> TrainingInfo:
        """Provenance for the model file (held-out metrics fall back to training metrics without a split)."""
        has_val = math.isfinite(self.val_rmse_model)
        return TrainingInfo(
            t0=dataset.t0,
            t1=dataset.t1,
            sources=dataset.sources,
            loss=self.loss,
            val_rmse_nominal=self.val_rmse_nominal if has_val else self.train_rmse_nominal,
            val_rmse_model=self.val_rmse_model if has_val else self.train_rmse_model,
            epochs=self.epochs,
            wall_time=self.wall_time,
        )


def make_dataset(
    segments: Sequence[Segment],
    filter_hz: float,
    validation_fraction: float = 0.2,
    gap_factor: float = 3.0,
) -> Dataset:
    """Pairs from ``segments``: split at gaps, low-pass filtered, last fraction of each held out.

    The filter is a zero-phase Butterworth (``filtfilt``) at ``filter_hz`` (<= 0: off).  Mocap
    velocities are finite differences and noisy; unfiltered, the residual would learn the noise.
    The same filter is applied to p and u too: the nominal model is linear, so filtering every
    signal keeps p' = v and v' = u + r exact for the filtered signals, whereas filtering v alone
    would make the fast part of u look like a model error.
    """
    if not 0.0 <= validation_fraction < 1.0:
        raise ValueError(f"validation_fraction must be in [0, 1), got {validation_fraction}")
    train_parts, val_parts, sources = [], [], []
    t_first, t_last = math.inf, -math.inf
    for k, seg in enumerate(segments):
        t, x, u = (np.asarray(a, dtype=np.float64) for a in (seg.t, seg.x, seg.u))
        n = t.shape[0]
        if t.ndim != 1 or x.shape != (n, 6) or u.shape not in ((n, 3), (n, 6)):
            raise ValueError(f"segment {k}: expected t (n,), x (n, 6), u (n, 3) or (n, 6); got {t.shape}, {x.shape}, {u.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x)) and np.all(np.isfinite(u))):
            raise ValueError(f"segment {k}: non-finite values")
        if n < 2:
            continue
        sources.append(seg.source or f"segment{k}")
        t_first, t_last = min(t_first, float(t[0])), max(t_last, float(t[-1]))
        pairs = _segment_pairs(t, x, u, filter_hz, gap_factor)
        m = len(pairs)
        if m == 0:
            continue
        n_val = 0
        if validation_fraction > 0.0 and m >= 2:
            n_val = min(m - 1, max(1, round(validation_fraction * m)))
        train_parts.append(_take(pairs, slice(0, m - n_val)))
        val_parts.append(_take(pairs, slice(m - n_val, m)))
    train = Pairs.concat(train_parts)
    if len(train) == 0:
        raise ValueError("no usable sample pairs in the data (too short, or all intervals are gaps)")
    return Dataset(train, Pairs.concat(val_parts), t_first, t_last, tuple(sources))


def _segment_pairs(t: np.ndarray, x: np.ndarray, u: np.ndarray, filter_hz: float, gap_factor: float) -> Pairs:
    dt = np.diff(t)
    positive = dt[dt > 0]
    if positive.size == 0:
        return Pairs.concat([])
    ok = (dt > 0) & (dt <= gap_factor * float(np.median(positive)))
    # Contiguous runs of good intervals: filter each run alone so a gap never smears across.
    parts = []
    edges = np.flatnonzero(np.diff(np.concatenate(([0], ok.astype(np.int8), [0]))))
    for start, stop in zip(edges[0::2], edges[1::2]):  # intervals start..stop-1, samples start..stop
        ts, xs, us = t[start : stop + 1], x[start : stop + 1].copy(), u[start : stop + 1].copy()
        _lowpass_inplace(ts, xs, us, filter_hz)
        parts.append(Pairs(ts[:-1], xs[:-1], us[:-1], np.diff(ts), xs[1:]))
    return Pairs.concat(parts)


def _lowpass_inplace(t: np.ndarray, x: np.ndarray, u: np.ndarray, filter_hz: float) -> None:
    if filter_hz <= 0.0 or t.shape[0] < 2:
        return
    fs = 1.0 / float(np.median(np.diff(t)))
    wn = filter_hz / (0.5 * fs)
    if wn >= 1.0:
        return  # cut-off at or above Nyquist: nothing to remove
    if t.shape[0] <= 3 * (FILTER_ORDER + 1):
        return  # too short to filter meaningfully
    b, a = butter(FILTER_ORDER, wn)
    # Pad by three cut-off periods (scipy's default is 3 taps): the end transients otherwise
    # reach tens of samples in, exactly where the validation pairs are.
    padlen = min(int(math.ceil(3.0 * fs / filter_hz)), t.shape[0] - 1)
    x[:] = filtfilt(b, a, x, axis=0, padlen=padlen)
    u[:] = filtfilt(b, a, u, axis=0, padlen=padlen)


def _take(p: Pairs, sl: slice) -> Pairs:
    return Pairs(p.t0[sl], p.x0[sl], p.u[sl], p.dt[sl], p.x1[sl])


def fit_normalisation(dataset: Dataset) -> Normalisation:
    """Input mean/scale of (v, u) and an output scale from the apparent residual, with floors."""
    p = dataset.train
    z = np.concatenate((p.x0[:, 3:6], p.u), axis=1)
    floors = np.array([VELOCITY_SCALE_FLOOR] * 3 + [ACCELERATION_SCALE_FLOOR] * 3
                      + [NEIGHBOUR_SCALE_FLOOR] * (p.u.shape[1] - 3))
    scale = np.maximum(z.std(axis=0), floors)
    apparent = (p.x1[:, 3:6] - p.x0[:, 3:6]) / p.dt[:, None] - p.u[:, 0:3]  # finite-difference residual
    out_scale = np.maximum(np.sqrt(np.mean(apparent**2, axis=0)), OUTPUT_SCALE_FLOOR)
    return Normalisation(z.mean(axis=0), scale, out_scale)


def nominal_prediction(p: Pairs) -> np.ndarray:
    """Exact nominal one-step prediction (p' = v, v' = u with u held)."""
    x1 = np.empty_like(p.x0)
    dt = p.dt[:, None]
    u = p.u[:, 0:3]  # without the neighbour's columns, if any
    x1[:, 0:3] = p.x0[:, 0:3] + dt * p.x0[:, 3:6] + 0.5 * dt * dt * u
    x1[:, 3:6] = p.x0[:, 3:6] + dt * u
    return x1


class _HybridOde(nn.Module):
    """dx/ds = dt_i * f(x, u_i) on normalised time s in [0, 1]: every pair ends at s = 1."""

    def __init__(self, model: TrainingResidual, u: torch.Tensor, dt: torch.Tensor) -> None:
        super().__init__()
        self.model = model
        self.u = u
        self.dt = dt[:, None]

    def forward(self, s: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self.dt * self.model.rhs(x, self.u)


@dataclass(frozen=True)
class _Batch:
    x0: torch.Tensor
    x1: torch.Tensor
    ode: _HybridOde


def _batch(queue: KnodeQueue, p: Pairs, model: TrainingResidual | None = None) -> _Batch:
    as_t = lambda a: torch.as_tensor(a, dtype=queue.dtype)  # noqa: E731
    model = model if model is not None else TrainingResidual(queue)
    return _Batch(as_t(p.x0), as_t(p.x1), _HybridOde(model, as_t(p.u), as_t(p.dt)))


def _minibatches(batch: _Batch, size: int, seed: int) -> Callable[[], _Batch]:
    """Each call, the batch one Adam step trains on: all pairs, or above ``size`` a random ``size`` of them.

    Up to ``size`` pairs (every cfknode log of a few minutes, every online window) a step is the
    full batch, as before; a 60,000-sample dataset costs a quarter as much a step (docs/data.md).
    """
    n = int(batch.x0.shape[0])
    if size <= 0 or n <= size:
        return lambda: batch
    generator = torch.Generator().manual_seed(seed)

    def draw() -> _Batch:
        idx = torch.randperm(n, generator=generator)[:size]
        ode = _HybridOde(batch.ode.model, batch.ode.u[idx], batch.ode.dt[idx, 0])
        return _Batch(batch.x0[idx], batch.x1[idx], ode)

    return draw


def _integrate(batch: _Batch, method: str, adjoint: bool, step_size: float, params: Sequence[torch.Tensor]) -> torch.Tensor:
    """x at s = 1 for every pair: one batched odeint call."""
    s = torch.tensor([0.0, 1.0], dtype=batch.x0.dtype)
    options = {"step_size": step_size} if method in ("rk4", "euler") else None
    if adjoint:
        traj = odeint_adjoint(
            batch.ode, batch.x0, s, method=method, options=options, adjoint_options=options, adjoint_params=tuple(params)
        )
    else:
        traj = odeint(batch.ode, batch.x0, s, method=method, options=options)
    return traj[-1]


def _data_loss(pred: torch.Tensor, batch: _Batch, position_weight: float) -> torch.Tensor:
    dt = batch.ode.dt
    acc_err = (pred[:, 3:6] - batch.x1[:, 3:6]) / dt
    loss = (acc_err * acc_err).sum(dim=1).mean()
    if position_weight > 0.0:
        pos_err = (pred[:, 0:3] - batch.x1[:, 0:3]) * (2.0 / (dt * dt))
        loss = loss + position_weight * (pos_err * pos_err).sum(dim=1).mean()
    return loss


def _velocity_rmse(pred_v: np.ndarray, true_v: np.ndarray) -> float:
    if pred_v.shape[0] == 0:
        return math.nan
    return float(np.sqrt(np.mean((pred_v - true_v) ** 2)))


def train(
    queue: KnodeQueue,
    dataset: Dataset,
    cfg: TrainingConfig,
    *,
    step_size: float = 1.0,
    position_weight: float = 0.0,
    progress: Callable[[int, float], None] | None = None,
) -> TrainResult:
    """Train the newest network of ``queue`` in place (the others are frozen).

    Uses ``cfg.epochs``, ``lr``, ``weight_decay``, ``method`` and ``adjoint`` (the seed acts where
    networks are created: ``train_new_model``, ``KnodeQueue(seed=...)``).
    ``step_size`` is the rk4 step in units of each pair's own interval (1.0: one step per pair).
    ``progress(epoch, data_loss)`` is called after every epoch.
    """
    if not 0.0 < step_size <= 1.0:
        raise ValueError(f"step_size is a fraction of each interval in (0, 1], got {step_size}")
    # Two threads on a shared 2-core machine slowed these small batches 4-80x
    # (docs/solver-timings.md#training).
    torch.set_num_threads(1)
    params = list(queue.trainable_parameters())
    if not params:
        raise ValueError("the queue has no trainable network: push() one before training")
    start = time.perf_counter()
    model = TrainingResidual(queue)
    batch = _batch(queue, dataset.train, model)
    optimiser = torch.optim.Adam(params, lr=cfg.lr)
    # Weight decay spares the output bias: it is the constant offset (a mass or thrust error at
    # hover, a CoG bias) a window identifies best; decayed, it was learned at a fraction of its
    # size (docs/history.md#online-learning-how-the-defaults-were-reached).
    bias = queue.newest.layers[-1].bias
    decayed = [p for p in params if p is not bias]
    history = []
    draw = _minibatches(batch, cfg.batch_size, cfg.seed)
    for epoch in range(1, cfg.epochs + 1):
        optimiser.zero_grad(set_to_none=True)
        step = draw()
        pred = _integrate(step, cfg.method, cfg.adjoint, step_size, params)
        loss = _data_loss(pred, step, position_weight)
        objective = loss + cfg.weight_decay * sum((p * p).sum() for p in decayed)
        objective.backward()
        optimiser.step()
        history.append(float(loss.detach()))
        if progress is not None:
            progress(epoch, history[-1])
    wall = time.perf_counter() - start

    with torch.no_grad():
        pred_train = _integrate(batch, cfg.method, False, step_size, params)
        final_loss = float(_data_loss(pred_train, batch, position_weight))
        reg = float(sum((p * p).sum() for p in decayed))
        if len(dataset.val):
            val_pred = _integrate(_batch(queue, dataset.val, model), cfg.method, False, step_size, params).numpy()
        else:
            val_pred = np.zeros((0, 6))
        z_all = Pairs.concat([dataset.train, dataset.val])
        residual = queue(torch.as_tensor(z_all.x0, dtype=queue.dtype), torch.as_tensor(z_all.u, dtype=queue.dtype))
    tr, va = dataset.train, dataset.val
    return TrainResult(
        loss=final_loss,
        objective=final_loss + cfg.weight_decay * reg,
        epochs=cfg.epochs,
        wall_time=wall,
        train_rmse_nominal=_velocity_rmse(nominal_prediction(tr)[:, 3:6], tr.x1[:, 3:6]),
        train_rmse_model=_velocity_rmse(pred_train.numpy()[:, 3:6], tr.x1[:, 3:6]),
        val_rmse_nominal=_velocity_rmse(nominal_prediction(va)[:, 3:6], va.x1[:, 3:6]),
        val_rmse_model=_velocity_rmse(val_pred[:, 3:6], va.x1[:, 3:6]),
        max_abs_residual=float(residual.abs().max()) if residual.numel() else 0.0,
        history=tuple(history),
    )


def one_step_rmse(queue: KnodeQueue, pairs: Pairs, method: str = "rk4", step_size: float = 1.0) -> float:
    """Held-out one-step velocity RMSE (m/s) of nominal + ``queue`` on ``pairs``; for validation gates.

    An empty queue gives the nominal model's error, so a candidate and the current model are
    compared on the same pairs with the same integrator.
    """
    if len(pairs) == 0:
        return math.nan
    if not queue.networks:
        return _velocity_rmse(nominal_prediction(pairs)[:, 3:6], pairs.x1[:, 3:6])
    with torch.no_grad():
        pred = _integrate(_batch(queue, pairs), method, False, step_size, []).numpy()
    return _velocity_rmse(pred[:, 3:6], pairs.x1[:, 3:6])


def train_new_model(
    dataset: Dataset,
    knode_cfg: KnodeConfig,
    training_cfg: TrainingConfig,
    *,
    initial: ModelFile | None = None,
    warm_start: bool = True,
    step_size: float = 1.0,
    position_weight: float = 0.0,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[KnodeQueue, TrainResult]:
    """Push a network onto ``initial``'s queue (or a new queue) and train it.

    A new queue takes its architecture from ``knode_cfg``, its normalisation from the data and
    its initialisation from ``training_cfg.seed``.  On an existing queue the new network is a
    copy of the newest (``warm_start``) or fresh with the newest's normalisation.
    """
    if initial is None:
        queue = KnodeQueue.from_config(knode_cfg, fit_normalisation(dataset), seed=training_cfg.seed)
        queue.push()
    else:
        queue = to_torch_queue(initial, seed=training_cfg.seed)
        queue.push(copy_from_newest=warm_start)
    result = train(queue, dataset, training_cfg, step_size=step_size, position_weight=position_weight, progress=progress)
    return queue, result


__all__ = [
    "Dataset",
    "Pairs",
    "Segment",
    "TrainResult",
    "fit_normalisation",
    "make_dataset",
    "nominal_prediction",
    "one_step_rmse",
    "train",
    "train_new_model",
]
