"""Wiring: build the parts a configuration asks for, fly, and summarise.

This is the one place that knows which backend is in use. The flight loop itself sees
only a clock, a pose source, a safety supervisor (which owns the radio) and a log,
identical in simulation and on hardware. Fault injection (``faults:``) is installed here,
around the simulator's parts, and nowhere in the flight path.
"""

from __future__ import annotations

import logging
import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence


from cfknode import __version__
from cfknode.app.config import Config, ConfigError
from cfknode.app.flight_checks import refuse_unflyable
from cfknode.flight.controller import Controller
from cfknode.flight.learning.trainer_client import refuse_in_spawned_import
from cfknode.flight.estimator import VelocityEstimator
from cfknode.app.foxglove.view import Drawing, FoxgloveView, McapSink, reference_points
from cfknode.app.logs.writer import FlightLog
from cfknode.app.stall_exit import LoopProgress, stall_exit
from cfknode.flight.loop import FlightParts, FlightRecord, TickObserver, fly
from cfknode.kernel.clock import run_loop
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc
from cfknode.app.backends.base import Backend
from cfknode.app.backends.sim import SimulatorBackend
from cfknode.app.ui.summary import FlightSummary, compute_summary
from cfknode.flight.tick_guard import GuardedLog, hand_back
from cfknode.flight.trajectory import make_trajectory
from cfknode.app.ui.status import StatusTap
from cfknode.safety.estop_mailbox import EstopMailbox, FlightRunning, MailboxError, mailbox_dir
from cfknode.safety.supervisor import ERROR_RECORD, Outcome, SupervisedFlight, Supervisor, SupervisorInputs


_logger = logging.getLogger(__name__)


class MissionError(RuntimeError):
    """A flight could not start or finish; the message is one line for the user."""


@dataclass(frozen=True)
class FlightResult:
    summary: FlightSummary
    record: FlightRecord
    outcome: Outcome  # how the flight ended; ``outcome.message`` is the line the user sees
    learner: Any = None  # the online learner (flight.online.OnlineLearner) when online learning ran
    log_incomplete: str | None = None  # the flight log stopped writing: from when, and why (FlightLog.incomplete)


def build_supervisor(
    cfg: Config, radio: Any, *, trajectory: Any, log: Any, deadlines_apply: bool,
    inputs: SupervisorInputs = SupervisorInputs(),
) -> Supervisor:
    """The safety supervisor for ``cfg``'s flight (the robot's name in messages on hardware)."""
    flight = SupervisedFlight(trajectory, cfg.vehicle, cfg.controller.rate_hz, deadlines_apply,
                              robot=cfg.hardware.robot if cfg.backend == "cf" else "")
    return Supervisor(cfg.safety, radio, flight, log=log, inputs=inputs)


def build_controller(cfg: Config) -> TranslationalMpc | None:
    if cfg.controller.kind == "geometric":
        return None
    return TranslationalMpc(cfg.controller, cfg.vehicle)


def build_model_slot(cfg: Config, notes: list[str] | None = None) -> ModelSlot | None:
    """The KNODE residual to fly with, loaded before take-off so a bad file refuses the flight. A model whose
    stored score beside the layer is above ``model_min_score`` on no axis is not flown (``model_not_flown``;
    the line is logged and appended to ``notes``): the flight flies the layer alone."""
    ctrl = cfg.controller
    if cfg.sim.air_model:
        return air_model_slot(cfg)
    if ctrl.kind == "geometric":
        if ctrl.model:
            raise ConfigError("controller.model is set but controller.kind is geometric, which uses no model")
        return None
    if ctrl.kind == "knode-mpc" and not ctrl.model:
        raise ConfigError("controller.kind knode-mpc needs a model file: --model FILE (see cfknode train)")
    if not ctrl.model:
        return None
    from cfknode.models.modelfile import ModelFileError, load_model
    from cfknode.models.residual_np import ResidualQueue

    try:
        model_file = load_model(ctrl.model)
    except ModelFileError as exc:
        raise ConfigError(f"refusing to fly: {exc}") from None
    refuse_neighbour_mismatch(cfg, model_file)
    queue = ResidualQueue.from_model_file(model_file)
    refuse_implausible_model(cfg, model_file, queue)
    note = model_not_flown(cfg, queue.beyond_layer)
    if note:
        _logger.warning(note)
        if notes is not None:
            notes.append(note)
        return None
    return ModelSlot(queue, version=1)


