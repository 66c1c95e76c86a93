"""The online trainer: a child process that trains one new KNODE network per data window (the paper's Algorithm 2).

The flight process starts it (``cfknode.flight.learning.trainer_client``: forked from a server that
has imported ``CHILD_IMPORTS`` on Linux, spawned elsewhere) and talks to it over one duplex
``multiprocessing`` pipe. This module's top level is torch-free, so the flight process can name
``trainer_main`` as the process target and use the message types below; torch is imported
only in the child (and in the server it is forked from).

Protocol (every message a picklable frozen dataclass of numpy arrays and plain values):
- child -> parent, once: ``TrainerReady`` after torch is imported and one warm-up round has run
  (the first round in a fresh interpreter is ~10x slower; paying that before take-off keeps
  the first honest latency honest about training, not about imports);
- parent -> child: ``TrainRequest`` (at most one outstanding; the parent enforces it), or
  ``None`` to stop;
- child -> parent: one ``TrainOutcome`` per request, with the new queue as a numpy
  ``ModelFile`` (or ``error`` set when the round failed in an ordinary way, e.g. too little data);
- parent -> child, between rounds: a ``Job`` (numpy work, e.g. the validation gate), answered by one
  ``JobOutcome``: the trainer's core does it instead of the flight loop's tick gaps.

A round: the window (and optionally a few recent ones, each its own segment) becomes a
dataset with ``make_dataset``; a network is pushed onto the queue the window was flown with
(``base``; oldest dropped when full, older ones frozen) and trained with ``train``. A warm
start copies the newest network and refits its normalisation to the new data while keeping
the function it computes, so Adam's steps are scaled for the new data (a mass change
multiplies the residual by 20 where the old output scale was fitted to a residual of ~0).

Fault injection (``FaultInjection``, config ``online.inject``) acts on the request's round
number, which the parent counts across restarts: crash = ``os._exit``, hang = sleep forever,
nan = the trained network's output layer becomes NaN.
"""

from __future__ import annotations

import importlib
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any, Callable

import numpy as np

from cfknode.models.input_bounds import BOUNDS_KEY, data_bounds, queue_bounds
from cfknode.models.settings import FaultInjection, KnodeConfig, TrainingConfig
from cfknode.models.input_layouts import WAKE_INPUT_NAMES, about_the_axis
from cfknode.models.modelfile import MASKED_INPUT_SCALE, ModelFile, Normalisation

CRASH_EXIT_CODE = 70  # what an injected crash exits with (EX_SOFTWARE)
# Stop signals the trainer ignores: a Ctrl-C in the terminal reaches its whole process group,
# but only the flight process decides when the flight ends; it stops the trainer over the
# pipe (or kills it).
IGNORED_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
# What a trainer imports before its first round: about 3 s of CPU in a fresh interpreter, which a
# trainer forked from a server that imported them once skips. ``torch._dynamo`` is torch.optim's
# (its first step imports it, 1.1-1.5 s); a name this torch lacks is skipped.
CHILD_IMPORTS = ("torch", "torch._dynamo", "cfknode.models.knode", "cfknode.models.training")
# Online input scales are floored at the flight envelope, not one window's spread: a 0.5 s
# window barely varies (v, u), and standardising by that spread lets the network fit steep,
# spurious slopes (measured: dr/dv up to +2.4 1/s, dr/du down to -0.9 where the truth was 0
# and -0.23) that the MPC then trusts over its whole horizon. At envelope scale a window
# spans a small input range, so the fit stays close to an offset unless slopes pay off.
ONLINE_VELOCITY_SCALE = 1.0  # m/s
ONLINE_ACCELERATION_SCALE = 3.0  # m/s^2


@dataclass(frozen=True)
class Window:
    """One recorded window: t (n,), x = (p, v) (n, 6), u = commanded acceleration (n, 3)."""

    index: int  # the recorder's window counter (across the flight)
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    version: int  # model version that flew the whole window
    nb: np.ndarray | None = None  # (n, 3) the neighbour's relative position (docs/fleet.md#neighbour-input); None: none

    @property
    def inputs(self) -> np.ndarray:
        """What the networks see besides v: the command, and the neighbour's relative position when recorded."""
        return self.u if self.nb is None else np.concatenate((self.u, self.nb), axis=1)

    @property
    def t0(self) -> float:
        return float(self.t[0])

    @property
    def t1(self) -> float:
        return float(self.t[-1])


