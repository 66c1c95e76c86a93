"""The 400 Hz flight loop: mocap -> estimator -> supervisor -> MPC -> Mellinger layer -> supervisor -> radio.

The loop is the only asyncio code on the flight path: it awaits the clock between
ticks (lockstep sim or wall time) and does the compute synchronously, so a tick's
measured compute time is the real cost of estimator + MPC + Mellinger + safety + bookkeeping.

The safety supervisor owns the radio: ``FlightParts`` has none, so poses and setpoints reach
the drone only through ``supervisor.accept_pose`` and ``supervisor.send``. The supervisor
also decides what each tick flies (``plan``) and when the flight is over (``finished``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from cfknode.flight.controller import Controller, TickInfo, TickObserver
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.flight.tick_guard import GuardedLog, GuardedObserver, fallback_command, hold_reference
from cfknode.kernel.clock import Clock
from cfknode.kernel.imu import ImuSource
from cfknode.kernel.reference import RefSamples, Reference
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.mocap.source import PoseSource
from cfknode.safety.operator import EstopMailbox, estop_watch, stop_signal_handler
from cfknode.safety.supervisor import BLIND, ERROR_LAND, ERROR_RECORD, ERROR_STOP, FLY, MOTORS_OFF, Supervisor

__all__ = ["FlightParts", "FlightRecord", "Log", "TickInfo", "TickObserver", "fly"]


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


@dataclass
class FlightParts:
    clock: Clock
    mocap: PoseSource
    estimator: VelocityEstimator
    trajectory: Reference
    controller: Controller  # the control law: MPC (with its model slot) or geometric, and the Mellinger layer
    supervisor: Supervisor  # owns the radio: the loop's only way to the drone
    log: Log
    truth: Callable[[], np.ndarray] | None = None  # simulator's true 13-state, for logs and MSE
    observers: list[TickObserver] = field(default_factory=list)
    estop: EstopMailbox | None = None  # where `cfknode estop` reaches this flight
    imu: ImuSource | None = None  # the vehicle's accelerometer: its newest sample goes into each tick's estimate
    signals: bool = True  # route stop signals to this flight's supervisor (a fleet routes them itself, to all)


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
    fallback_reasons: dict[str, int] = field(default_factory=dict)  # MPC status -> ticks
    no_state_ticks: int = 0
    wall_time: float = 0.0
    events: list[str] = field(default_factory=list)
    adaptation: dict[str, Any] = field(default_factory=dict)  # fast adaptation's end state, for the summary

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
            fallbacks=self.fallbacks, fallback_reasons=self.fallback_reasons, no_state_ticks=self.no_state_ticks,
            wall_time=self.wall_time, events=self.events, adaptation=self.adaptation,
        )

    def ensure_room(self) -> None:
        """Double the arrays when full: a supervisor landing can outlast the planned flight."""
        n = len(self.t)
        if self.ticks < n:
            return
        for name in ("t", "p", "p_ref", "compute_s", "solve_s", "missed", "mpc_ok"):
            old = getattr(self, name)
            new = np.zeros((2 * n, *old.shape[1:]), dtype=old.dtype)
            new[:n] = old
            setattr(self, name, new)


async def fly(parts: FlightParts) -> FlightRecord:
    """Fly the trajectory until the supervisor has cut the motors; returns the per-tick record.

    Stop signals go to the supervisor while the flight runs (from a relay thread, so also while
    this thread is stuck): the first SIGINT, SIGTERM or SIGHUP lands, the second stops the motors. The e-stop mailbox is open for ``cfknode estop``
    for the same span.

    No exception from a part ends the loop: the supervisor logs it once, with its traceback
    (``Supervisor.internal_error``), and the loop degrades. The controller (MPC, model) raising
    flies the geometric fallback from then on and lands; the trajectory raising holds position
    and lands; mocap raising lands; the estimator or the fallback raising stops the motors;
    an observer raising is detached; a log write raising is dropped. The clock (the simulator
    in lockstep) or the supervisor itself raising stops the motors and ends the loop at once:
    the radio's hand-back then cuts them.
    """
    controller, traj, sup = parts.controller, parts.trajectory, parts.supervisor
    period = 1.0 / controller.settings.rate_hz
    rec = FlightRecord.empty(int(np.ceil((traj.duration + 0.5) / period)) + 1)
    acc_prev = np.zeros(3)
    last_pose_t = -np.inf
    wall_start = time.perf_counter()
    k = 0

    def fault(part: str, exc: BaseException, action: str) -> None:
        try:
            sup.internal_error(part, exc, action)
        except Exception:  # noqa: BLE001 - the supervisor could not even record it: nothing more to do here
            pass

    def detached(part: str, exc: BaseException) -> None:
        fault(part, exc, ERROR_RECORD)

    log = parts.log if isinstance(parts.log, GuardedLog) else GuardedLog(parts.log)
    log.report_to(detached)
    observers = [GuardedObserver(o, detached) for o in parts.observers]
    inner_observers = list(controller.observers)
    controller.observers[:] = [GuardedObserver(o, detached) for o in inner_observers]
    controller_failed = estimator_failed = False
    imu = parts.imu
    logs_imu = imu is not None  # a flight with an IMU logs what each tick saw of it, NaN for nothing yet
    held: RefSamples | None = None  # the hold reference once the trajectory has raised
    try:
        signals = stop_signal_handler(sup) if parts.signals else contextlib.nullcontext(False)
        with signals, estop_watch(sup, parts.estop):
            while not sup.finished:
                t_tick = k * period
                try:
                    await parts.clock.sleep_until(t_tick)
                    now = parts.clock.now()
                except Exception as exc:  # noqa: BLE001 - time no longer advances: stop and leave
                    fault("the clock (the simulator in lockstep)", exc, ERROR_STOP)
                    break
                # Read before the tick's timer starts: in lockstep the radio waits here for the simulator's
                # log packets to cross cflib's thread, which is the simulation's time, not the tick's.
                imu_sample = None
                if imu is not None:
                    try:
                        imu_sample = imu.latest(now)
                    except Exception as exc:  # noqa: BLE001 - fly on without it, as a flight with no IMU
                        imu = None
                        fault("the IMU source", exc, ERROR_RECORD)
                start = time.perf_counter()
                try:
                    pose = parts.mocap.latest(now)
                except Exception as exc:  # noqa: BLE001
                    fault("the mocap source", exc, ERROR_LAND)
                    pose = None
                try:
                    fresh = pose is not None and pose.t > last_pose_t and sup.accept_pose(now, pose)
                    if pose is not None:
                        last_pose_t = max(last_pose_t, pose.t)
                except Exception as exc:  # noqa: BLE001
                    fault("the supervisor", exc, ERROR_STOP)
                    break
                est = None
                if not estimator_failed:
                    try:
                        if fresh:
                            parts.estimator.update(pose)
                        est = parts.estimator.predict(now, acc_prev)
                    except Exception as exc:  # noqa: BLE001 - no state to fly on, not even the fallback's
                        estimator_failed = True
                        fault("the estimator", exc, ERROR_STOP)
                        est = None
                if est is not None and imu is not None:
                    est = dataclasses.replace(est, imu=imu_sample)
                if fresh:
                    log.write("/mocap", now, {"p": pose.position, "q": pose.quaternion, "received": True,
                                              "stamp": pose.t})
                times = controller.preview_times(now)
                if held is None:
                    try:
                        samples = traj.sample(times)
                    except Exception as exc:  # noqa: BLE001
                        fault("the trajectory", exc, ERROR_LAND)
                        where = est.p if est is not None else rec.p_ref[max(rec.ticks - 1, 0)]
                        held = hold_reference(times - now, where)
                if held is not None:
                    samples = RefSamples(held.t + now, held.p, held.v, held.a, held.yaw)
                try:
                    action, ref, source = sup.plan(now, est, samples)
                except Exception as exc:  # noqa: BLE001
                    fault("the supervisor", exc, ERROR_STOP)
                    break

                solve_s, ok, status = 0.0, False, ""
                command = None
                sp = MOTORS_OFF
                if action is FLY and est is not None:
                    command = None
                    if not controller_failed:
                        try:
                            plan_est, plan_ref, delay = est, ref, parts.estimator.command_path.delay
                            if delay > 0.0:
                                # Plan from where the vehicle will be when this command acts (flight/latency.py);
                                # a reference the supervisor replaced (landing, fence) is flown as it is.
                                plan_est = parts.estimator.command_path.ahead(est)
                                if ref is samples and held is None:
                                    plan_ref = traj.sample(controller.preview_times(now + delay))
                            command = controller.step(now, plan_est, plan_ref, pose_fresh=fresh,
                                                      phase=sup.state.value)
                            if controller.adaptation is not None:
                                log.write("/adaptation", now, controller.adaptation.log())
                        except Exception as exc:  # noqa: BLE001 - the MPC, the model or the law: fly the fallback
                            controller_failed = True
                            fault("the controller", exc, ERROR_LAND)
                    if command is None:
                        try:
                            command = fallback_command(controller, est, ref, "error")
                        except Exception as exc:  # noqa: BLE001
                            fault("the geometric fallback", exc, ERROR_STOP)
                    if command is not None:
                        ok, solve_s, source, status = command.ok, command.solve_s, command.source, command.status
                        if source == "fallback":
                            rec.fallbacks += 1
                            rec.fallback_reasons[status] = rec.fallback_reasons.get(status, 0) + 1
                        acc_prev, sp = command.acc, command.setpoint
                    else:
                        source = "stop"
                elif action is BLIND:
                    sp, acc_prev = sup.blind_setpoint, sup.blind_acc
                    if not controller_failed:
                        controller.reset()  # the last solution is stale once flying blind
                else:
                    if not controller_failed:
                        controller.idle()
                    if source == "no_state":
                        rec.no_state_ticks += 1
                try:
                    sp = sup.send(now, sp)
                    parts.estimator.command_path.note(now, acc_prev)
                except Exception as exc:  # noqa: BLE001
                    fault("the supervisor", exc, ERROR_STOP)
                    break
                compute = time.perf_counter() - start

                missed = compute > period or (not parts.clock.lockstep and parts.clock.now() > t_tick + period)
                try:
                    sup.after_tick(now, source == "fallback", status, missed)
                except Exception as exc:  # noqa: BLE001
                    fault("the supervisor", exc, ERROR_STOP)
                    break
                truth = None
                if parts.truth is not None:
                    try:
                        truth = parts.truth()
                    except Exception as exc:  # noqa: BLE001
                        fault("the simulator's true state", exc, ERROR_RECORD)
                p_now = truth[:3] if truth is not None else (est.p if est is not None else np.full(3, np.nan))
                rec.ensure_room()
                i = rec.ticks
                rec.t[i], rec.p[i], rec.p_ref[i] = now, p_now, ref.p[0]
                rec.compute_s[i], rec.solve_s[i], rec.missed[i], rec.mpc_ok[i] = compute, solve_s, missed, ok
                rec.ticks += 1
                try:
                    _log_tick(log, now, est, truth, ref, sp, acc_prev, source, compute, solve_s, missed, ok,
                              status if source == "fallback" else "", fresh, sup.state.value, logs_imu)
                except Exception as exc:  # noqa: BLE001 - building the messages, not writing them
                    fault("the flight log (tick messages)", exc, ERROR_RECORD)
                model = controller.model
                version = model.version if model is not None else 0  # the model this tick flew, before any swap
                if action is FLY and not controller_failed:
                    try:
                        controller.publish(compute_s=compute, missed=missed, supervisor_state=sup.state.value)
                    except Exception as exc:  # noqa: BLE001
                        fault("the controller's observers", exc, ERROR_RECORD)
                if observers:
                    saturated = action is FLY and command is not None and command.saturated
                    info = TickInfo(now, est, ref.p[0], ref.v[0], acc_prev, sp, source, compute, solve_s, missed,
                                    version, sup.state.value, saturated)
                    for observer in observers:
                        observer.on_tick(info)

                k += 1
                if not parts.clock.lockstep:
                    # On a wall clock a late tick is skipped, not queued: the next tick is the next slot ahead.
                    k = max(k, int(parts.clock.now() / period) + 1)
    finally:
        controller.observers[:] = inner_observers
    rec.wall_time = time.perf_counter() - wall_start
    rec.events = list(sup.events)
    if controller.adaptation is not None:
        rec.adaptation = controller.adaptation.summary()
    return rec.trimmed()


_NAN = float("nan")
_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False


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
    status: str = "",
    fresh: bool = True,
    phase: str = "",
    logs_imu: bool = False,
) -> None:
    if est is not None:
        # fresh, phase and the newest frame are what the fast layer read this tick: replay feeds them back.
        state: dict[str, Any] = {"p": est.p, "v": est.v, "q": est.q, "fresh": bool(fresh), "phase": phase}
        if est.frame is not None:
            state["frame_t"], state["frame_p"] = est.frame
        if logs_imu:
            imu = est.imu
            state["imu_t"] = imu.t if imu is not None else _NAN
            state["imu_f"] = imu.specific_force if imu is not None else _NAN3
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
    tick: dict[str, Any] = {"compute_s": compute, "solve_s": solve_s, "missed": missed, "mpc_ok": ok}
    if status:
        tick["status"] = status  # why the MPC was not used (fallback ticks only)
    log.write("/tick", now, tick)