def air_model_slot(cfg: Config) -> ModelSlot:
    """``sim.air_model``: the realistic plant's own air terms as the MPC's model (a bench's ceiling); empty until
    ``sim.air_model_from_s`` (``air_model_observers`` swaps the model in then)."""
    model = air_model(cfg)
    return ModelSlot(None, version=0) if cfg.sim.air_model_from_s > 0.0 else ModelSlot(model, version=1)


def air_model(cfg: Config) -> Any:
    """The ``AirModel`` that ``sim.air_model`` flies; a one-line ``ConfigError`` where it means nothing."""
    why = ("simulation only (backend sim)" if cfg.backend != "sim"
           else "it needs sim.aero realistic: the ideal plant has no air terms" if cfg.sim.aero != "realistic"
           else "controller.kind geometric uses no model" if cfg.controller.kind == "geometric"
           else "it replaces controller.model: set one of them" if cfg.controller.model
           else "online learning swaps its own models in: not with online.enabled" if cfg.online.enabled
           else "sim.air_model_terms wake needs a fleet (fleet.size >= 2) with fleet.neighbour_input"
           if cfg.sim.air_model_terms == "wake" and not (cfg.fleet.size >= 2 and cfg.fleet.neighbour_input)
           else "")
    if why:
        raise ConfigError(f"sim.air_model gives the MPC the simulator's air: {why}")
    from cfknode.sim_backend.air_model import AirModel

    terms = cfg.sim.aero_terms
    if cfg.sim.air_model_terms == "wake":  # the wake alone: the drone's own drag, inflow and floor left to the layer
        terms = dataclasses.replace(terms, rotor_drag=0.0, inflow=0.0, ground_effect=0.0)
    return AirModel(terms, cfg.vehicle.gravity, neighbour=cfg.fleet.neighbour_input)


def air_model_observers(cfg: Config, slot: ModelSlot | None) -> list[Any]:
    """With ``sim.air_model_from_s`` > 0, the tick observer that swaps the air model into ``slot`` then."""
    if not cfg.sim.air_model or cfg.sim.air_model_from_s <= 0.0 or slot is None:
        return []
    from cfknode.sim_backend.timed_swap import SwapAt

    return [SwapAt(slot, air_model(cfg), cfg.sim.air_model_from_s)]


def model_not_flown(cfg: Config, score: Any) -> str | None:
    """One line when the layer flies and the model's stored score (x, y, z) is above the threshold on no axis
    (``controller.adaptation_settings.model_min_score``), else None (no layer, no coefficients, or no score
    stored: the score is the share beyond the layer, and acts through the coefficients)."""
    from cfknode.models.residual_check import flown_axes

    ctrl = cfg.controller
    min_score = ctrl.adaptation_settings.model_min_score
    axes = flown_axes(score, min_score)  # None: no score stored
    if ctrl.adaptation == "none" or not ctrl.adaptation_settings.model_coefficients or axes is None or any(axes):
        return None
    scores = ", ".join(f"{v:+.2%}" for v in score.tolist())
    return (f"model not flown: {ctrl.model} adds nothing beside the fast layer on any axis (its held-out score "
            f"x, y, z: {scores}; model_min_score {min_score:.2%}); flying the layer alone")


