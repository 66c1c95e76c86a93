"""The 400 Hz flight loop: mocap -> estimator -> MPC -> Mellinger layer -> radio, every tick.

The loop is the only asyncio code on the flight path: it awaits the clock between
ticks (lockstep sim or wall time) and does the compute synchronously, so a tick's
measured compute time is the real cost of estimator + MPC + Mellinger + bookkeeping.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from cfknode.config import ControllerConfig, VehicleConfig
from cfknode.flight.clock import Clock
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.flight.geometric import GeometricGains, geometric_acc
from cfknode.flight.mellinger import AttitudeSetpoint, acc_to_setpoint
from cfknode.flight.model_slot import ModelSlot, linearisation_points
from cfknode.flight.trajectory import Trajectory
from cfknode.mocap.source import PoseSource

MOTORS_OFF = AttitudeSetpoint(0.0, 0.0, 0.0, 0)
# After the landing reference reaches the ground, motors are cut and zeros streamed
# this long before the radio's shutdown sequence hands the firmware back.
CUTOFF_HOLD_S = 0.2


class Radio(Protocol):
    def set_setpoint(self, sp: AttitudeSetpoint) -> None: ...

    def set_extpose(self, position: np.ndarray, quaternion: np.ndarray) -> None: ...

    def pump(self, now: float) -> None: ...


class Controller(Protocol):
    def solve(self, x0: np.ndarray, ref: Any, residual: Any = None) -> Any: ...


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


@dataclass(frozen=True)
class TickInfo:
    """What one tick saw and decided, for observers (training recorder, dashboard status)."""

    t: float
    est: StateEstimate | None
    ref_p: np.ndarray
    ref_v: np.ndarray
    acc: np.ndarray  # commanded world acceleration (the model's input u)
    setpoint: AttitudeSetpoint
    source: str  # "mpc" | "fallback" | "geometric" | "cutoff" | "no_state"
    compute_s: float
    solve_s: float
    missed: bool
    model_version: int


class TickObserver(Protocol):
    def on_tick(self, tick: TickInfo) -> None: ...


@dataclass
class FlightParts:
    clock: Clock
    mocap: PoseSource
    estimator: VelocityEstimator
    trajectory: Trajectory
    mpc: Controller | None  # None flies the geometric controller alone
    radio: Radio
    log: Log
    vehicle: VehicleConfig
    controller: ControllerConfig
    truth: Callable[[], np.ndarray] | None = None  # simulator's true 13-state, for logs and MSE
    model: ModelSlot | None = None  # KNODE residual for the MPC; None flies the nominal model
    observers: list[TickObserver] = field(default_factory=list)


@dataclass
class FlightRecord:
    """Per-tick arrays for the summary (the log holds the same, and more)."""

    t: np.ndarray
    p: np.ndarray  # true position in simulation, else the estimate
    p_ref: np.ndarray
    compute_s: np.ndarray
    solve_s: np.ndarray
    missed: np.ndarray
    mpc_ok: np.ndarray
    ticks: int = 0
    fallbacks: int = 0
    no_state_ticks: int = 0
    wall_time: float = 0.0
    events: list[str] = field(default_factory=list)

    @classmethod
    def empty(cls, n: int) -> "FlightRecord":
        return cls(
            t=np.zeros(n),
            p=np.zeros((n, 3)),
            p_ref=np.zeros((n, 3)),
            compute_s=np.zeros(n),
            solve_s=np.zeros(n),
            missed=np.zeros(n, dtype=bool),
            mpc_ok=np.zeros(n, dtype=bool),
        )

    def trimmed(self) -> "FlightRecord":
        n = self.ticks
        return FlightRecord(
            t=self.t[:n], p=self.p[:n], p_ref=self.p_ref[:n], compute_s=self.compute_s[:n],
            solve_s=self.solve_s[:n], missed=self.missed[:n], mpc_ok=self.mpc_ok[:n], ticks=n,
            fallbacks=self.fallbacks, no_state_ticks=self.no_state_ticks, wall_time=self.wall_time,
            events=self.events,
        )


async def fly(parts: FlightParts) -> FlightRecord:
    """Fly the whole trajectory, then cut the motors; returns the per-tick record."""
    ctrl, traj = parts.controller, parts.trajectory
    period = 1.0 / ctrl.rate_hz
    horizon_offsets = ctrl.dt * np.arange(ctrl.horizon + 1)
    n_ticks = int(np.ceil((traj.duration + CUTOFF_HOLD_S) / period)) + 1
    rec = FlightRecord.empty(n_ticks)
    gains = GeometricGains.from_config(ctrl, parts.vehicle)
    acc_prev = np.zeros(3)
    prev: _Previous = _Previous()
    last_pose_t = -np.inf
    wall_start = time.perf_counter()
    k = 0
    while k < n_ticks:
        t_tick = k * period
        await parts.clock.sleep_until(t_tick)
        start = time.perf_counter()
        now = parts.clock.now()

        pose = parts.mocap.latest(now)
        if pose is not None and pose.t > last_pose_t:
            last_pose_t = pose.t
            parts.estimator.update(pose)
            parts.radio.set_extpose(pose.position, pose.quaternion)
            parts.log.write("/mocap", now, {"p": pose.position, "q": pose.quaternion, "received": True, "stamp": pose.t})
        est = parts.estimator.predict(now, acc_prev)
        ref = traj.sample(now + horizon_offsets)

        solve_s, ok = 0.0, False
        if now >= traj.duration:
            sp, source = MOTORS_OFF, "cutoff"
        elif est is None:
            # No pose yet: stay on the ground rather than fly blind.
            sp, source = MOTORS_OFF, "no_state"
            rec.no_state_ticks += 1
        else:
            acc, ok, solve_s, source = _control(parts, est, ref, gains, prev)
            if not ok:
                rec.fallbacks += 1
            acc_prev = acc
            sp = acc_to_setpoint(acc, float(ref.yaw[0]), est.q, parts.vehicle, ctrl)
        parts.radio.set_setpoint(sp)
        parts.radio.pump(now)
        compute = time.perf_counter() - start

        missed = compute > period or (not parts.clock.lockstep and parts.clock.now() > t_tick + period)
        truth = parts.truth() if parts.truth is not None else None
        p_now = truth[:3] if truth is not None else (est.p if est is not None else np.full(3, np.nan))
        i = rec.ticks
        rec.t[i], rec.p[i], rec.p_ref[i] = now, p_now, ref.p[0]
        rec.compute_s[i], rec.solve_s[i], rec.missed[i], rec.mpc_ok[i] = compute, solve_s, missed, ok
        rec.ticks += 1
        _log_tick(parts.log, now, est, truth, ref, sp, acc_prev, source, compute, solve_s, missed, ok)
        if parts.observers:
            version = parts.model.version if parts.model is not None else 0
            info = TickInfo(now, est, ref.p[0], ref.v[0], acc_prev, sp, source, compute, solve_s, missed, version)
            for observer in parts.observers:
                observer.on_tick(info)

        k += 1
        if not parts.clock.lockstep:
            # On a wall clock a late tick is skipped, not queued: the next tick is the next slot ahead.
            k = max(k, int(parts.clock.now() / period) + 1)
    rec.wall_time = time.perf_counter() - wall_start
    return rec.trimmed()


@dataclass
class _Previous:
    """The last MPC solution: the RTI linearisation points for this tick's residual."""

    x_pred: np.ndarray | None = None
    u_pred: np.ndarray | None = None


