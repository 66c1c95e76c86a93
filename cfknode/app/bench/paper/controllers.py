"""The benchmark's controllers and learners, in the two formulations.

``Formulation.paper()`` is the authors' code (docs/paper-code.md#mpc, #knode, #online-loop):
unit weights on raw SI units, a constant-point reference (the reference at t + 2 ms held
over the 1 s horizon), a 17 -> 64 -> 13 residual on all 13 derivatives with raw inputs,
fresh networks trained 80 Adam steps on one 0.15 s window, and the lockstep in which the
simulator waits for every model.  ``Formulation.default()`` is cfknode's: reference preview
over the horizon, weights scaled to the units, the rotor-force polytope as input bounds, a
(v, q, w, u) -> (v', w') residual, warm-started training with a validation gate, and honest
latency (a model acts only after its window closed and its training wall time passed).

Controllers share one interface: the runner calls ``before_tick``/``after_tick`` around a
control tick and ``observe`` after every plant step; ``residual`` is the model the MPC uses.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch

from cfknode.app.bench.paper.mpc_full import FullMpcSpec
from cfknode.models.quadrotor import quat_to_rotation
from cfknode.app.bench.paper.rigid_body_knode import (
    NumpyResidual,
    OneStepPairs,
    Physics,
    QueueWeights,
    ResidualLayout,
    RigidBodyQueue,
    TrainSettings,
    residual_error,
    fit_output_layer,
    train_newest,
)
from cfknode.app.bench.paper.protocol import ChordCircle, CrazyflieParams, PaperProtocol

ControllerKind = Literal["mpc", "knode_offline", "geometric", "knode_online", "oracle"]
CONTROLLERS: tuple[ControllerKind, ...] = ("mpc", "knode_offline", "geometric", "knode_online", "oracle")


@dataclass(frozen=True)
class Formulation:
    """Everything that differs between the paper's code and cfknode on the same protocol."""

    name: str
    mpc: FullMpcSpec  # residual_rows are set per controller (empty for nominal and oracle)
    preview: bool  # stage k tracks the reference at t + k dt (else the point at t + plant dt)
    # Inputs are penalised about the model's hover input (T_h, 0, 0, 0), T_h from the MPC's own model
    # (nominal, oracle mass, or with the learned residual); else about 0, the paper's R = I.
    hover_input_ref: bool
    layout: ResidualLayout
    online: TrainSettings
    offline: TrainSettings
    t_col: float = 0.15
    collect_from: float = 2.0  # s: the collector's start (the paper's is the known disturbance time)
    lockstep: bool = True  # wait for every model (the paper); False: honest latency
    warm_start: bool = False  # a new network starts as a copy of the newest (else fresh Xavier)
    validation_fraction: float = 0.0  # > 0: hold out the window's tail and gate the swap on it
    restart_window_on_swap: bool = False  # discard data flown partly under the previous model
    misaligned_pairs: bool = True  # reproduce the original's pairing of rows [x_{k+1}, u_k]
    noise_std: float = 1e-4  # added to the training rows (the original's N(0, 1e-8))
    fallback_bug: bool = True  # the original's k_t f^2 for a negative rotor force (else 0)
    online_starts_from: Literal["offline", "nominal"] = "offline"
    torch_dtype: str = "float32"
    residual_bound: float = 1e3  # gate: |residual| above this on the window rejects the model
    nominal_on_failure: bool = False  # a failed solve with a model is re-solved without it (else: hold u)
    output_ridge: float = 0.0  # > 0: after the Adam steps, solve the output layer in closed form (ridge)
    monitor: bool = False  # drop a model that predicts the last tick's samples worse than nominal
    # ... by this factor: a partly learned model can lose to nominal on one tick's samples by
    # chance (seen: 1.2-2x); a model the world has moved away from loses by 20x and more.
    monitor_margin: float = 3.0

    @property
    def dtype(self) -> torch.dtype:
        return getattr(torch, self.torch_dtype)

    def mpc_spec(self, with_residual: bool) -> FullMpcSpec:
        return replace(self.mpc, residual_rows=self.layout.rows if with_residual else ())

    @classmethod
    def paper(cls) -> Formulation:
        return cls(
            name="paper",
            mpc=FullMpcSpec(),  # N 20, dt 0.05, RK4 x 4, Q = R = P = I, 0 <= T <= 0.575 N
            preview=False,
            hover_input_ref=False,
            layout=ResidualLayout.paper(),
            online=TrainSettings(epochs=80, lr=0.01, l2=5e-8, loss="paper"),
            # The original's offline model carries 200 loss entries; its training script is not public.
            offline=TrainSettings(epochs=200, lr=0.01, l2=5e-8, loss="paper"),
            collect_from=2.0,
            lockstep=True,
            online_starts_from="offline",
        )

    @classmethod
    def default(cls, vehicle: CrazyflieParams | None = None) -> Formulation:
        veh = vehicle or CrazyflieParams()
        hover = veh.mass * veh.gravity
        # Scales: 0.1 m in x, y and 0.03 m in z, 0.5 m/s, 0.1 in tilt quaternion (about 11 deg),
        # 0.03 in yaw, 3 rad/s; 0.3 N of thrust and 1e-3 N m of moment (about 70 rad/s^2) cost 1.
        # The stiff z and cheap thrust keep a mass step's transient small before any model
        # has learned it (measured: z MSE after the two events 30x lower than at 0.1 m / 0.1 N).
        q = (100.0, 100.0, 1000.0) + (4.0,) * 3 + (0.0, 100.0, 100.0, 1000.0) + (0.1,) * 3
        r = (10.0, 1e6, 1e6, 1e6)
        p = tuple(10.0 * w for w in q)
        return cls(
            name="default",
            mpc=FullMpcSpec(
                hessian="nominal",
                input_scale=(0.1, 1e-3, 1e-3, 1e-3),
                q=q,
                r=r,
                p=p,
                thrust_bounds=(0.0, veh.thrust_max),
                rotor_mixer=tuple(tuple(row) for row in veh.mixer),
                rotor_force_max=veh.rotor_force_max,
            ),
            preview=True,
            hover_input_ref=True,
            layout=ResidualLayout.default(hover),
            online=TrainSettings(epochs=20, lr=0.005, l2=1e-6, loss="residual"),
            offline=TrainSettings(epochs=400, lr=0.005, l2=1e-6, loss="residual"),
            collect_from=0.0,
            lockstep=False,
            warm_start=True,
            validation_fraction=0.2,
            restart_window_on_swap=True,
            misaligned_pairs=False,
            noise_std=0.0,
            fallback_bug=False,
            online_starts_from="nominal",
            nominal_on_failure=True,
            output_ridge=10.0,
            monitor=True,
        )

    @classmethod
    def named(cls, name: str) -> Formulation:
        if name == "paper":
            return cls.paper()
        if name == "default":
            return cls.default()
        raise ValueError(f"unknown formulation {name!r}; expected 'paper' or 'default'")