def refuse_neighbour_mismatch(cfg: Config, model_file: Any) -> None:
    """A model file whose input layout is not the one this flight feeds (docs/fleet.md#neighbour-input), in one line."""
    fleet = cfg.fleet.size >= 2 and cfg.fleet.neighbour_input
    if model_file.takes_neighbour and not fleet:
        raise ConfigError(f"refusing to fly: model file {cfg.controller.model} takes the neighbour input "
                          "(nbx, nby, nbz): it flies in a fleet with fleet.neighbour_input true")
    if fleet and cfg.online.enabled and not model_file.takes_neighbour:
        raise ConfigError(f"refusing to fly: model file {cfg.controller.model} has no neighbour input, which online "
                          "learning with fleet.neighbour_input trains: set fleet.neighbour_input false")


def refuse_implausible_model(cfg: Config, model_file: Any, queue: Any) -> None:
    """The online gate's residual rules on the operating envelope, before take-off: a finite but
    absurd model (say, weights scaled by 1e300) would fail the MPC on every tick."""
    from cfknode.app.learning import gate_limits
    from cfknode.flight.learning.gate import residual_verdict

    limits = gate_limits(cfg)
    reason, _ = residual_verdict(model_file, queue, limits.envelope_x, limits.envelope_u, limits.max_residual)
    if reason:
        raise ConfigError(f"refusing to fly: model file {cfg.controller.model}: implausible on the operating envelope ({reason})")


def run_flight(
    cfg: Config,
    name_hint: str = "flight",
    observers: Sequence[TickObserver] = (),
    on_supervisor: Callable[[Supervisor], None] | None = None,
    dashboard: Any = None,
    trajectory: Any = None,
    estop: bool = True,
    live: Any = None,
) -> FlightResult:
    """Fly one mission with the configured backend and return its summary.

    ``observers`` get every tick (a training recorder, a dashboard); the injected faults'
    observers run after them. ``on_supervisor(supervisor)`` is called once before take-off,
    for operator controls outside the loop. ``dashboard`` is a rich Console to draw the live
    dashboard on (None: headless); its space and q keys land the drone. ``trajectory``: the
    reference to fly instead of the configured one (a fleet drone's placed pattern). ``estop``
    False: no e-stop mailbox entry of its own (a fleet's driver keeps the drone's entry). ``live``:
    a Foxglove live server (``cfknode.app.foxglove.live.LiveServer``) to show the flight on too.
    """
    refuse_in_spawned_import()
    if cfg.backend == "sim":
        if not cfg.radio.uri.startswith("sim://"):
            raise ConfigError(f"config key 'radio.uri' must be a sim:// URI with backend sim, got {cfg.radio.uri!r}")
        from cfknode.sim_backend.faults import check_faults

        check_faults(cfg.faults, cfg.sim, cfg.controller.kind, cfg.backend)
        flight_cfg, session = cfg, SimulatorBackend.open(cfg)
    else:
        if cfg.controller.adaptation == "oracle":
            raise ConfigError("controller.adaptation oracle reads the simulator's true mass: simulation only (backend sim)")
        from cfknode.app.backends.crazyflie import HARDWARE_ERRORS, flight_config, robot_for

        try:
            flight_cfg = flight_config(cfg, robot_for(cfg))  # the robot's mass and limits
        except HARDWARE_ERRORS as exc:
            raise MissionError(str(exc)) from exc
        session = _crazyflie(cfg, dashboard)
    # Before anything is built or connected: an unflyable config is refused in one line.
    forced = refuse_unflyable(flight_cfg, where="" if flight_cfg is cfg else f"robot {cfg.hardware.robot}")
    for event in forced:
        _logger.warning(event["text"])
    from cfknode.app.learning import online_model_slot, start_trainer

    notes: list[str] = []
    model = build_model_slot(flight_cfg, notes)
    loaded_model = model is not None
    forced = [*forced, *({"level": "warning", "text": n, "source": "model"} for n in notes)]
    model = online_model_slot(flight_cfg, model)  # online learning swaps into an empty (nominal) slot
    if model is None and cfg.faults.nan_model_at >= 0:
        model = ModelSlot(None)  # nominal until the injected model is swapped in
    mpc = build_controller(flight_cfg)  # built (and compiled) before the clock starts
    # The trainer is up before the session starts the clock, so a wall-clock flight loses no take-off.
    # The e-stop mailbox first: a second flight of a flying robot is refused before anything connects.
    box = estop_mailbox(cfg, flight_cfg) if estop else contextlib.nullcontext(None)
    with box as estop_box, start_trainer(flight_cfg) as trainer, session as sess:
        request = _Request(name_hint, observers, on_supervisor, dashboard, trajectory, live)
        return _fly_session(sess, request, _Kit(model, loaded_model, mpc, trainer, estop_box, (*forced, *sess.events),
                                                notes[0] if notes else None))


