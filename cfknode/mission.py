"""Wiring: build the parts a configuration asks for, fly, and summarise.

This is the one place that knows which backend is in use. The flight loop itself sees
only a clock, a pose source, a safety supervisor (which owns the radio) and a log,
identical in simulation and on hardware. Fault injection (``faults:``) is installed here,
around the simulator's parts, and nowhere in the flight path.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from cfknode import __version__
from cfknode.config import Config, ConfigError
from cfknode.kernel.clock import SimClock, WallClock
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import VelocityEstimator
from cfknode.flight.flightlog import FlightLog
from cfknode.flight.mpc_codegen import default_cache_dir
from cfknode.flight.loop import FlightParts, FlightRecord, TickObserver, fly
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc
from cfknode.flight.radio import CflibRadio
from cfknode.flight.summary import FlightSummary, compute_summary
from cfknode.flight.trajectory import make_trajectory
from cfknode.flight.status import StatusTap
from cfknode.safety.estop_mailbox import EstopMailbox, FlightRunning, MailboxError, mailbox_dir
from cfknode.safety.supervisor import Outcome, Supervisor, SupervisorInputs
from cfknode.safety.watchdogs import radio_link_status, worst_link


class MissionError(RuntimeError):
    """A flight could not start or finish; the message is one line for the user."""


@dataclass(frozen=True)
class FlightResult:
    summary: FlightSummary
    record: FlightRecord
    outcome: Outcome  # how the flight ended; ``outcome.message`` is the line the user sees
    learner: Any = None  # the online learner (flight.online.OnlineLearner) when online learning ran


def build_supervisor(
    cfg: Config, radio: Any, *, trajectory: Any, log: Any, deadlines_apply: bool,
    inputs: SupervisorInputs = SupervisorInputs(),
) -> Supervisor:
    """The safety supervisor for ``cfg``'s flight (the robot's name in messages on hardware)."""
    return Supervisor(cfg.safety, radio, trajectory=trajectory, vehicle=cfg.vehicle, log=log,
                      rate_hz=cfg.controller.rate_hz, deadlines_apply=deadlines_apply, inputs=inputs,
                      robot=cfg.hardware.robot if cfg.backend == "cf" else "")


def build_controller(cfg: Config) -> TranslationalMpc | None:
    if cfg.controller.kind == "geometric":
        return None
    return TranslationalMpc(cfg.controller, cfg.vehicle)


def build_model_slot(cfg: Config) -> ModelSlot | None:
    """The KNODE residual to fly with, loaded before take-off so a bad file refuses the flight."""
    ctrl = cfg.controller
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
        queue = ResidualQueue.from_model_file(load_model(ctrl.model))
    except ModelFileError as exc:
        raise ConfigError(f"refusing to fly: {exc}") from None
    return ModelSlot(queue, version=1)


@dataclass
class Session:
    """What a backend hands the flight: the same shape for the simulator and for hardware."""

    config: Config  # the flight's config (on hardware: with the robot's mass and limits)
    clock: Any
    mocap: Any
    radio: Any
    start_position: np.ndarray
    truth: Callable[[], np.ndarray] | None
    battery_voltage: Callable[[], float | None]
    link_status: Callable[[float], Any]
    wrap_controller: Callable[[Any], Any] = lambda mpc: mpc
    fault_observers: Callable[[ModelSlot | None], list[TickObserver]] = lambda model: []
    events: tuple[dict[str, Any], ...] = ()  # logged before take-off (pre-flight checks)
    after_handback: Callable[[], dict[str, Any]] = dict  # summary extras once the drone is handed back
    true_mass: Callable[[], float] | None = None  # the simulator's true mass (the oracle reads it); None on hardware


def run_flight(
    cfg: Config,
    name_hint: str = "flight",
    observers: Sequence[TickObserver] = (),
    on_supervisor: Callable[[Supervisor], None] | None = None,
    dashboard: Any = None,
) -> FlightResult:
    """Fly one mission with the configured backend and return its summary.

    ``observers`` get every tick (a training recorder, a dashboard); the injected faults'
    observers run after them. ``on_supervisor(supervisor)`` is called once before take-off,
    for operator controls outside the loop. ``dashboard`` is a rich Console to draw the live
    dashboard on (None: headless); its space and q keys land the drone.
    """
    if cfg.backend == "sim":
        if not cfg.radio.uri.startswith("sim://"):
            raise ConfigError(f"config key 'radio.uri' must be a sim:// URI with backend sim, got {cfg.radio.uri!r}")
        from cfknode.sim_backend.faults import check_faults

        check_faults(cfg.faults, cfg.sim, cfg.controller.kind, cfg.backend)
        flight_cfg, session = cfg, _sim_session(cfg)
    else:
        if cfg.controller.adaptation == "oracle":
            raise ConfigError("controller.adaptation oracle reads the simulator's true mass: simulation only (backend sim)")
        from cfknode.hardware import HARDWARE_ERRORS, flight_config, robot_for

        try:
            flight_cfg = flight_config(cfg, robot_for(cfg))  # the robot's mass and limits
        except HARDWARE_ERRORS as exc:
            raise MissionError(str(exc)) from exc
        session = _cf_session(cfg, dashboard)
    from cfknode.online_wiring import online_model_slot, start_trainer

    model = build_model_slot(flight_cfg)
    loaded_model = model is not None
    model = online_model_slot(flight_cfg, model)  # online learning swaps into an empty (nominal) slot
    if model is None and cfg.faults.nan_model_at >= 0:
        model = ModelSlot(None)  # nominal until the injected model is swapped in
    mpc = build_controller(flight_cfg)  # built (and compiled) before the clock starts
    # The trainer is up before the session starts the clock, so a wall-clock flight loses no take-off.
    # The e-stop mailbox first: a second flight of a flying robot is refused before anything connects.
    with estop_mailbox(cfg, flight_cfg) as estop, start_trainer(flight_cfg) as trainer, session as sess:
        return _fly_session(sess, name_hint, model, loaded_model, mpc, observers, on_supervisor, dashboard, trainer,
                            estop)


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


def _fly_session(
    sess: Session,
    name_hint: str,
    model: ModelSlot | None,
    loaded_model: bool,
    mpc: TranslationalMpc | None,
    observers: Sequence[TickObserver],
    on_supervisor: Callable[[Supervisor], None] | None,
    dashboard: Any,
    trainer: Any,
    estop: EstopMailbox | None = None,
) -> FlightResult:
    from cfknode.online_wiring import online_session

    cfg = sess.config
    trajectory = make_trajectory(cfg.trajectory, sess.start_position)
    status = _dashboard_status(cfg) if dashboard is not None else None
    with FlightLog.create(cfg.log.dir, cfg.to_dict(), __version__, name_hint) as flight_log:
        log: Any = flight_log if status is None else StatusTap(flight_log, status)
        for event in sess.events:
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
        with online_session(cfg, model, log, sess.clock, trainer, ground_z=ground_z) as online:
            # In lockstep no time passes while computing, so a slow solve is not late: no deadline.
            deadline = cfg.safety.solve_deadline_s if supervisor.deadlines_apply else None
            controller = Controller(cfg.controller, cfg.vehicle, model=model, solver=sess.wrap_controller(mpc),
                                    deadline_s=deadline, ground_z=ground_z, true_mass=sess.true_mass)
            if online is not None:
                controller.observers.append(online)
            parts = FlightParts(
                clock=sess.clock,
                mocap=sess.mocap,
                estimator=VelocityEstimator(cfg.estimator),
                trajectory=trajectory,
                controller=controller,
                supervisor=supervisor,
                log=log,
                truth=sess.truth,
                observers=[
                    *observers,
                    *([status] if status is not None else []),
                    *sess.fault_observers(model),
                ],
                estop=estop,
            )
            if on_supervisor is not None:
                on_supervisor(supervisor)
            flight = fly(parts)
            if status is not None:
                flight = _with_dashboard(flight, status, dashboard, sess, supervisor, cfg)
            record = asyncio.run(flight)
            sess.radio.shutdown()
            outcome = supervisor.outcome()
            summary = compute_summary(
                t=record.t,
                p=record.p,
                p_ref=record.p_ref,
                compute_s=record.compute_s,
                solve_s=record.solve_s,
                missed=record.missed,
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
                    "controller": _controller_label(cfg, loaded_model, online is not None),
                    "model": cfg.controller.model or None,
                    "solver": cfg.controller.solver if mpc is not None else "none",
                    "backend": cfg.backend,
                    "lockstep": bool(sess.clock.lockstep),
                    "mocap_dropouts": sess.mocap.stats().dropouts,
                    **record.adaptation,
                    **(online.summary_fields() if online is not None else {}),
                    **sess.after_handback(),
                },
            )
            log.write("/summary", record.t[-1] if record.ticks else 0.0, summary.to_dict())
    return FlightResult(summary=summary, record=record, outcome=outcome, learner=online)


def _controller_label(cfg: Config, loaded_model: bool, online: bool) -> str:
    if online:
        return "knode-mpc-online (paper lockstep)" if cfg.online.paper_lockstep else "knode-mpc-online"
    return "knode-mpc" if loaded_model else cfg.controller.kind


def _dashboard_status(cfg: Config) -> Any:
    from cfknode.flight.status import FlightStatus

    t, c = cfg.trajectory, cfg.controller
    return FlightStatus(c.rate_hz, title=f"{t.kind} r={t.radius} m - {c.kind} ({c.solver})")


def _with_dashboard(flight: Any, status: Any, console: Any, sess: Session, supervisor: Supervisor, cfg: Config) -> Any:
    """Wrap the flight coroutine so the dashboard draws beside it; space and q land the drone."""
    from cfknode.flight.dashboard import with_dashboard
    from cfknode.flight.status import battery_poller, mocap_poller, radio_poller

    status.add_poller(mocap_poller(sess.mocap))
    status.add_poller(radio_poller(sess.radio))
    status.add_poller(battery_poller(lambda: sess.battery_voltage() or float("nan")))

    def on_key(key: str) -> None:
        if key in ("space", "q"):
            supervisor.request_land(f"operator e-stop key ({key})")

    return with_dashboard(flight, status, console, on_key, cfg.dashboard.refresh_hz)


def _vehicle_after(sim: Any) -> dict[str, Any]:
    """Where the simulated drone ended and whether its motors run (after the hand-back)."""
    return {
        "position": [round(float(v), 4) for v in sim.state[:3]],
        "motors": [int(m) for m in sim.firmware.motor_commands],
        "on_ground": bool(sim.vehicle.on_ground),
    }


def _firmware_after_handback(sim, clock) -> str:
    """The simulated firmware's state once the handback has settled (lockstep only).

    The firmware's 2 s landed hysteresis decides between Landed and Locked after the
    radio stops streaming, so a lockstep flight runs the simulator on to show which.
    """
    if clock.lockstep:
        sim.step_to(sim.t + 2.5)
    return sim.firmware.supervisor_state


@contextlib.contextmanager
def _sim_session(cfg: Config) -> Iterator[Session]:
    """The simulated Crazyflie behind the real cflib path: sim:// driver, simulated mocap, a clock,
    and the configured faults installed around them."""
    from cfknode.mocap.simulated import SimulatedMocap
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.faults import install_faults
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
    from cfknode.sim_backend.realtime import RealtimeStepper

    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    faults = install_faults(sim, cfg.faults)
    mocap = SimulatedMocap.from_config(sim, cfg.sim, outages=faults.mocap_outages)
    register_simulator(cfg.radio.uri, sim)
    clock: WallClock | SimClock = WallClock() if cfg.sim.realtime else SimClock(sim)
    radio = CflibRadio.from_config(
        cfg.radio,
        lockstep=clock.lockstep,
        clock=clock.now,
        # In lockstep the shutdown's zero stream must span simulated time, so the radio steps the sim.
        advance=sim.step_to if clock.lockstep else None,
        rw_cache=str(default_cache_dir() / "cflib"),  # TOC cache, as on hardware
    )
    link = radio_link_status(radio)
    if faults.link_status is not None:
        link = worst_link(link, faults.link_status)
    stepper = None
    try:
        radio.connect()
        if cfg.sim.realtime:
            stepper = RealtimeStepper(sim, clock.now).start()
        yield Session(
            config=cfg,
            clock=clock,
            mocap=mocap,
            radio=radio,
            start_position=np.asarray(cfg.sim.initial_position, dtype=float),
            truth=lambda: sim.state,
            true_mass=lambda: sim.mass,
            battery_voltage=lambda: sim.battery_voltage,
            link_status=link,
            wrap_controller=lambda mpc: faults.controller(mpc, clock.now),
            fault_observers=faults.observers,
            after_handback=lambda: {
                "firmware_after_shutdown": _firmware_after_handback(sim, clock),
                "vehicle_after_shutdown": _vehicle_after(sim),
            },
        )
    finally:
        radio.shutdown()
        if stepper is not None:
            stepper.stop()
        mocap.close()
        unregister_simulator(cfg.radio.uri)


@contextlib.contextmanager
def _cf_session(cfg: Config, console: Any) -> Iterator[Session]:
    """A Crazyflie over cflib with mocap over ``motioncapture`` (or the simulator behind sim://)."""
    from rich.console import Console

    from cfknode.hardware import HARDWARE_ERRORS, cf_session

    try:
        with cf_session(cfg, console=console or Console(stderr=True)) as hw:

            def battery() -> float | None:
                telemetry = hw.radio.telemetry()
                return telemetry.vbat if telemetry is not None else None

            def after() -> dict[str, Any]:
                extra: dict[str, Any] = {"preflight": hw.preflight.to_dict(), "handback": hw.radio.handback_note}
                if hw.sim is not None:
                    extra["firmware_after_shutdown"] = hw.sim.firmware.supervisor_state
                return extra

            yield Session(
                config=hw.config,
                clock=hw.clock,
                mocap=hw.mocap,
                radio=hw.radio,
                start_position=hw.start_position,
                truth=hw.truth,
                battery_voltage=battery,
                link_status=radio_link_status(hw.radio),
                events=tuple(hw.preflight.events()),
                after_handback=after,
            )
    except HARDWARE_ERRORS as exc:
        raise MissionError(str(exc)) from exc