def mpc_reference(
    form: Formulation, circle: ChordCircle, t: float, plant_dt: float, hover_thrust: float
) -> tuple[np.ndarray, np.ndarray]:
    """(x_ref (N, 13), u_ref (N, 4)) for a tick at time t."""
    n, dt = form.mpc.horizon, form.mpc.dt
    times = t + dt * np.arange(1, n + 1) if form.preview else np.full(n, t + plant_dt)
    p, v = circle.sample(times)
    x_ref = np.zeros((n, 13))
    x_ref[:, 0:3] = p
    x_ref[:, 3:6] = v
    x_ref[:, 6] = 1.0
    u_ref = np.zeros((n, 4))
    if form.hover_input_ref:
        u_ref[:, 0] = hover_thrust
    return x_ref, u_ref


def model_hover_thrust(
    x: np.ndarray, mass: float, gravity: float, residual: NumpyResidual | None, thrust_max: float
) -> float:
    """Thrust that holds altitude (v_z' = 0) at state x with no moments, under the MPC's own model.

    Nominal: m g / b_z; with a residual, three Newton steps on T b_z / m - g + r_z(x, T) = 0.
    """
    bz = 1.0 - 2.0 * (x[7] ** 2 + x[8] ** 2)
    thrust = mass * gravity / max(bz, 0.5)
    if residual is None or 5 not in residual.rows:
        return thrust
    row = residual.rows.index(5)
    z = np.concatenate((x, [thrust, 0.0, 0.0, 0.0]))[None, :]
    for _ in range(3):
        z[0, 13] = thrust
        r, jac = residual.value_and_jacobian(z)
        slope = bz / mass + jac[0, row, 13]
        if slope <= 1e-6:
            break
        thrust = float(np.clip(thrust - (thrust * bz / mass - gravity + r[0, row]) / slope, 0.0, thrust_max))
    return thrust


# --- geometric baseline -------------------------------------------------------------------