def estop_name(cfg: Config) -> str:
    """The name ``cfknode estop --robot`` knows the flight by: the robot on hardware; in
    simulation ``sim-<robot>``, so a simulated flight is never taken for (or blocks) a real one."""
    return cfg.hardware.robot if cfg.backend == "cf" else f"sim-{cfg.hardware.robot}"


@contextlib.contextmanager
def estop_mailbox(cfg: Config, flight_cfg: Config) -> Iterator[EstopMailbox]:
    """The flight's e-stop mailbox, open (announced) for the block.

    A robot on a real radio is exclusive: a second flight of it is a MissionError (exit status 1;
    it is not bad input, the same command works once the other flight has ended). A mailbox
    directory that cannot be made or that others can write to is a ConfigError (exit status 2).
    """
    box = EstopMailbox(mailbox_dir(cfg.safety.estop_dir), estop_name(cfg),
                       exclusive=not flight_cfg.radio.uri.startswith("sim://"))
    try:
        box.open()
    except FlightRunning as exc:
        raise MissionError(f"take-off refused: {exc}") from None
    except MailboxError as exc:
        raise ConfigError(f"config key 'safety.estop_dir': {exc}") from None
    try:
        yield box
    finally:
        box.close()


@dataclass(frozen=True)
class _Request:
    """What ``run_flight``'s caller asked for beyond the config (see its docstring)."""

    name_hint: str
    observers: Sequence[TickObserver]
    on_supervisor: Callable[[Supervisor], None] | None
    dashboard: Any
    trajectory: Any
    live: Any


@dataclass(frozen=True)
class _Kit:
    """What ``run_flight`` built before the session's clock started."""

    model: ModelSlot | None
    loaded_model: bool  # a model file was loaded (not only an online slot)
    mpc: TranslationalMpc | None
    trainer: Any
    estop: EstopMailbox | None
    events: Sequence[dict[str, Any]]  # logged at t=0: forced config changes, the session's pre-flight events
    model_not_flown: str | None = None  # why the configured model file is not flown (build_model_slot)


