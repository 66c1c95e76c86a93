"""The per-tick control law as one object: ``Controller.step(t, state, reference) -> Command``.

It owns the MPC, the KNODE model slot, the warm start (the previous solution is the next
tick's linearisation point), the reference preview grid, the geometric fallback, deadline
handling and the Mellinger layer. The flight loop, replay, the benchmarks, fault injection
and other people's simulators all call it, so there is one copy of the law.

Observers (the online learner) see each tick once its command has gone out: the caller
calls ``publish()`` after sending; a caller that never does is covered by ``step``, which
publishes the previous tick first.

A tick splits as a real-time iteration does: a caller that sets ``prepares_after_send`` calls
``prepare()`` after each send, which does the next tick's work that waits for no new pose, so that the pose's
next command waits only for the solve. The fast layer learns from the pose just flown and records the command
sent; the model is linearised at the plan just solved; the MPC's residual is put together. The next command then
flies the layer's estimate from the pose before (2.5 ms older at 400 Hz), except where the layer must learn
first: an accelerometer sample that shows a step (or comes while one is tracked), a swapped model
(docs/design.md#the-tick-in-two-phases).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from cfknode.flight.adaptation import GROUND_MARGIN, AdaptationEstimate, AdaptationLayer, LoopAdaptation, OracleAdaptation
from cfknode.flight.fall_guard import FallGuard, FallGuardSettings, guard_acceleration
from cfknode.flight.geometric import GeometricGains, geometric_acc
from cfknode.flight.mellinger import CommandShaping, command_saturated, force_to_setpoint, shape_force
from cfknode.flight.model_slot import ModelSlot, PreparedResidual, linearisation_points, plan_nodes
from cfknode.flight.mpc_problem import MpcParameters, ResidualLinearisation
from cfknode.flight.settings import ControllerConfig
from cfknode.flight.solver_stats import SolverStats
from cfknode.kernel.reference import RefSamples
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.kernel.vehicle import VehicleConfig


GUESS_WARN_Z = 0.15  # m: a first state higher than this above z = 0 is taken as a start in the air


class State(Protocol):
    """What the controller needs of a state estimate: world position, velocity, attitude (wxyz)."""

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray


class Solver(Protocol):
    """The MPC's face to the controller (``TranslationalMpc``, or a fault-injecting wrapper)."""

    backend: str

    def solve(self, x0: np.ndarray, params: MpcParameters) -> Any:
        """The plan for state ``x0`` (p, v) given everything else the solve reads (``MpcParameters``)."""
        ...

    def stats(self) -> SolverStats:
        """Solves, failures and rescues so far."""
        ...


@dataclass(frozen=True)
class Command:
    """What one tick decided."""

    acc: np.ndarray  # commanded world acceleration [m/s^2] (the model's input u)
    setpoint: AttitudeSetpoint  # what cflib's send_setpoint takes
    source: str  # "mpc" | "fallback" (the MPC failed or was late) | "geometric" (no MPC) | "brake" (the fence brake)
    status: str  # "ok", the solver's status, or "deadline"
    solve_s: float  # the MPC's own solve time (0 without an MPC)
    ok: bool  # the MPC's answer flew (or the geometric controller, when it is the controller)
    saturated: bool = False  # the command as sent was cut: thrust at the RPYT clamp, or the tilt limit or cone
    # (or the fall guard flew it: its motion is the guard's, not the model's)
    # The adaptation layer's estimate and state this tick (tracking a step, frozen, saturated, the axes it acts
    # on); None without a layer.
    layer: AdaptationEstimate | None = None
    guarded: bool = False  # the fall guard flew the thrust clamp (flight/fall_guard.py)