@dataclass(frozen=True)
class TrainerSettings:
    """What every round uses; fixed for the process's life."""

    knode: KnodeConfig
    training: TrainingConfig  # with the online epochs, lr and weight decay
    warm_start: bool
    inject: FaultInjection
    # Added to the trainer's niceness (``online.trainer_nice``) on a wall clock: the flight loop shares the
    # cores with it, and a training round that holds a core the loop wakes up on makes the loop miss its slot.
    nice: int = 0
    # Modules the child imports before it reports ready, by name: the first job would otherwise pay them
    # (the gate's scipy.signal took seconds on a loaded machine), counted against its hang deadline.
    preload: tuple[str, ...] = ()
    # Store each new network's input range with the model (models/input_bounds.py): the flight holds it there.
    input_bounds: bool = False
    # With the neighbour input: the networks see only the neighbour's relative position (``online_normalisation``).
    wake_only: bool = False


@dataclass(frozen=True)
class TrainRequest:
    round: int  # 1, 2, ... across the flight (and across trainer restarts)
    version: int  # version the candidate will carry
    window: Window  # the newest window: the one this round learns from
    replay: tuple[Window, ...]  # earlier windows trained on as well (oldest first)
    base: ModelFile | None  # the queue the window was flown with (None: nominal)
    holdout_fraction: float  # the last fraction of the window is held out (0: train on all of it)


@dataclass(frozen=True)
class Job:
    """Numpy work the flight side hands the trainer process instead of doing it between its own ticks.

    ``fn`` is named by reference (a module-level function), so this module needs no import of it; the
    child imports its module on first use (``TrainerSettings.preload`` does that before take-off).
    The learner sends one only while the trainer is idle: no round waits behind it."""

    id: int
    fn: Callable[..., Any]
    args: tuple[Any, ...]


@dataclass(frozen=True)
class JobOutcome:
    id: int
    value: Any  # ``fn``'s return value (None when it raised)
    error: str = ""  # non-empty: ``fn`` raised this, in one line
    cpu_s: float = 0.0  # CPU time of the job in the child


@dataclass(frozen=True)
class TrainerReady:
    pid: int
    warmup_s: float  # wall time of the warm-up round
    nice: int = 0  # the trainer's niceness (the parent's plus ``TrainerSettings.nice``)
    threads: int = 1  # torch's intra-op threads


@dataclass(frozen=True)
class TrainOutcome:
    round: int
    version: int
    base_version: int  # version of the base queue (taken from the request's window)
    model: ModelFile | None  # None when the round failed
    window_t0: float
    window_t1: float
    train_t1: float  # last sample time trained on (< window_t1 when the tail was held out)
    pairs: int  # training pairs
    loss: float  # final data loss, (m/s^2)^2
    val_rmse_model: float  # trainer's held-out one-step velocity RMSE, m/s (NaN without a holdout)
    val_rmse_nominal: float
    max_abs_residual: float  # m/s^2 over the training inputs
    wall_s: float  # wall time of the whole round in the child (dataset + training + export)
    cpu_s: float  # CPU time of the round in the child
    error: str = ""  # non-empty: the round failed (model is None)


def trainer_main(conn: Connection, settings: TrainerSettings, tagged: bool = False) -> None:
    """Child-process entry: warm up, report ready, serve requests until ``None`` or EOF, then end the process.

    ``tagged``: one trainer serving several learners (a fleet); each request comes as ``(tag,
    TrainRequest)`` and its outcome goes back as ``(tag, TrainOutcome)``, in arrival order."""
    for sig in IGNORED_SIGNALS:  # first, before the slow torch import (see IGNORED_SIGNALS)
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, IGNORED_SIGNALS)  # blocked by the parent while starting it
    if settings.nice > 0:
        # Before the torch import: it and the warm-up are the child's heaviest work while the flight
        # starts up. Only ever lower: raising a priority needs privileges and is not the trainer's to take.
        os.nice(settings.nice)
    import torch

    # One thread: two on these shared 2-core machines slowed small batches 4-80x
    # (docs/solver-timings.md#training),
    # and the other core is the flight loop's. No inter-op pool either: its threads would be more
    # runnable threads beside the loop's.
    torch.set_num_threads(1)
    torch.set_num_interop_threads(1)
    start = time.perf_counter()
    # A few epochs pay the first-call costs (autograd, allocator); more would only delay take-off.
    _train_round(_warmup_request(), replace(settings, training=replace(settings.training, epochs=3)))
    for name in settings.preload:
        importlib.import_module(name)
    conn.send(TrainerReady(os.getpid(), time.perf_counter() - start, os.nice(0), torch.get_num_threads()))
    _serve(conn, settings, tagged)
    # Nothing is left to hand back: leave without the interpreter's teardown of torch, about 1 s that
    # the flight's close would wait for after every landing.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _serve(conn: Connection, settings: TrainerSettings, tagged: bool) -> None:
    """Answer requests until ``None`` (the flight closes the trainer) or EOF (the flight is gone)."""
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return  # the flight process is gone
        if request is None:
            return
        tag, request = request if tagged else (None, request)
        if isinstance(request, Job):
            outcome: TrainOutcome | JobOutcome = run_job(request)
        else:
            _maybe_fail_before(request.round, settings.inject)
            outcome = _train_round(request, settings)
        conn.send((tag, outcome) if tagged else outcome)