def _fly_session(sess: Backend, request: _Request, kit: _Kit) -> FlightResult:
    from cfknode.app.learning import keep_learned_model, online_session

    cfg = sess.config
    if request.trajectory is None:
        request = dataclasses.replace(request, trajectory=make_trajectory(cfg.trajectory, sess.start_position))
    trajectory, dashboard, mpc = request.trajectory, request.dashboard, kit.mpc
    status = _dashboard_status(cfg) if dashboard is not None else None
    with FlightLog.create(cfg.log.dir, cfg.to_dict(), __version__, request.name_hint) as flight_log:
        view = foxglove_view(flight_log, cfg, trajectory, request.live)
        # Guarded: a failing write (or dashboard tap) is reported, never the end of the flight.
        log: Any = GuardedLog(view if status is None else StatusTap(view, status))
        for event in kit.events:
            log.write("/events", 0.0, event)
        supervisor = build_supervisor(
            cfg,
            sess.radio,
            trajectory=trajectory,
            log=log,
            deadlines_apply=not sess.clock.lockstep,
            inputs=SupervisorInputs(battery_voltage=sess.battery_voltage, link_status=sess.link_status),
        )
        ground_z = float(sess.start_position[2])
        with online_session(cfg, kit.model, log, sess.clock, kit.trainer, ground_z=ground_z) as online:
            parts = _flight_parts(sess, request, kit, supervisor, log, status, online)
            controller = parts.controller
            view.follow_plan(cfg.hardware.robot, lambda: controller.predicted_positions)
            if request.on_supervisor is not None:
                request.on_supervisor(supervisor)
            progress = LoopProgress()
            parts.observers.insert(0, progress)
            flight = fly(parts)
            if status is not None:
                flight = _with_dashboard(flight, status, dashboard, sess, supervisor, cfg)
            with stall_exit([sess.radio], flight_log, progress):  # a loop that never returns ends the process
                record = run_loop(flight)
            after = hand_back(sess.radio.shutdown, sess.after_handback,
                              lambda part, exc: supervisor.internal_error(part, exc, ERROR_RECORD))
            outcome = supervisor.outcome()
            summary = compute_summary(
                record,
                window=trajectory.pattern_window,
                wall_time=record.wall_time,
                log_path=str(flight_log.path),
                steps=[(m.t, m.factor) for m in cfg.sim.mass_changes] if cfg.backend == "sim" else (),
                # The same margin for every controller, so the rows compare: the MPC's preview horizon.
                recovery_margin_s=cfg.controller.horizon * cfg.controller.dt,
                extra={
                    "outcome": outcome.message,
                    "safety_state": outcome.state.value,
                    "safety_cause": outcome.cause,
                    "fallback_ticks": record.fallbacks,
                    "fallback_reasons": dict(record.fallback_reasons),
                    "fence_excursion_m": float(supervisor.fence.excursion(record.p).max()) if record.ticks else 0.0,
                    "controller": _controller_label(cfg, kit.loaded_model, online is not None),
                    "model": cfg.controller.model or None,
                    **({"model_not_flown": kit.model_not_flown} if kit.model_not_flown else {}),
                    "solver": cfg.controller.solver if mpc is not None else "none",
                    "backend": cfg.backend,
                    "lockstep": bool(sess.clock.lockstep),
                    # The loop thread's CPU time: with trainer_cpu_s (online), who used the cores.
                    "loop_cpu_s": round(record.loop_cpu_s, 3),
                    "mocap_dropouts": sess.mocap.stats().dropouts,
                    **imu_fields(sess.radio, parts.imu is not None),
                    **record.adaptation,
                    **(online.summary_fields() if online is not None else {}),
                    **keep_learned_model(online, flight_log.path),
                    "internal_errors": list(outcome.errors),
                    **({"foxglove_failures": view.failures} if view.failures else {}),
                    **after,
                },
            )
            log.write("/summary", record.t[-1] if record.ticks else 0.0, summary.to_dict())
    # After close: closing writes the footer, which a full disk can refuse too.
    incomplete = flight_log.incomplete()
    if incomplete is not None:  # the flight is fine, its record is not: the summary and the outcome say so
        summary = dataclasses.replace(summary, extra={**summary.extra, "flight_log": incomplete})
        outcome = dataclasses.replace(outcome, message=f"{outcome.message}; but the flight log is {incomplete}")
    return FlightResult(summary=summary, record=record, outcome=outcome, learner=online, log_incomplete=incomplete)