@dataclass(frozen=True)
class TickInfo:
    """What one tick saw and decided, for observers (training recorder, dashboard status)."""

    t: float
    est: Any  # the state estimate (p, v, q); None when there was none
    ref_p: np.ndarray
    ref_v: np.ndarray
    acc: np.ndarray  # commanded world acceleration (the model's input u)
    setpoint: AttitudeSetpoint
    source: str  # "mpc" | "fallback" | "geometric" | "brake" | "blind" | "cutoff" | "stop" | "no_state" | "refused"
    compute_s: float
    solve_s: float
    missed: bool
    model_version: int
    supervisor_state: str = ""  # the safety supervisor's state after this tick, when there is one
    saturated: bool = False  # the command as sent was cut by the thrust clamp or the tilt limit (never trained on)
    # The fast layer's estimate this tick (an ``AdaptationEstimate``; None without a layer): the learner does
    # not train on the layer's own transients (a step being tracked, a mass still being learned).
    layer: AdaptationEstimate | None = None
    guarded: bool = False  # the fall guard flew it: the thrust dropped under the flying model (the learner drops it)
    skipped: int = 0  # slots the loop passed over before this tick (wall clock): deadlines missed with no command


class TickObserver(Protocol):
    def on_tick(self, tick: TickInfo) -> None: ...