@dataclass(frozen=True)
class GeometricGains:
    """SE(3) gains found pickled in the authors' offline model (docs/paper-code.md#baselines)."""

    kp: tuple[float, float, float] = (20.0, 20.0, 20.0)  # 1/s^2 (times the mass: N/m)
    kd: tuple[float, float, float] = (8.9443, 8.9443, 8.9443)
    kr: tuple[float, float, float] = (1000.0, 1000.0, 50.0)  # attitude, 1/s^2 (times the inertia)
    kw: tuple[float, float, float] = (63.2456, 63.2456, 16.2635)


class GeometricController:
    """Lee/Mellinger SE(3) control on position and velocity of the reference, yaw 0, no feedforward
    (the paper's trajectory provides none), with the nominal mass; run at the plant rate."""

    def __init__(self, vehicle: CrazyflieParams, gains: GeometricGains | None = None) -> None:
        self.vehicle = vehicle
        self.gains = gains or GeometricGains()
        self._inertia = np.asarray(vehicle.inertia)

    def command(self, x: np.ndarray, p_ref: np.ndarray, v_ref: np.ndarray) -> np.ndarray:
        g = self.gains
        m = self.vehicle.mass
        force = m * (-np.asarray(g.kp) * (x[0:3] - p_ref) - np.asarray(g.kd) * (x[3:6] - v_ref))
        force[2] += m * self.vehicle.gravity
        rot = quat_to_rotation(x[6:10])
        thrust = float(force @ rot[:, 2])
        b3 = force / np.linalg.norm(force)
        b2 = np.cross(b3, np.array([1.0, 0.0, 0.0]))
        b2 /= np.linalg.norm(b2)
        rot_des = np.column_stack((np.cross(b2, b3), b2, b3))
        s = 0.5 * (rot_des.T @ rot - rot.T @ rot_des)
        e_r = np.array([s[2, 1], s[0, 2], s[1, 0]])
        w = x[10:13]
        jw = self._inertia * w
        moment = self._inertia * (-np.asarray(g.kr) * e_r - np.asarray(g.kw) * w) + np.cross(w, jw)
        return np.array([thrust, moment[0], moment[1], moment[2]])


# --- learners --------------------------------------------------------------------------------


@dataclass(frozen=True)
class RoundRecord:
    """One training round of an online learner."""

    window_end: float  # s, sim time the window closed
    start: float  # s, sim time training started
    ready: float  # s, sim time the model was available (lockstep: = window_end)
    swap: float  # s, sim time the model first drove the MPC (nan when rejected or never used)
    wall_time: float  # s, measured training wall time (incl. the gate)
    samples: int
    loss_first: float
    loss_last: float
    accepted: bool
    val_candidate: float = math.nan
    val_current: float = math.nan


class NoLearner:
    """A fixed model (or none): nominal MPC, oracle, offline KNODE-MPC."""

    def __init__(self, residual: NumpyResidual | None = None) -> None:
        self.residual = residual
        self.rounds: list[RoundRecord] = []

    def before_tick(self, t: float) -> None:
        pass

    def after_tick(self, t: float) -> None:
        pass

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        pass


def _physics(vehicle: CrazyflieParams) -> Physics:
    return Physics(vehicle.mass, vehicle.inertia, vehicle.gravity)