def run_job(job: Job) -> JobOutcome:
    """Run one job; an exception comes back as the outcome's ``error``, as a failed round does."""
    cpu0 = time.process_time()
    try:
        value = job.fn(*job.args)
    except Exception as exc:  # noqa: BLE001 - the flight side decides what a failed job means
        return JobOutcome(job.id, None, f"{type(exc).__name__}: {' '.join(str(exc).split())}",
                          time.process_time() - cpu0)
    return JobOutcome(job.id, value, "", time.process_time() - cpu0)


def _maybe_fail_before(round_: int, inject: FaultInjection) -> None:
    if round_ == inject.crash_at_round > 0:
        os._exit(CRASH_EXIT_CODE)
    if round_ == inject.hang_at_round > 0:
        while True:  # a hung trainer: only a kill ends it
            time.sleep(3600.0)


def _train_round(request: TrainRequest, settings: TrainerSettings) -> TrainOutcome:
    """Train one candidate; ordinary failures come back as an outcome with ``error`` set."""
    wall0, cpu0 = time.perf_counter(), time.process_time()
    base_version = request.window.version
    try:
        outcome = _train(request, settings)
    except (ValueError, RuntimeError, FloatingPointError) as exc:
        w = request.window
        return TrainOutcome(
            request.round, request.version, base_version, None, w.t0, w.t1, w.t1, 0, math.nan, math.nan, math.nan,
            math.nan, time.perf_counter() - wall0, time.process_time() - cpu0, error=" ".join(str(exc).split()) or type(exc).__name__,
        )
    return replace(outcome, wall_s=time.perf_counter() - wall0, cpu_s=time.process_time() - cpu0)


def _seen(window: Window, wake_only: bool) -> np.ndarray:
    """A window's inputs as the round's networks see them: a wake network the drone above about its axis."""
    if not wake_only or window.nb is None:
        return window.inputs
    return np.concatenate((window.u, about_the_axis(window.nb)), axis=1)


def _train(request: TrainRequest, settings: TrainerSettings) -> TrainOutcome:
    import torch

    from cfknode.models.knode import KnodeQueue, from_torch_queue, to_torch_queue
    from cfknode.models.training import Pairs, Segment, fit_normalisation, make_dataset, train

    w = request.window
    segments = [Segment(r.t, r.x, _seen(r, settings.wake_only), source=f"window{r.index}")
                for r in (*request.replay, w)]
    # make_dataset holds out the tail of every segment it is given, but only the newest window's
    # tail is held out for the gate: the replayed windows become a dataset of their own, all trained on.
    dataset = make_dataset(segments[-1:], settings.training.velocity_filter_hz, request.holdout_fraction)
    if len(segments) > 1:
        older = make_dataset(segments[:-1], settings.training.velocity_filter_hz, 0.0)
        dataset = replace(
            dataset,
            train=Pairs.concat([older.train, dataset.train]),
            t0=min(older.t0, dataset.t0),
            sources=older.sources + dataset.sources,
        )
    norm = online_normalisation(fit_normalisation(dataset), settings.wake_only)
    seed = settings.training.seed + request.round
    base = request.base
    if base is not None and (tuple(base.inputs) == WAKE_INPUT_NAMES) != settings.wake_only:
        base = None  # its networks read d otherwise: a queue holds one input layout
    if base is None or not base.networks:
        queue = KnodeQueue.from_config(settings.knode, norm, seed=seed)
        queue.push()
    else:
        queue = to_torch_queue(base, seed=seed)
        # A wake-only network is not warm-started from one that saw the drone's own inputs, nor the other way:
        # the masked scale would keep (or drop) their function, inputs and all.
        if settings.warm_start and base.networks[-1].normalisation.wake_only == settings.wake_only:
            net = queue.push(copy_from_newest=True)
            renormalise(net, norm)
        else:
            queue.push(normalisation=norm)
    result = train(queue, dataset, settings.training)
    if request.round == settings.inject.nan_at_round > 0:
        with torch.no_grad():
            queue.newest.layers[-1].weight.fill_(float("nan"))
    model = from_torch_queue(
        queue,
        training=result.training_info(dataset),
        extra={"version": request.version, "round": request.round, "base_version": w.version},
    )
    if settings.wake_only:
        model = replace(model, inputs=WAKE_INPUT_NAMES)
    if settings.input_bounds and len(dataset.train):
        z = np.concatenate((dataset.train.x0[:, 3:6], dataset.train.u), axis=1)
        held = queue_bounds(None if base is None else base.extra, 0 if base is None else len(base.networks),
                            data_bounds(z), len(model.networks))
        model = replace(model, extra={**model.extra, BOUNDS_KEY: held})
    train_t1 = float(dataset.train.t0[-1] + dataset.train.dt[-1]) if len(dataset.train) else w.t1
    return TrainOutcome(
        round=request.round,
        version=request.version,
        base_version=w.version,
        model=model,
        window_t0=w.t0,
        window_t1=w.t1,
        train_t1=train_t1,
        pairs=len(dataset.train),
        loss=result.loss,
        val_rmse_model=result.val_rmse_model,
        val_rmse_nominal=result.val_rmse_nominal,
        max_abs_residual=result.max_abs_residual,
        wall_s=0.0,
        cpu_s=0.0,
    )