def _flight_parts(sess: Backend, request: _Request, kit: _Kit, supervisor: Supervisor, log: Any, status: Any,
                  online: Any) -> FlightParts:
    """The controller (with the online learner watching it) and the loop's parts for one session."""
    cfg = sess.config
    # In lockstep no time passes while computing, so a slow solve is not late: no deadline.
    deadline = cfg.safety.solve_deadline_s if supervisor.deadlines_apply else None
    controller = Controller(cfg.controller, cfg.vehicle, model=kit.model, solver=sess.wrap_solver(kit.mpc),
                            deadline_s=deadline, ground_z=float(sess.start_position[2]), true_mass=sess.true_mass)
    from cfknode.app.learning import attitude_lag_identifier

    estimator = VelocityEstimator(cfg.estimator)
    if online is not None:
        controller.observers.append(online)
        identifier = attitude_lag_identifier(cfg, online, estimator, kit.model)
        controller.observers.extend([identifier] if identifier is not None else [])
    return FlightParts(
        clock=sess.clock,
        mocap=sess.mocap,
        estimator=estimator,
        trajectory=request.trajectory,
        controller=controller,
        supervisor=supervisor,
        log=log,
        truth=sess.truth,
        imu=getattr(sess, "imu", None),
        observers=[
            *request.observers,
            *([status] if status is not None else []),
            *sess.fault_observers(kit.model),
            *air_model_observers(cfg, kit.model),
        ],
        estop=kit.estop,
    )


def foxglove_view(flight_log: FlightLog, cfg: Config, trajectory: Any, live: Any) -> FoxgloveView:
    """The flight log's tap that mirrors the flight in Foxglove's schemas, into the log and to ``live``."""
    drawing = Drawing(reference_points(trajectory), (cfg.safety.fence_min, cfg.safety.fence_max))
    sinks = [McapSink(flight_log), *([live] if live is not None else [])]
    return FoxgloveView(flight_log, sinks, {cfg.hardware.robot: drawing})


def imu_fields(radio: Any, flown: bool) -> dict[str, Any]:
    """The accelerometer block's counts for the summary, when the flight had one (lockstep: samples waited out)."""
    if not flown or not hasattr(radio, "stats"):
        return {}
    stats = radio.stats()
    return {"imu_samples": stats.imu_samples, "imu_late": stats.imu_late}


def _controller_label(cfg: Config, loaded_model: bool, online: bool) -> str:
    if online:
        return "knode-mpc-online (paper lockstep)" if cfg.online.paper_lockstep else "knode-mpc-online"
    if cfg.sim.air_model:
        return "mpc + air model (simulator's)"
    return "knode-mpc" if loaded_model else cfg.controller.kind


def _dashboard_status(cfg: Config) -> Any:
    from cfknode.app.ui.status import FlightStatus

    t, c = cfg.trajectory, cfg.controller
    return FlightStatus(c.rate_hz, title=f"{t.kind} r={t.radius} m - {c.kind} ({c.solver})")


def _with_dashboard(flight: Any, status: Any, console: Any, sess: Backend, supervisor: Supervisor, cfg: Config) -> Any:
    """Wrap the flight coroutine so the dashboard draws beside it; space and q land the drone."""
    from cfknode.app.ui.dashboard import with_dashboard
    from cfknode.app.ui.status import battery_poller, mocap_poller, radio_poller

    status.add_poller(mocap_poller(sess.mocap))
    status.add_poller(radio_poller(sess.radio))
    status.add_poller(battery_poller(lambda: sess.battery_voltage() or float("nan")))

    def on_key(key: str) -> None:
        if key in ("space", "q"):
            supervisor.request_land(f"operator e-stop key ({key})")

    return with_dashboard(flight, status, console, on_key, cfg.dashboard.refresh_hz,
                          on_error=lambda exc: supervisor.internal_error("the dashboard", exc, ERROR_RECORD))


@contextlib.contextmanager
def _crazyflie(cfg: Config, console: Any) -> Iterator[Backend]:
    """The Crazyflie backend, its hardware errors as one-line ``MissionError``s."""
    from cfknode.app.backends.crazyflie import HARDWARE_ERRORS, CrazyflieBackend

    try:
        with CrazyflieBackend.open(cfg, console) as backend:
            yield backend
    except HARDWARE_ERRORS as exc:
        raise MissionError(str(exc)) from exc