class LockstepLearner:
    """The paper's online loop as its code runs it (docs/paper-code.md#online-loop).

    Rows [x after step k, u_k] are collected from ``collect_from``; when a window of ``t_col``
    closes, the simulation waits while a fresh network is pushed onto the queue and trained
    on that window alone.  The model is loaded after the next tick's solve, so it first
    drives the tick after that.
    """

    def __init__(
        self, protocol: PaperProtocol, form: Formulation, initial: QueueWeights | None, seed: int
    ) -> None:
        self.protocol = protocol
        self.form = form
        self.phys = _physics(protocol.vehicle)
        self.dt = 1.0 / protocol.plant_hz  # the original's t_step, for its exact float comparisons
        self.queue = RigidBodyQueue(form.layout, form.dtype, seed)
        if initial is not None and len(initial) and form.online_starts_from == "offline":
            self.queue = RigidBodyQueue.from_weights(initial, form.dtype, seed)
        self.residual = NumpyResidual(self.queue.to_weights()) if len(self.queue) else None
        self._rng = np.random.default_rng(seed)
        self._rows: list[np.ndarray] = []
        self._window = 0
        self._pending: tuple[NumpyResidual, int] | None = None
        self.rounds: list[RoundRecord] = []

    def before_tick(self, t: float) -> None:
        pass

    def after_tick(self, t: float) -> None:
        if self._pending is not None and t > 0.0:
            self.residual, index = self._pending
            self._pending = None
            # It drives the control from the next tick on.
            self.rounds[index] = replace(self.rounds[index], swap=t + 1.0 / self.protocol.control_hz)

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        form = self.form
        if not step * self.dt > form.collect_from:
            return
        self._rows.append(np.concatenate((x_after, u)))
        if step * self.dt > (self._window + 1) * form.t_col + form.collect_from:
            self._train(step)
            self._rows = []
            self._window += 1

    def _train(self, step: int) -> None:
        form = self.form
        rows = np.asarray(self._rows)
        if form.noise_std > 0.0:
            rows = rows + form.noise_std * self._rng.standard_normal(rows.shape)
        if form.misaligned_pairs:
            pairs = OneStepPairs.from_paper_rows(rows)
        else:  # rows hold x after each step: pair x_{k+1} with u_{k+1} -> x_{k+2}
            pairs = OneStepPairs(np.concatenate((rows[:-1, :13], rows[1:, 13:]), axis=1), rows[1:, :13])
        start = time.perf_counter()
        self.queue.push()
        stats = train_newest(self.queue, pairs, form.online, self.phys)
        self._pending = (NumpyResidual(self.queue.to_weights()), len(self.rounds))
        wall = time.perf_counter() - start
        t_end = (step + 1) * self.dt
        self.rounds.append(RoundRecord(t_end, t_end, t_end, math.nan, wall, len(pairs), stats.loss_first, stats.loss_last, True))


@dataclass
class _Job:
    ready: float
    candidate: RigidBodyQueue | None  # None: rejected by the gate
    index: int