class Controller:
    """MPC (or geometric) position control plus the Mellinger layer, one tick at a time.

    ``settings.kind`` "geometric" flies the geometric controller alone; otherwise ``solver``
    (built from the settings when None) flies, with ``model``'s KNODE residual when given.
    ``deadline_s``: an MPC answer slower than this flies the fallback (wall-clock flights;
    None in lockstep, where computing takes no simulated time). ``settings.adaptation`` other
    than "none" runs the fast adaptation layer (``adaptation``): its offset reaches the MPC as
    the residual's constant, its mass estimate the thrust cone and the Mellinger layer.
    ``ground_z``: the floor's height, near which the layer does not learn (None: the first
    state's height, as for a flight that takes off from where it starts).
    ``true_mass``: the simulator's true mass [kg], read every tick by ``adaptation`` "oracle"
    (``adaptation/oracle.py``), which needs it. ``adaptation``: a layer of one's own (an ``AdaptationLayer``,
    e.g. ``NoAdaptation``) in place of the one ``settings.adaptation`` names.
    """

    def __init__(
        self,
        settings: ControllerConfig,
        vehicle: VehicleConfig,
        *,
        model: ModelSlot | None = None,
        solver: Solver | None = None,
        deadline_s: float | None = None,
        ground_z: float | None = None,
        true_mass: Callable[[], float] | None = None,
        adaptation: AdaptationLayer | None = None,
    ) -> None:
        self.settings = settings
        self.vehicle = vehicle
        self.model = model
        if solver is None and settings.kind != "geometric":
            from cfknode.flight.mpc import TranslationalMpc

            solver = TranslationalMpc(settings, vehicle)
        self.solver = solver
        self.deadline_s = deadline_s
        self.gains = GeometricGains.from_config(settings, vehicle)
        self.offsets = settings.dt * np.arange(settings.horizon + 1)
        self.observers: list[TickObserver] = []
        if adaptation is not None:
            check_layer(adaptation)
        self.adaptation: AdaptationLayer | None = adaptation
        if adaptation is None and settings.adaptation == "oracle":
            if true_mass is None:
                raise ValueError("controller.adaptation oracle needs the true mass: it is simulation only")
            self.adaptation = OracleAdaptation(settings, vehicle, true_mass)
        elif adaptation is None and settings.adaptation != "none":
            self.adaptation = LoopAdaptation(settings, vehicle, ground_z)
        # Without a fast layer nothing else sees a lost thrust in time: the fall guard (flight/fall_guard.py).
        self.fall_guard: FallGuard | None = None
        if self.adaptation is None and solver is not None and settings.fall_guard_level > 0.0:
            self.fall_guard = FallGuard(FallGuardSettings(settings.fall_guard_level, settings.cone_reserve_deg,
                                                          settings.rate_hz), vehicle)
        self._x_pred: np.ndarray | None = None
        self._u_pred: np.ndarray | None = None
        self._pending: TickInfo | None = None
        self._ground_z = ground_z
        self._prepared: PreparedResidual | None = None  # the next tick's linearisation, done after the send
        self._command_flown: tuple[Any, ...] | None = None  # after_command's arguments, until prepare()
        self._layer_input: tuple[Any, ...] | None = None  # before_solve's pose, until prepare()
        self._imu_seen = -math.inf  # the newest accelerometer sample a step was given
        self._layer_version: int | None = None  # the model version the layer last learned beside
        self._prepared_flown: ResidualLinearisation | None = None  # the next tick's MPC residual (model + layer)
        # Set by a caller that calls prepare() after each send (the flight loop): the layer's update from the pose
        # and its record of the command then wait for it (or for the next step, reset or idle).
        self.prepares_after_send = False

    @property
    def ground_z(self) -> float | None:
        """The floor (m): as given, or the first state's height once one was seen; None before that."""
        return self._ground_z

    def _guess_ground(self, z: float) -> None:
        self._ground_z = z
        if z > GUESS_WARN_Z:  # started in the air: the guessed floor is very likely wrong
            warnings.warn(f"Controller: no ground_z given, so the floor is taken as the first state's height "
                          f"(z = {z:.2f} m); the fast layer does not learn within {GROUND_MARGIN} m of it. "
                          "Pass ground_z=<floor height> for a vehicle that starts in the air.", stacklevel=3)

    @property
    def predicted_positions(self) -> np.ndarray | None:
        """The last solved plan's positions over the horizon, (N+1, 3) m; None before a solve or after a failed one."""
        return None if self._x_pred is None else self._x_pred[:, :3].copy()

    @property
    def backend(self) -> str:
        """The solver's name (e.g. ``rti-qrqp-codegen``), or ``geometric``."""
        return self.solver.backend if self.solver is not None else "geometric"

    def preview_times(self, t: float) -> np.ndarray:
        """The MPC's node times from ``t``: where the reference is sampled."""
        return t + self.offsets

    def step(
        self, t: float, state: State, reference: Any, *, force_fallback: bool = False, pose_fresh: bool = True,
        phase: str = "TRACK", observed: State | None = None, brake_tilt_deg: float | None = None,
    ) -> Command:
        """The command for time ``t`` from ``state``, tracking ``reference``.

        ``reference`` is anything with ``sample(times) -> RefSamples`` (a trajectory), or
        ``RefSamples`` already on ``preview_times(t)``. ``force_fallback`` flies the geometric
        fallback after solving (replay of a tick that missed its deadline in flight), so the
        warm start stays what it was in flight. For the fast adaptation layer: ``pose_fresh``
        (a new mocap frame arrived for this state; stale ones freeze the layer) and ``phase``
        (the supervisor's state: "LAND" freezes the layer, "IDLE"/"LANDED"/"EMERGENCY" reset it).
        ``observed``: the estimate as measured when ``state`` is a prediction ahead of it (the command delay,
        flight/latency.py): the MPC plans from ``state``, but the layer, the fall guard and the observers (the
        online learner's data) compare the vehicle with what it did, so they take the measured one.
        ``brake_tilt_deg``: the supervisor's fence brake (source "brake"): the MPC still solves, so its warm start
        stays current, but the geometric law flies, less the layer's offset, tilted up to this many degrees
        (see ``_brake``).
        """
        self._flush_layer()
        obs = state if observed is None else observed
        start = time.perf_counter()
        if self._ground_z is None:
            self._guess_ground(float(state.p[2]))
        if self._pending is not None:
            self.publish()
        ref = reference if isinstance(reference, RefSamples) else reference.sample(self.preview_times(t))
        adapt = self.adaptation
        defer = adapt is not None and self._learns_after_send(t, obs)
        if adapt is not None and not defer:
            self._learn(t, obs, pose_fresh, phase)
        thrust_limit = adapt.f_max() if adapt is not None else math.inf
        acc, ok, solve_s, source, status, model_residual = self._acceleration(
            state, ref, force_fallback or brake_tilt_deg is not None, thrust_limit, defer)
        settings = self.settings
        if brake_tilt_deg is not None:
            acc, ok, source, status = self._brake(state, ref), True, "brake", "ok"
            settings = dataclasses.replace(settings, max_tilt_deg=brake_tilt_deg)
        shaping = adapt.shaping() if adapt is not None else None
        guarding = self._guarding(obs, ref, phase)
        if guarding:  # the clamp, the horizontal within the reserve's lean (the Mellinger layer's cone)
            acc, shaping = guard_acceleration(acc, self.vehicle, self.settings.cone_reserve_deg), CommandShaping()
        shaped = shape_force(acc, self.vehicle, settings, shaping)
        setpoint = force_to_setpoint(shaped.force, float(ref.yaw[0]), state.q, self.vehicle, settings)
        if adapt is not None:
            x_obs = np.concatenate((obs.p, obs.v))
            if model_residual is not None and obs is not state and self.model is not None:
                # Planned from a state predicted ahead (the command delay): the layer is told what the model gives
                # where the vehicle was measured, not the plan's linearisation stretched 0.1 s back to there.
                model_residual = self.model.residual_at(x_obs, np.asarray(shaped.applied_acc, dtype=float))
            self._command_flown = (x_obs, shaped, setpoint.thrust, model_residual)
            if defer:
                self._layer_input = (t, obs, pose_fresh, phase)
            elif not self.prepares_after_send:
                self._flush_layer()
        if self.fall_guard is not None:
            self.fall_guard.sent(setpoint.thrust * self.vehicle.newton_per_cmd)
        # From the command actually sent, on every path: a cut tick's motion is the limit's, not the model's.
        saturated = command_saturated(shaped, setpoint, self.vehicle) or guarding
        command = Command(acc, setpoint, source, status, solve_s, ok, saturated,
                          adapt.estimate if adapt is not None else None, guarding)
        if self.observers:
            version = self.model.version if self.model is not None else 0
            self._pending = TickInfo(t, obs, ref.p[0], ref.v[0], acc, setpoint, source,
                                     time.perf_counter() - start, solve_s, False, version, saturated=saturated,
                                     layer=adapt.estimate if adapt is not None else None, guarded=guarding)
        return command

    def publish(self, **tick: Any) -> None:
        """Show the last tick to the observers; ``tick`` overrides its fields (the loop's
        ``compute_s``, ``missed``, ``supervisor_state``). Call it once the command is sent."""
        info, self._pending = self._pending, None
        if info is None:
            return
        if tick:
            info = dataclasses.replace(info, **tick)
        for observer in self.observers:
            observer.on_tick(info)

    def prepare(self) -> None:
        """After the send: the next tick's work that waits for no new pose. The fast layer learns from the pose
        just flown and records the command sent; the model is linearised at the plan just solved (the next
        tick's nodes; not for a model that takes the neighbour's moving position), and the MPC's residual put
        together with the layer's part. ``step`` flies them if no swap came between."""
        self._flush_layer()
        nodes = plan_nodes(self._x_pred, self._u_pred) if self.model is not None else None
        prepared = self.model.prepare(*nodes) if nodes is not None else None  # type: ignore[union-attr]
        self._prepared = prepared
        adapt = self.adaptation
        self._prepared_flown = None
        if prepared is not None and adapt is not None and self.prepares_after_send:
            self._prepared_flown = adapt.residual(prepared.residual, self.settings.horizon)

    def _new_sample(self, obs: State) -> bool:
        """Whether ``obs`` carries an accelerometer sample newer than any step was given (then remembered)."""
        imu = getattr(obs, "imu", None)
        if imu is None or imu.t <= self._imu_seen:
            return False
        self._imu_seen = imu.t
        return True

    def _learns_after_send(self, t: float, obs: State) -> bool:
        """Whether the layer learns from this pose after the send (``prepares_after_send``). Not when the model
        changed since the last preparation: the layer re-bases on a swap before the solve flies the new model.
        Not for a new accelerometer sample the layer must act on now (``needs_sample_now``: a step's alarm, a
        step being tracked): the radio sends one tick's command in four, and a step learned after that send
        reaches the motors a slot later (docs/design.md#the-tick-in-two-phases)."""
        new_sample = self._new_sample(obs)
        if not self.prepares_after_send or self._model_version() != self._layer_version:
            return False
        return not (new_sample and self.adaptation.needs_sample_now(t, obs))  # type: ignore[union-attr]

    def _model_version(self) -> int:
        return self.model.version if self.model is not None else 0

    def _learn(self, t: float, obs: State, pose_fresh: bool, phase: str) -> None:
        """The layer's update from the pose at ``t`` (``before_solve``), beside the model flying now."""
        self._layer_version = self._model_version()
        self.adaptation.before_solve(t, obs, pose_fresh, phase, self.model)  # type: ignore[union-attr]

    def _flush_layer(self) -> None:
        """What the layer was left by the last step, once: its update from that pose, then the command sent."""
        pending, self._layer_input = self._layer_input, None
        if pending is not None and self.adaptation is not None:
            self._learn(*pending)
        flown, self._command_flown = self._command_flown, None
        if flown is not None and self.adaptation is not None:
            self.adaptation.after_command(*flown)

    def reset(self) -> None:
        """Forget the warm start and the adaptation (after flying blind, or any gap in the controller's ticks)."""
        self._x_pred = self._u_pred = None
        self._prepared = self._prepared_flown = None
        self.idle()

    def idle(self) -> None:
        """A tick someone else flew (motors off, waiting for a pose): the adaptation starts over."""
        self._flush_layer()
        if self.adaptation is not None:
            self.adaptation.off_air()
        if self.fall_guard is not None:
            self.fall_guard.reset()

    def _guarding(self, state: State, ref: RefSamples, phase: str) -> bool:
        """Whether the fall guard flies this tick: only on the pattern (take-off and landing change the height on
        purpose, near the floor the ground carries part of the weight)."""
        if self.fall_guard is None:
            return False
        airborne = phase == "TRACK" and float(state.p[2]) > (self._ground_z or 0.0) + GROUND_MARGIN
        above = float(state.p[2]) - float(ref.p[0][2])
        return self.fall_guard.engaged(state, float(ref.v[0][2]), airborne, above)

    def _acceleration(self, state: State, ref: RefSamples, force_fallback: bool, thrust_limit: float,
                      prepared_layer: bool = False) -> tuple[Any, ...]:
        """(acc, ok, solve time, source, status, the model's own residual linearisation or None).
        ``prepared_layer``: the layer learned nothing inside this tick, so a residual put together after the
        last send still holds with the prepared linearisation."""
        if self.solver is None:
            return self._geometric(state, ref), True, 0.0, "geometric", "ok", None
        x0 = np.concatenate((state.p, state.v))
        model_residual = residual = None
        prepared, self._prepared = self._prepared, None
        flown, self._prepared_flown = self._prepared_flown, None
        if prepared is not None and self.model is not None and self.model.holds(prepared):
            model_residual = prepared.residual
            if prepared_layer and flown is not None:
                residual = flown
        elif self.model is not None:
            model_residual = self.model.residual(*linearisation_points(x0, ref.a, self._x_pred, self._u_pred))
        if residual is None:
            residual = model_residual
            if self.adaptation is not None:
                residual = self.adaptation.residual(model_residual, self.settings.horizon)
        sol = self.solver.solve(x0, MpcParameters(ref, residual, thrust_limit))
        self._x_pred, self._u_pred = (sol.x_pred, sol.u_pred) if sol.ok else (None, None)
        late = force_fallback or (self.deadline_s is not None and sol.solve_time > self.deadline_s)
        if sol.ok and not late:
            return sol.acc, True, sol.solve_time, "mpc", "ok", model_residual
        status = sol.status if not sol.ok else "deadline"
        return self._geometric(state, ref), False, sol.solve_time, "fallback", status, model_residual

    def _brake(self, state: State, ref: RefSamples) -> np.ndarray:
        """The fence brake's acceleration: the geometric law (firmware Mellinger gains), less the fast layer's
        offset (the disturbance it has measured). The MPC's horizontal box is compiled at
        ``controller.max_tilt_deg``: a gust that takes all of it pushes the vehicle on however the MPC plans, and
        only a steeper tilt brings it back, which this law may use in full."""
        acc = self._geometric(state, ref)
        if self.adaptation is not None:
            acc = acc - np.asarray(self.adaptation.estimate.offset, dtype=float)
        return acc

    def _geometric(self, state: State, ref: RefSamples) -> np.ndarray:
        return geometric_acc(state.p, state.v, ref.p[0], ref.v[0], ref.a[0], self.gains)


def check_layer(layer: Any) -> None:
    """A layer of one's own must fill the controller's slot (``AdaptationLayer``): one line naming what it lacks,
    before the flight, rather than an AttributeError in the middle of one."""
    missing = [name for name in dir(AdaptationLayer) if not name.startswith("_") and not hasattr(layer, name)]
    if missing:
        raise TypeError(f"Controller: adaptation {type(layer).__name__} is not an AdaptationLayer: it lacks "
                        f"{', '.join(missing)} (flight/adaptation/protocol.py)")