def _control(
    parts: FlightParts, est: StateEstimate, ref: Any, gains: GeometricGains, prev: _Previous
) -> tuple[np.ndarray, bool, float, str]:
    """Acceleration command for this tick: the MPC, or the geometric controller when it fails."""
    if parts.mpc is not None:
        x0 = np.concatenate((est.p, est.v))
        residual = None
        if parts.model is not None:
            residual = parts.model.residual(*linearisation_points(x0, ref.a, prev.x_pred, prev.u_pred))
        sol = parts.mpc.solve(x0, ref, residual)
        prev.x_pred, prev.u_pred = (sol.x_pred, sol.u_pred) if sol.ok else (None, None)
        if sol.ok:
            return sol.acc, True, sol.solve_time, "mpc"
        fallback_source = "fallback"
    else:
        fallback_source = "geometric"
    acc = geometric_acc(est.p, est.v, ref.p[0], ref.v[0], ref.a[0], gains)
    return acc, parts.mpc is None, 0.0, fallback_source


def _log_tick(
    log: Log,
    now: float,
    est: StateEstimate | None,
    truth: np.ndarray | None,
    ref: Any,
    sp: AttitudeSetpoint,
    acc: np.ndarray,
    source: str,
    compute: float,
    solve_s: float,
    missed: bool,
    ok: bool,
) -> None:
    if est is not None:
        state: dict[str, Any] = {"p": est.p, "v": est.v, "q": est.q}
        if truth is not None:
            state["p_true"] = truth[:3]
            state["v_true"] = truth[3:6]
        log.write("/state", now, state)
    log.write("/reference", now, {"p": ref.p[0], "v": ref.v[0], "a": ref.a[0], "yaw": float(ref.yaw[0])})
    log.write(
        "/command",
        now,
        {
            "acc": acc,
            "roll_deg": sp.roll_deg,
            "pitch_deg": sp.pitch_deg,
            "yawrate_deg": sp.yawrate_deg,
            "thrust": sp.thrust,
            "source": source,
        },
    )
    log.write("/tick", now, {"compute_s": compute, "solve_s": solve_s, "missed": missed, "mpc_ok": ok})