class LatencyLearner:
    """cfknode's online loop with honest latency, simulated exactly in the lockstep harness.

    Aligned samples (x_k, u_k) -> x_{k+1} are cut into windows of ``t_col``.  A finished
    window goes to the trainer as soon as it is free; training starts at max(window end,
    trainer free), and its result is usable at start + the measured training wall time.
    A candidate (warm-started copy of the newest network) must beat the model in use on
    the window's held-out tail; accepted ones are swapped in at the next tick.  The window
    being collected at a swap is discarded, so every window was flown under one model.

    With ``monitor``, every tick also checks the model in use on the samples flown since the
    previous tick: when it predicts them worse than the nominal model (the world changed
    under it, e.g. a second mass change) by ``monitor_margin``, the MPC drops to the nominal model until the next
    accepted candidate; that is a controller change too, so the window restarts.
    """

    def __init__(
        self, protocol: PaperProtocol, form: Formulation, initial: QueueWeights | None, seed: int,
        fixed_latency: float | None = None,
    ) -> None:
        self.protocol = protocol
        self.form = form
        self.phys = _physics(protocol.vehicle)
        self.dt = protocol.plant_dt
        self.window_steps = int(round(form.t_col * protocol.plant_hz))
        self.fixed_latency = fixed_latency  # tests: a deterministic stand-in for the wall time
        self.queue = RigidBodyQueue(form.layout, form.dtype, seed)
        if initial is not None and len(initial) and form.online_starts_from == "offline":
            self.queue = RigidBodyQueue.from_weights(initial, form.dtype, seed)
        self.residual = NumpyResidual(self.queue.to_weights()) if len(self.queue) else None
        self._states: list[np.ndarray] = []
        self._inputs: list[np.ndarray] = []
        self._waiting: tuple[OneStepPairs, float] | None = None
        self._job: _Job | None = None
        self._free_at = -math.inf
        self._nominal = RigidBodyQueue(form.layout, form.dtype)  # empty: scores the nominal model
        self._recent: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # steps since the last tick
        self.rounds: list[RoundRecord] = []
        self.drops: list[float] = []  # sim times the monitor dropped the model

    @property
    def _active(self) -> RigidBodyQueue:
        """The model the MPC flies: the queue, or nominal after a monitor drop."""
        return self.queue if self.residual is not None else self._nominal

    def before_tick(self, t: float) -> None:
        recent, self._recent = self._recent, []
        job = self._job
        if job is not None and t >= job.ready - 1e-12:
            self._job = None
            if job.candidate is not None:
                self.queue = job.candidate
                self.residual = NumpyResidual(self.queue.to_weights())
                self.rounds[job.index] = replace(self.rounds[job.index], swap=t)
                self._restart_window()
                return
        if self.form.monitor and self.residual is not None and len(recent) >= 5:
            pairs = OneStepPairs(
                np.array([np.concatenate((x, u)) for x, u, _ in recent]), np.array([x1 for _, _, x1 in recent])
            )
            h = self.form.online.h
            err_model = residual_error(self.queue, pairs, h, self.phys)
            if err_model > self.form.monitor_margin * residual_error(self._nominal, pairs, h, self.phys):
                self.residual = None
                self.drops.append(t)
                self._restart_window()

    def _restart_window(self) -> None:
        if self.form.restart_window_on_swap:
            self._states, self._inputs = [], []

    def after_tick(self, t: float) -> None:
        pass

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        t_after = (step + 1) * self.dt
        if self.form.monitor:
            self._recent.append((x_before.copy(), np.asarray(u, dtype=float).copy(), x_after.copy()))
        if t_after <= self.form.collect_from + 1e-12:
            return
        if not self._states:
            self._states.append(x_before.copy())
        self._inputs.append(np.asarray(u, dtype=float).copy())
        self._states.append(x_after.copy())
        if len(self._inputs) >= self.window_steps:
            self._waiting = (OneStepPairs.aligned(np.asarray(self._states), np.asarray(self._inputs)), t_after)
            self._states, self._inputs = [], []
        if self._waiting is not None and self._job is None and t_after >= self._free_at - 1e-12:
            self._train(t_after)

    def _train(self, now: float) -> None:
        form = self.form
        pairs, t_end = self._waiting
        self._waiting = None
        start_sim = max(t_end, self._free_at)
        train, val = pairs.split(form.validation_fraction) if form.validation_fraction > 0 else (pairs, pairs)
        t0 = time.perf_counter()
        candidate = copy.deepcopy(self.queue)
        candidate.push(copy_from_newest=form.warm_start)
        stats = train_newest(candidate, train, form.online, self.phys)
        if form.output_ridge > 0.0:
            fit_output_layer(candidate, train, form.online.h, self.phys, form.output_ridge)
        val_new = residual_error(candidate, val, form.online.h, self.phys)
        val_cur = residual_error(self._active, val, form.online.h, self.phys)
        bounded = _bounded(candidate, pairs, form.residual_bound)
        accepted = bool(math.isfinite(val_new) and val_new < val_cur and bounded)
        wall = time.perf_counter() - t0
        latency = wall if self.fixed_latency is None else self.fixed_latency
        ready = start_sim + latency
        self._free_at = ready
        index = len(self.rounds)
        self.rounds.append(
            RoundRecord(t_end, start_sim, ready, math.nan, wall, len(train), stats.loss_first, stats.loss_last,
                        accepted, val_new, val_cur)
        )
        self._job = _Job(ready, candidate if accepted else None, index)


def _bounded(queue: RigidBodyQueue, pairs: OneStepPairs, bound: float) -> bool:
    with torch.no_grad():
        r = queue.residual(torch.as_tensor(pairs.z0, dtype=queue.dtype))
    return bool(torch.isfinite(r).all() and float(r.abs().max()) < bound)


# --- offline training ------------------------------------------------------------------------


def train_offline(
    form: Formulation, states: np.ndarray, inputs: np.ndarray, vehicle: CrazyflieParams, seed: int
) -> tuple[QueueWeights, float]:
    """One network trained on a recorded run: states (m+1, 13), inputs (m, 4) held per step.

    The paper formulation pairs the data as the original does (rows [x_{k+1}, u_k], noise).
    Returns the weights and the training wall time.
    """
    queue = RigidBodyQueue(form.layout, form.dtype, seed)
    if form.misaligned_pairs:
        rows = np.concatenate((states[1:], inputs), axis=1)
        if form.noise_std > 0.0:
            rows = rows + form.noise_std * np.random.default_rng(seed).standard_normal(rows.shape)
        pairs = OneStepPairs.from_paper_rows(rows)
    else:
        pairs = OneStepPairs.aligned(states, inputs)
    queue.push()
    stats = train_newest(queue, pairs, form.offline, _physics(vehicle))
    return queue.to_weights(), stats.wall_time


__all__ = [
    "CONTROLLERS",
    "ControllerKind",
    "Formulation",
    "GeometricController",
    "GeometricGains",
    "LatencyLearner",
    "LockstepLearner",
    "NoLearner",
    "RoundRecord",
    "model_hover_thrust",
    "mpc_reference",
    "train_offline",
]