def online_normalisation(fitted: Normalisation, wake_only: bool = False) -> Normalisation:
    """``fitted`` with its input scales raised to the online floors (see ONLINE_VELOCITY_SCALE).

    ``wake_only`` (a network with the neighbour input): the drone's own velocity and command are switched
    off (``MASKED_INPUT_SCALE``). In a wake the controller answers the force (more thrust, a dip, slower
    along the line), so in closed-loop data those inputs follow the wake, and a network given them explained
    it by them: slopes of -1 on the vertical command and +6 1/s on the vertical speed, which the MPC then
    flies as a feedback. Its horizontal outputs are off too: on a line the neighbour's position also says
    where along it the drone is, and a network fitted the attitude loop's lag there (docs/fleet.md#wake-only)."""
    extra = len(fitted.input_scale) - 6  # the neighbour's relative position keeps its fitted scale
    floors = np.array([ONLINE_VELOCITY_SCALE] * 3 + [ONLINE_ACCELERATION_SCALE] * 3 + [0.0] * extra)
    scale, out = np.maximum(fitted.input_scale, floors), fitted.output_scale.copy()
    if wake_only and extra:  # own inputs off; the wake acts downward, so the horizontal outputs off too
        scale[:6], out[0:2] = MASKED_INPUT_SCALE, 1.0 / MASKED_INPUT_SCALE
    return Normalisation(fitted.input_mean, scale, out)


def renormalise(net: Any, norm: Normalisation) -> None:
    """Give a ``ResidualNet`` new input/output normalisation without changing the function it computes.

    First layer: W (z - m)/s + b = W' (z - m')/s' + b' with W' = W s'/s, b' = b + W (m' - m)/s.
    Output: s_o (W h + b) = s_o' (W'' h + b'') with W'' = W s_o/s_o', b'' = b s_o/s_o'.
    """
    import torch

    with torch.no_grad():
        dtype = net.input_mean.dtype
        m_new = torch.as_tensor(norm.input_mean, dtype=dtype)
        s_new = torch.as_tensor(norm.input_scale, dtype=dtype)
        o_new = torch.as_tensor(norm.output_scale, dtype=dtype)
        first, last = net.layers[0], net.layers[-1]
        first.bias.add_(first.weight @ ((m_new - net.input_mean) / net.input_scale))
        first.weight.mul_((s_new / net.input_scale)[None, :])
        gain = net.output_scale / o_new
        last.weight.mul_(gain[:, None])
        last.bias.mul_(gain)
        net.input_mean.copy_(m_new)
        net.input_scale.copy_(s_new)
        net.output_scale.copy_(o_new)


def _warmup_request() -> TrainRequest:
    """A small synthetic round (hover with a constant residual) to pay torch's first-call costs."""
    n = 120
    t = np.arange(n) / 400.0
    u = np.zeros((n, 3))
    v = np.zeros((n, 3))
    v[:, 2] = 0.5 * t  # v' = u + 0.5 m/s^2
    x = np.concatenate((np.zeros((n, 3)), v), axis=1)
    return TrainRequest(0, 0, Window(0, t, x, u, 0), (), None, 0.0)


__all__ = [
    "CRASH_EXIT_CODE",
    "Job",
    "JobOutcome",
    "TrainOutcome",
    "TrainRequest",
    "TrainerReady",
    "TrainerSettings",
    "Window",
    "renormalise",
    "trainer_main",
]
