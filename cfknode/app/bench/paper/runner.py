"""One closed-loop run of the paper's protocol: a controller, a formulation, a cell -> MSE and timings.

The loop is the authors' (docs/paper-code.md#online-loop, #plant and #metric): at plant step k
(t = k dt, 500 Hz) the controller acts every 25th step on the state at t with the reference
at t + dt, the rotors clip its output, the plant advances one step with it held, and mass
events apply after their step.  The metric pairs the state at t with the reference at
t + dt over all 4000 steps.  Everything is single-threaded and deterministic given the
seed, except the default formulation's swap times, which follow measured training wall
times (recorded in the result).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from cfknode.app.bench.paper.mpc_full import FullStateMpc
from cfknode.app.bench.paper.rigid_body_knode import NumpyResidual, QueueWeights
from cfknode.app.bench.paper.controllers import (
    ControllerKind,
    Formulation,
    GeometricController,
    LatencyLearner,
    LockstepLearner,
    NoLearner,
    RoundRecord,
    model_hover_thrust,
    mpc_reference,
    train_offline,
)
from cfknode.app.bench.paper.protocol import Actuators, ChordCircle, PaperPlant, PaperProtocol, per_axis_mse, position_mse

TRAJECTORY_EVERY = 10  # plant steps between stored trajectory samples (50 Hz) for plots


@dataclass(frozen=True)
class RunResult:
    formulation: str
    controller: str
    radius: float
    speed: float
    mse: float
    per_axis: tuple[float, float, float]
    wall_time: float  # s, the whole run
    sim_time: float  # s simulated
    solve_ms_median: float  # MPC solve wall time per tick (nan for geometric)
    solve_ms_p99: float
    iterations_mean: float
    failures: int  # ticks whose solve failed (the previous input was held)
    fallbacks: int  # ticks whose solve with the model failed and were re-solved without it
    rounds: tuple[RoundRecord, ...] = ()
    model_drops: tuple[float, ...] = ()  # sim times the default's monitor dropped a model for nominal
    training_wall: float = 0.0  # s of wall time spent training inside this run
    offline_train_wall: float = math.nan  # s, the offline model's training (knode_offline)
    trajectory: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)), repr=False)  # (t, x, y, z)

    @property
    def swaps(self) -> int:
        return sum(1 for r in self.rounds if math.isfinite(r.swap))


@dataclass(frozen=True)
class RecordedRun:
    """States (m + 1, 13) and the applied inputs (m, 4) of a run, for offline training."""

    states: np.ndarray
    inputs: np.ndarray


def simulate(
    protocol: PaperProtocol,
    form: Formulation,
    kind: ControllerKind,
    offline: QueueWeights | None = None,
    seed: int = 0,
    mpc: FullStateMpc | None = None,
    fixed_latency: float | None = None,
    record_from: float | None = None,
) -> tuple[RunResult, RecordedRun | None]:
    """Run one controller over the protocol.  ``record_from``: also return the (state, input)
    history of the steps starting after that time (the offline KNODE-MPC's data)."""
    if kind in ("knode_offline",) and offline is None:
        raise ValueError("knode_offline needs the offline model")
    wall0 = time.perf_counter()
    veh = protocol.vehicle
    plant = PaperPlant(protocol)
    circle = ChordCircle(protocol)
    act = Actuators(veh, protocol.rotors, reproduce_fallback=form.fallback_bug)
    steps, hold, dt = protocol.steps, protocol.hold, protocol.plant_dt
    uses_nn = kind in ("knode_offline", "knode_online")
    if kind != "geometric":
        if mpc is None or bool(mpc.spec.residual_rows) != uses_nn:
            mpc = FullStateMpc(form.mpc_spec(uses_nn))
        mpc.reset()
    learner = _learner(protocol, form, kind, offline, seed, fixed_latency)
    geo = GeometricController(veh) if kind == "geometric" else None

    ref_pos = circle.sample((np.arange(steps) + 1) * dt)[0]
    pos = np.empty((steps, 3))
    solve_ms: list[float] = []
    iterations: list[int] = []
    failures = 0
    fallbacks = 0
    u = np.zeros(4)
    rec_states: list[np.ndarray] = []
    rec_inputs: list[np.ndarray] = []
    for k in range(steps):
        t = k * dt
        x = plant.state
        if geo is not None:
            p_r, v_r = circle.sample(t + dt)
            u = act.apply(geo.command(x, p_r, v_r))
        elif k % hold == 0:
            learner.before_tick(t)
            mass = plant.mass if kind == "oracle" else veh.mass
            hover = model_hover_thrust(x, mass, veh.gravity, learner.residual, veh.max_thrust) if form.hover_input_ref else 0.0
            x_ref, u_ref = mpc_reference(form, circle, t, dt, hover)
            sol = mpc.solve(x, x_ref, u_ref, mass, learner.residual)
            if not sol.ok and form.nominal_on_failure and learner.residual is not None:
                fallbacks += 1
                sol = mpc.solve(x, x_ref, u_ref, mass, None)
            solve_ms.append(1e3 * sol.solve_time)
            iterations.append(sol.iterations)
            if sol.ok:
                u = act.apply(sol.u)
            else:
                failures += 1  # hold the previous rotor command
            learner.after_tick(t)
        pos[k] = x[:3]
        x_before = x.copy()
        x_after = plant.step(u)
        learner.observe(k, x_before, u, x_after)
        if record_from is not None and k * dt > record_from:
            if not rec_states:
                rec_states.append(x_before)
            rec_states.append(x_after.copy())
            rec_inputs.append(u.copy())
    recorded = RecordedRun(np.asarray(rec_states), np.asarray(rec_inputs)) if record_from is not None else None
    solves = _Solves(solve_ms, iterations, failures, fallbacks)
    return _run_result(protocol, form, kind, pos, ref_pos, solves, learner, wall0), recorded


def _learner(protocol: PaperProtocol, form: Formulation, kind: ControllerKind, offline: QueueWeights | None,
             seed: int, fixed_latency: float | None) -> NoLearner | LockstepLearner | LatencyLearner:
    """What learns (online kinds) or holds the fixed residual (offline) during one run."""
    if kind == "knode_online":
        if form.lockstep:
            return LockstepLearner(protocol, form, offline, seed)
        return LatencyLearner(protocol, form, offline, seed, fixed_latency)
    return NoLearner(NumpyResidual(offline) if kind == "knode_offline" and offline is not None else None)


@dataclass(frozen=True)
class _Solves:
    """One run's MPC solves: per-solve times (ms) and iterations, failures, nominal fallbacks."""

    solve_ms: list[float]
    iterations: list[int]
    failures: int
    fallbacks: int


def _run_result(protocol: PaperProtocol, form: Formulation, kind: ControllerKind, pos: np.ndarray,
                ref_pos: np.ndarray, solves: _Solves, learner: NoLearner | LockstepLearner | LatencyLearner,
                wall0: float) -> RunResult:
    steps, dt = protocol.steps, protocol.plant_dt
    sub = slice(0, steps, TRAJECTORY_EVERY)
    traj = np.column_stack((np.arange(steps)[sub] * dt, pos[sub]))
    ms = np.asarray(solves.solve_ms) if solves.solve_ms else np.full(1, math.nan)
    return RunResult(
        formulation=form.name,
        controller=kind,
        radius=protocol.radius,
        speed=protocol.speed,
        mse=position_mse(pos, ref_pos),
        per_axis=tuple(float(a) for a in per_axis_mse(pos, ref_pos)),
        wall_time=time.perf_counter() - wall0,
        sim_time=steps * dt,
        solve_ms_median=float(np.median(ms)),
        solve_ms_p99=float(np.percentile(ms, 99)),
        iterations_mean=float(np.mean(solves.iterations)) if solves.iterations else math.nan,
        failures=solves.failures,
        fallbacks=solves.fallbacks,
        rounds=tuple(learner.rounds),
        model_drops=tuple(getattr(learner, "drops", ())),
        training_wall=float(sum(r.wall_time for r in learner.rounds)),
        trajectory=traj,
    )


def offline_model(
    protocol: PaperProtocol, form: Formulation, seed: int = 0, mpc: FullStateMpc | None = None
) -> tuple[QueueWeights, float, float]:
    """The offline KNODE-MPC's model: fly the nominal MPC through the first mass change only,
    record everything after it, and train one network on that.

    Returns (weights, wall time of the data run, training wall time).
    """
    if not protocol.events:
        raise ValueError("the offline model needs a mass event to learn")
    first = protocol.events[0]
    data_protocol = replace(protocol, events=(first,))
    result, recorded = simulate(data_protocol, form, "mpc", seed=seed, mpc=mpc, record_from=first.time)
    assert recorded is not None
    weights, train_wall = train_offline(form, recorded.states, recorded.inputs, protocol.vehicle, seed)
    return weights, result.wall_time, train_wall


__all__ = ["RecordedRun", "RunResult", "offline_model", "simulate"]
