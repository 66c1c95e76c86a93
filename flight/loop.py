"""The 400 Hz flight loop: mocap -> estimator -> supervisor -> MPC -> Mellinger layer -> supervisor -> radio.

The loop is the only asyncio code on the flight path: it awaits the clock between
ticks (lockstep sim or wall time) and does the compute synchronously, so a tick's
measured compute time is the real cost of estimator + MPC + Mellinger + safety, from the pose's read to
the send. The log, the observers and the controller's preparation of the next tick follow the send.

The safety supervisor owns the radio: ``FlightParts`` has none, so poses and setpoints reach
the drone only through ``supervisor.accept_pose`` and ``supervisor.send``. The supervisor
also decides what each tick flies (``plan``) and when the flight is over (``finished``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from cfknode.flight.controller import Controller, TickInfo, TickObserver
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.flight.tick_guard import GuardedLog, GuardedObserver, fallback_command, hold_reference
from cfknode.flight.tick_log import Log, TickLogged, log_tick
from cfknode.kernel.clock import Clock
from cfknode.kernel.imu import ImuSource
from cfknode.kernel.reference import RefSamples, Reference, sample_twice
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.mocap.source import PoseSource
from cfknode.safety.operator import EstopMailbox, estop_watch, stop_signal_handler
from cfknode.safety.supervisor import BLIND, ERROR_LAND, ERROR_RECORD, ERROR_STOP, FLY, MOTORS_OFF, Supervisor

__all__ = ["FlightParts", "FlightRecord", "Log", "TickInfo", "TickObserver", "fly"]


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
    missed: np.ndarray  # the tick's command was sent after its slot ended
    mpc_ok: np.ndarray
    skipped: np.ndarray  # slots passed over before the tick (wall clock): each a deadline missed with no command
    ticks: int = 0
    fallbacks: int = 0
    fallback_reasons: dict[str, int] = field(default_factory=dict)  # MPC status -> ticks
    no_state_ticks: int = 0
    wall_time: float = 0.0
    loop_cpu_s: float = 0.0  # CPU time of the loop's thread over the flight (wall_time less it: waits, preemption)
    events: list[str] = field(default_factory=list)
    adaptation: dict[str, Any] = field(default_factory=dict)  # fast adaptation's end state, for the summary

    @classmethod
    def empty(cls, n: int) -> "FlightRecord":
        return cls(t=np.zeros(n), p=np.zeros((n, 3)), p_ref=np.zeros((n, 3)), compute_s=np.zeros(n),
                   solve_s=np.zeros(n), missed=np.zeros(n, dtype=bool), mpc_ok=np.zeros(n, dtype=bool),
                   skipped=np.zeros(n, dtype=int))

    def trimmed(self) -> "FlightRecord":
        n = self.ticks
        return FlightRecord(
            t=self.t[:n], p=self.p[:n], p_ref=self.p_ref[:n], compute_s=self.compute_s[:n],
            solve_s=self.solve_s[:n], missed=self.missed[:n], mpc_ok=self.mpc_ok[:n], skipped=self.skipped[:n],
            ticks=n,
            fallbacks=self.fallbacks, fallback_reasons=self.fallback_reasons, no_state_ticks=self.no_state_ticks,
            wall_time=self.wall_time, loop_cpu_s=self.loop_cpu_s, events=self.events, adaptation=self.adaptation,
        )

    def ensure_room(self) -> None:
        """Double the arrays when full: a supervisor landing can outlast the planned flight."""
        n = len(self.t)
        if self.ticks < n:
            return
        for name in ("t", "p", "p_ref", "compute_s", "solve_s", "missed", "mpc_ok", "skipped"):
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
    loop = _Loop(parts)
    sup = parts.supervisor
    try:
        signals = stop_signal_handler(sup) if parts.signals else contextlib.nullcontext(False)
        with signals, estop_watch(sup, parts.estop):
            while not sup.finished:
                try:
                    await loop.tick()
                except _Halt:
                    break
    finally:
        parts.controller.observers[:] = loop.inner_observers
        parts.controller.prepares_after_send = False
    return loop.finish()


class _Halt(Exception):
    """A part raised that leaves no safe way to go on: the fault is recorded, the loop ends."""


@dataclass
class _Tick:
    """What one tick read, planned and did, handed from step to step."""

    now: float
    t_tick: float
    skipped: int = 0  # slots passed over since the last tick (wall clock)
    start: float = 0.0  # perf_counter when the tick's compute began (after the IMU read)
    pose: Any = None
    fresh: bool = False
    est: StateEstimate | None = None
    action: Any = None
    ref: Any = None
    source: str = ""
    samples: RefSamples | None = None
    samples_ahead: RefSamples | None = None  # the reference a command delay later (a plan from the state ahead)
    command: Any = None
    sp: AttitudeSetpoint = MOTORS_OFF
    solve_s: float = 0.0
    ok: bool = False
    status: str = ""
    compute: float = 0.0
    missed: bool = False
    adapted: bool = False  # the control law stepped its fast layer: /adaptation is logged after the send


class _Loop:
    """The loop's state across ticks; each tick is read -> plan -> act -> record.

    A step that meets a fault it cannot degrade past raises ``_Halt`` (after recording it),
    which ends the loop as the ``break`` of a single loop body would.
    """

    def __init__(self, parts: FlightParts) -> None:
        self.parts = parts
        self.controller, self.traj, self.sup = parts.controller, parts.trajectory, parts.supervisor
        self.period = 1.0 / self.controller.settings.rate_hz
        self.rec = FlightRecord.empty(int(np.ceil((self.traj.duration + 0.5) / self.period)) + 1)
        self.acc_prev = np.zeros(3)
        self.last_pose_t = -np.inf
        self.wall_start = time.perf_counter()
        self.cpu_start = time.thread_time()
        self.k = 0
        self.skipped = 0  # slots passed over since the last tick (wall clock)
        self.log = parts.log if isinstance(parts.log, GuardedLog) else GuardedLog(parts.log)
        self.log.report_to(self.detached)
        self.observers = [GuardedObserver(o, self.detached) for o in parts.observers]
        self.inner_observers = list(self.controller.observers)
        self.controller.observers[:] = [GuardedObserver(o, self.detached) for o in self.inner_observers]
        self.controller.prepares_after_send, self.controller_failed, self.estimator_failed = True, False, False
        self.imu = parts.imu
        self.logs_imu = self.imu is not None  # a flight with an IMU logs what each tick saw of it, NaN for nothing yet
        self.held: RefSamples | None = None  # the hold reference once the trajectory has raised

    def fault(self, part: str, exc: BaseException, action: str) -> None:
        try:
            self.sup.internal_error(part, exc, action)
        except Exception:  # noqa: BLE001 - the supervisor could not even record it: nothing more to do here
            pass

    def detached(self, part: str, exc: BaseException) -> None:
        self.fault(part, exc, ERROR_RECORD)

    def halt(self, part: str, exc: BaseException) -> None:
        self.fault(part, exc, ERROR_STOP)
        raise _Halt(part)

    async def tick(self) -> None:
        t_tick = self.k * self.period
        try:
            await self.parts.clock.sleep_until(t_tick)
            now = self.parts.clock.now()
        except Exception as exc:  # noqa: BLE001 - time no longer advances: stop and leave
            self.halt("the clock (the simulator in lockstep)", exc)
        if self.rec.ticks == 0 and not self.parts.clock.lockstep:
            # A wall clock runs from before the loop starts: the first tick takes the slot it woke in.
            self.k = max(self.k, int(now / self.period))
            t_tick = self.k * self.period
        tick = _Tick(now, t_tick, self.skipped)
        self.read(tick)
        self.plan(tick)
        self.act(tick)
        self.record(tick)
        if self.parts.clock.lockstep:
            self.k += 1
        else:
            # On a wall clock ticks are never queued and a slot has one tick at most: a tick that ran into the
            # next slot starts that slot's tick late, inside its deadline; a slot already gone, or the one a
            # tick that woke late ran in, is passed over, a deadline missed (the next tick records it).
            started = max(self.k, int(now / self.period))
            slot = max(started + 1, int(self.parts.clock.now() / self.period))
            self.skipped, self.k = slot - self.k - 1, slot

    def read(self, tick: _Tick) -> None:
        """The IMU, the pose and the state estimate; starts the tick's timer."""
        parts, now = self.parts, tick.now
        # Read before the tick's timer starts: in lockstep the radio waits here for the simulator's
        # log packets to cross cflib's thread, which is the simulation's time, not the tick's.
        imu_sample = None
        if self.imu is not None:
            try:
                imu_sample = self.imu.latest(now)
            except Exception as exc:  # noqa: BLE001 - fly on without it, as a flight with no IMU
                self.imu = None
                self.fault("the IMU source", exc, ERROR_RECORD)
        tick.start = time.perf_counter()
        try:
            pose = parts.mocap.latest(now)
        except Exception as exc:  # noqa: BLE001
            self.fault("the mocap source", exc, ERROR_LAND)
            pose = None
        try:
            fresh = pose is not None and pose.t > self.last_pose_t and self.sup.accept_pose(now, pose)
            if pose is not None:
                self.last_pose_t = max(self.last_pose_t, pose.t)
        except Exception as exc:  # noqa: BLE001
            self.halt("the supervisor", exc)
        est = None
        if not self.estimator_failed:
            try:
                if fresh:
                    parts.estimator.update(pose)
                est = parts.estimator.predict(now, self.acc_prev)
            except Exception as exc:  # noqa: BLE001 - no state to fly on, not even the fallback's
                self.estimator_failed = True
                self.fault("the estimator", exc, ERROR_STOP)
                est = None
        if est is not None and self.imu is not None:
            est = dataclasses.replace(est, imu=imu_sample)
        if fresh:
            self.log.write("/mocap", now, {"p": pose.position, "q": pose.quaternion, "received": True,
                                           "stamp": pose.t})
        tick.pose, tick.fresh, tick.est = pose, fresh, est

    def plan(self, tick: _Tick) -> None:
        """The trajectory's preview (or the hold once it has raised) and the supervisor's choice."""
        now, est = tick.now, tick.est
        times, path = self.controller.preview_times(now), self.parts.estimator.command_path
        if self.held is None:
            try:
                later = self.controller.preview_times(now + path.delay) if path.active else None
                tick.samples, tick.samples_ahead = sample_twice(self.traj, times, later)
            except Exception as exc:  # noqa: BLE001
                self.fault("the trajectory", exc, ERROR_LAND)
                where = est.p if est is not None else self.rec.p_ref[max(self.rec.ticks - 1, 0)]
                self.held = hold_reference(times - now, where)
        if (held := self.held) is not None:
            tick.samples = RefSamples(held.t + now, held.p, held.v, held.a, held.yaw)
        try:
            tick.action, tick.ref, tick.source = self.sup.plan(now, est, tick.samples)
        except Exception as exc:  # noqa: BLE001
            self.halt("the supervisor", exc)

    def act(self, tick: _Tick) -> None:
        """The setpoint this tick flies, through the supervisor to the radio; stops the tick's timer."""
        if tick.action is FLY and tick.est is not None:
            self.command(tick)
        elif tick.action is BLIND:
            tick.sp, self.acc_prev = self.sup.blind_setpoint, self.sup.blind_acc
            if not self.controller_failed:
                self.controller.reset()  # the last solution is stale once flying blind
        else:
            if not self.controller_failed:
                self.controller.idle()
            if tick.source == "no_state":
                self.rec.no_state_ticks += 1
        try:
            tick.sp = self.sup.send(tick.now, tick.sp)
            self.parts.estimator.command_path.note(tick.now, self.acc_prev)
        except Exception as exc:  # noqa: BLE001
            self.halt("the supervisor", exc)
        tick.compute = time.perf_counter() - tick.start

    def command(self, tick: _Tick) -> None:
        """The control law's command, or the geometric fallback's once the law has raised."""
        controller, now, est, ref = self.controller, tick.now, tick.est, tick.ref
        command = None
        if not self.controller_failed:
            try:
                plan_est, plan_ref = self.ahead(tick) if self.parts.estimator.command_path.active else (est, ref)
                command = controller.step(now, plan_est, plan_ref, pose_fresh=tick.fresh, phase=self.sup.state.value,
                                          observed=est, brake_tilt_deg=self.sup.brake_tilt_deg)
                tick.adapted = controller.adaptation is not None
            except Exception as exc:  # noqa: BLE001 - the MPC, the model or the law: fly the fallback
                self.controller_failed = True
                self.fault("the controller", exc, ERROR_LAND)
        if command is None:
            try:
                command = fallback_command(controller, est, ref, "error")
            except Exception as exc:  # noqa: BLE001
                self.fault("the geometric fallback", exc, ERROR_STOP)
        tick.command = command
        if command is None:
            tick.source = "stop"
            return
        tick.ok, tick.solve_s, tick.source, tick.status = command.ok, command.solve_s, command.source, command.status
        if tick.source == "fallback":
            self.rec.fallbacks += 1
            self.rec.fallback_reasons[tick.status] = self.rec.fallback_reasons.get(tick.status, 0) + 1
        self.acc_prev, tick.sp = command.acc, command.setpoint

    def ahead(self, tick: _Tick) -> tuple[Any, Any]:
        """The state and reference the MPC plans from: where the vehicle will be when this command acts
        (flight/latency.py); a reference the supervisor replaced (landing, fence) is flown as it is."""
        path, now = self.parts.estimator.command_path, tick.now
        plan_est, plan_ref = path.ahead(tick.est), tick.ref
        if tick.ref is tick.samples and self.held is None and tick.samples_ahead is not None:
            plan_ref = tick.samples_ahead
            if path.delay_z != path.delay:  # z's reference over z's own delay (else its feed-forward acts early)
                z = tick.samples if not path.delay_z else self.traj.sample(
                    self.controller.preview_times(now + path.delay_z))
                plan_ref = dataclasses.replace(plan_ref, **{k: _with_z(getattr(plan_ref, k), getattr(z, k))
                                                            for k in ("p", "v", "a")})
        return plan_est, plan_ref

    def record(self, tick: _Tick) -> None:
        """The supervisor's view of the tick, the record, the log and the observers."""
        parts, sup, now, est = self.parts, self.sup, tick.now, tick.est
        period = self.period
        tick.missed = tick.compute > period or (not parts.clock.lockstep and parts.clock.now() > tick.t_tick + period)
        try:
            sup.after_tick(now, tick.source == "fallback", tick.status, tick.missed)
        except Exception as exc:  # noqa: BLE001
            self.halt("the supervisor", exc)
        truth = None
        if parts.truth is not None:
            try:
                truth = parts.truth()
            except Exception as exc:  # noqa: BLE001
                self.fault("the simulator's true state", exc, ERROR_RECORD)
        p_now = truth[:3] if truth is not None else (est.p if est is not None else np.full(3, np.nan))
        rec = self.rec
        rec.ensure_room()
        i = rec.ticks
        rec.t[i], rec.p[i], rec.p_ref[i] = now, p_now, tick.ref.p[0]
        rec.compute_s[i], rec.solve_s[i], rec.missed[i], rec.mpc_ok[i] = tick.compute, tick.solve_s, tick.missed, tick.ok
        rec.skipped[i] = tick.skipped
        rec.ticks += 1
        try:
            log_tick(self.log, TickLogged(
                now, est, truth, tick.ref, tick.sp, self.acc_prev, tick.source, tick.compute, tick.solve_s,
                tick.missed, tick.ok, tick.status if tick.source == "fallback" else "", tick.fresh,
                sup.state.value, self.logs_imu, tick.skipped))
        except Exception as exc:  # noqa: BLE001 - building the messages, not writing them
            self.fault("the flight log (tick messages)", exc, ERROR_RECORD)
        if tick.adapted:
            # Here, after the send, not in the tick's compute: bookkeeping never delays a setpoint, and the
            # layer's state is this tick's until its next step.
            try:
                self.log.write("/adaptation", now, self.controller.adaptation.log())  # type: ignore[union-attr]
            except Exception as exc:  # noqa: BLE001 - building the message, not writing it
                self.fault("the fast layer's log message", exc, ERROR_RECORD)
        self.observe(tick)

    def observe(self, tick: _Tick) -> None:
        """The controller's observers (learning, reports) and the flight's own."""
        controller, sup = self.controller, self.sup
        model = controller.model
        version = model.version if model is not None else 0  # the model this tick flew, before any swap
        if tick.action is FLY and not self.controller_failed:
            try:
                controller.publish(compute_s=tick.compute, missed=tick.missed, supervisor_state=sup.state.value)
            except Exception as exc:  # noqa: BLE001
                self.fault("the controller's observers", exc, ERROR_RECORD)
        if self.observers:
            flown = tick.command if tick.action is FLY else None
            ref = tick.ref
            info = TickInfo(tick.now, tick.est, ref.p[0], ref.v[0], self.acc_prev, tick.sp, tick.source,
                            tick.compute, tick.solve_s, tick.missed, version, sup.state.value,
                            flown is not None and flown.saturated, guarded=flown is not None and flown.guarded,
                            skipped=tick.skipped)
            for observer in self.observers:
                observer.on_tick(info)
        if tick.action is FLY and not self.controller_failed:
            try:  # the next tick's work that waits for no new pose, outside this tick's compute (controller.py)
                controller.prepare()
            except Exception as exc:  # noqa: BLE001 - the model's linearisation, as inside the tick
                self.controller_failed = True
                self.fault("the controller", exc, ERROR_LAND)

    def finish(self) -> FlightRecord:
        rec = self.rec
        rec.wall_time = time.perf_counter() - self.wall_start
        rec.loop_cpu_s = time.thread_time() - self.cpu_start
        rec.events = list(self.sup.events)
        if self.controller.adaptation is not None:
            rec.adaptation = self.controller.adaptation.summary()
        return rec.trimmed()


def _with_z(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``xy`` (n, 3) with the vertical column of ``z``."""
    out = np.array(xy, dtype=float)
    out[:, 2] = z[:, 2]
    return out
