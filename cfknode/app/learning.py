"""Wiring for online learning: config -> trainer process + ``OnlineLearner`` observer for one flight.

Mission wiring (``run_flight``) uses it in three lines::

    model = online_model_slot(cfg, build_model_slot(cfg))      # a slot even when starting nominal
    with start_trainer(cfg) as trainer:                        # pre-flight, before the clock starts
        ...                                                    # (backend, log, clock as today)
        with online_session(cfg, model, log, clock, trainer) as online:
            controller = Controller(cfg.controller, cfg.vehicle, model=model)
            controller.observers.extend([online] if online else [])
            parts = FlightParts(..., controller=controller)
            record = run_loop(fly(parts))
            extra.update(online.summary_fields() if online else {})

``start_trainer`` exists because a wall clock starts running when the backend is built: a
trainer still importing torch then would eat the take-off. In lockstep ``online_session``
can start the trainer itself (the virtual clock waits).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import math
import warnings
from pathlib import Path
from typing import Any, Iterator

from cfknode.app.config import Config, ConfigError
from cfknode.flight.controller import Controller
from cfknode.flight.learning.monitor import MonitorSettings
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.learning.learner import LearnerSettings, OnlineLearner
from cfknode.flight.learning.gate import GateLimits, operating_envelope
from cfknode.flight.learning.latency import LatencyPolicy
from cfknode.flight.learning.trainer_client import TrainerClient
from cfknode.flight.learning.windows import WakeOnly
from cfknode.flight.learning.attitude_lag import AttitudeLagIdentifier, AttitudeLagSettings

# s: the command path's low-pass of what the commands leave once a lag is identified (where
# estimator.command_residual_tau gives none): short is best, as the drag turns with the velocity
# (docs/history.md#why-a-pure-delay-hurt-the-slow-circle-and-the-three-keys-that-fix-it).
LEARNED_RESIDUAL_TAU = 0.05
from cfknode.models.trainer_process import TrainerSettings


def check_online(cfg: Config) -> None:
    """Refuse configurations online learning cannot fly (one-line ``ConfigError``)."""
    if cfg.fleet.wake_only and not cfg.fleet.neighbour_input:
        raise ConfigError("fleet.wake_only needs fleet.neighbour_input true: without it the networks would see nothing")
    if not cfg.online.enabled:
        return
    if cfg.controller.kind == "geometric":
        raise ConfigError("online.enabled needs an MPC (controller.kind mpc or knode-mpc), not geometric")
    if cfg.online.paper_lockstep and cfg.sim.realtime:
        raise ConfigError("online.paper_lockstep stops the simulation for every model: it needs lockstep (not --realtime)")
    if cfg.online.paper_lockstep and cfg.backend != "sim":
        raise ConfigError("online.paper_lockstep is a simulation-only reproduction mode")


def online_model_slot(cfg: Config, slot: ModelSlot | None) -> ModelSlot | None:
    """The slot online learning swaps into: the given one, or an empty (nominal) one."""
    if not cfg.online.enabled or slot is not None:
        return slot
    return ModelSlot(None, version=0)


def trainer_settings(cfg: Config) -> TrainerSettings:
    """Each round: the ``training`` section with the online epochs, learning rate, weight decay and method.

    On a wall clock (hardware, ``--realtime``) the trainer runs ``online.trainer_nice`` below the flight:
    there the loop's deadlines are real and a round may wait. In lockstep the loop itself waits for the
    trainer whenever its result is due, so a lowered trainer would only make the flight slower.
    """
    o, layer = cfg.online, beside_layer(cfg)
    training = dataclasses.replace(cfg.training, epochs=o.epochs, lr=o.lr, method=o.method,
                                   weight_decay=o.layer_weight_decay if layer else o.weight_decay,
                                   velocity_filter_hz=o.layer_filter_hz if layer else cfg.training.velocity_filter_hz)
    nice = o.trainer_nice if wall_clock(cfg) else 0
    # The trainer also judges the candidates (flight/learning/install.py): the gate's imports before take-off.
    return TrainerSettings(cfg.knode, training, cfg.online.warm_start, cfg.online.inject, nice,
                           preload=("cfknode.flight.learning.install",), input_bounds=layer and o.layer_input_bounds,
                           wake_only=wake_only(cfg))


def attitude_lag_identifier(cfg: Config, learner: OnlineLearner | None, estimator: Any,
                            slot: ModelSlot | None) -> AttitudeLagIdentifier | None:
    """The observer that identifies the attitude loop's lag and retunes ``estimator``'s command path
    (flight/learning/attitude_lag.py); None where it does not run: without online learning beside a fast layer, with
    ``online.layer_attitude_lag`` false, or where the configuration already gives the command path
    (``estimator.command_delay``). The learner reports it in the flight's summary."""
    o = cfg.online
    if learner is None or not (o.layer_attitude_lag and beside_layer(cfg)) or estimator.command_path.active:
        return None
    residual_tau = cfg.estimator.command_residual_tau or LEARNED_RESIDUAL_TAU
    settings = AttitudeLagSettings(o.attitude_lag_span_s, o.attitude_lag_min_fit, o.attitude_lag_horizon, residual_tau)
    identifier = AttitudeLagIdentifier(settings, estimator.command_path, learner.log, cfg.vehicle.gravity,
                                       cfg.controller.rate_hz, slot=slot)
    learner.attitude_lag = identifier
    return identifier


def wake_only(cfg: Config) -> bool:
    """Whether a fleet drone's networks see the neighbour's relative position alone (docs/fleet.md#wake-only)."""
    return cfg.fleet.size >= 2 and cfg.fleet.neighbour_input and cfg.fleet.wake_only


def wall_clock(cfg: Config) -> bool:
    """Whether the flight runs against the wall clock: on hardware, or simulated with ``--realtime``."""
    return cfg.backend != "sim" or cfg.sim.realtime


def learner_settings(
    cfg: Config, lockstep: bool, ground_z: float | None = None, speed: float | None = None
) -> LearnerSettings:
    """``speed``: the gate's envelope speed (m/s); None takes it from the data."""
    o, v, layer = cfg.online, cfg.vehicle, beside_layer(cfg)
    return LearnerSettings(
        t_col=o.t_col,
        period=1.0 / cfg.controller.rate_hz,
        lockstep=lockstep,
        paper_lockstep=o.paper_lockstep,
        gate=o.gate,
        gate_min_pairs=o.gate_layer_min_pairs if layer else o.gate_min_pairs,
        replay_windows=o.layer_replay_windows if layer else o.replay_windows,
        start_time=o.start_time,
        rollback_ticks=o.rollback_ticks,
        rollback_fallbacks=o.rollback_fallbacks,
        max_restarts=o.max_restarts,
        limits=gate_limits(cfg, speed),
        filter_hz=o.layer_filter_hz if layer else cfg.training.velocity_filter_hz,
        holdout_fraction=cfg.training.validation_fraction,
        queue_size=cfg.knode.queue_size,
        monitor=MonitorSettings(o.monitor_window_s, o.monitor_every_ticks, o.monitor_margin, o.monitor_floor)
        if o.monitor else None,
        ground_z=ground_z,
        min_height=o.min_height,
        latency=LatencyPolicy(o.latency, o.fixed_latency_s, o.latency_quantum_s),
        held_limits=gate_limits(cfg, speed, layer_live=False) if layer else None,
        wake_only=WakeOnly(v.gravity, v.newton_per_cmd / v.mass) if wake_only(cfg) else None,
        command_lag_s=o.layer_command_lag_s if layer else o.command_lag_s,
    )


def beside_layer(cfg: Config) -> bool:
    """Whether models fly beside a fast layer that estimates an additive offset."""
    return cfg.controller.adaptation in ("dob", "l1")


def gate_limits(cfg: Config, speed: float | None = None, layer_live: bool = True) -> GateLimits:
    """The gate's plausibility limits on the MPC's operating envelope: its input box, and velocities up to
    ``speed`` (m/s; None: twice the fastest axis of the data it judges, plus 0.5 m/s). ``layer_live`` False: for
    data on which the fast layer measured nothing (held near the floor), judged as without a layer."""
    from cfknode.flight.mpc import acceleration_bounds

    bounds = acceleration_bounds(cfg.controller, cfg.vehicle)
    x, u = operating_envelope(1.0 if speed is None else speed, bounds.lower, bounds.upper)
    o, beside = cfg.online, beside_layer(cfg)
    layer = beside and layer_live
    return GateLimits(cfg.knode.max_residual, o.gate_control_gain, o.gate_max_velocity_gain, x, u, o.gate_max_cross_gain,
                      envelope_from_data=speed is None, constant_free=layer,
                      min_improvement=o.gate_layer_margin if layer else 0.0,
                      steps=o.gate_layer_steps if layer else 1,
                      min_gain=o.gate_layer_min_gain if layer else 0.0, max_tilt_climb=o.gate_max_tilt_climb,
                      layer_hz=_layer_hz(cfg) if layer else None, min_score=o.gate_layer_min_score if layer else 0.0,
                      horizontal_gain=o.gate_layer_horizontal_gain if beside else (0.0, math.inf),
                      max_velocity_coupling=_or_inf(o.gate_layer_velocity_coupling) if beside else math.inf,
                      max_climb_feedback=_or_inf(o.gate_layer_climb_feedback) if layer else math.inf,
                      rejudge=o.gate_layer_rejudge and layer)


def _or_inf(limit: float | None) -> float:
    return math.inf if limit is None else limit


def _layer_hz(cfg: Config) -> tuple[tuple[float, float], tuple[float, float]]:
    """The fast layer's observer and output cut-offs ((xy, z) Hz each), as ``cfknode model check`` uses them."""
    a = cfg.controller.adaptation_settings
    return (a.bandwidth_xy_hz, a.bandwidth_hz), (a.output_bandwidth_xy_hz, a.output_bandwidth_hz)


@contextlib.contextmanager
def start_trainer(cfg: Config, wait: bool = True) -> Iterator[TrainerClient | None]:
    """The trainer process for one flight (None when online learning is off); stopped on exit."""
    check_online(cfg)
    if not cfg.online.enabled:
        yield None
        return
    client = TrainerClient(trainer_settings(cfg), cfg.online.trainer_timeout, start_timeout=cfg.online.trainer_start_timeout)
    client.start()
    try:
        if wait and not client.wait_ready(cfg.online.trainer_start_timeout):
            raise ConfigError(client.start_problem)
        yield client
    finally:
        client.close()


@contextlib.contextmanager
def online_session(
    cfg: Config, slot: ModelSlot | None, log: Any, clock: Any, trainer: TrainerClient | None = None,
    ground_z: float | None = None,
) -> Iterator[OnlineLearner | None]:
    """The loop observer that learns in flight (None when online learning is off).

    ``trainer``: one from ``start_trainer`` (pre-flight). Without it one is started here; in
    lockstep this waits until it is up (the virtual clock does not run meanwhile), on a wall
    clock it does not wait and the first windows queue until the trainer reports ready.
    """
    check_online(cfg)
    if not cfg.online.enabled:
        yield None
        return
    if slot is None:
        raise ConfigError("online learning needs a model slot: use online_model_slot(cfg, slot)")
    base = None
    if cfg.controller.model:
        from cfknode.models.modelfile import ModelFileError, load_model

        try:
            base = load_model(cfg.controller.model)  # the queue the flight starts with, as the trainer's base
        except ModelFileError as exc:
            raise ConfigError(f"refusing to fly: {exc}") from None
    with contextlib.ExitStack() as stack:
        if trainer is None:
            trainer = stack.enter_context(start_trainer(cfg, wait=bool(clock.lockstep)))
        # A mission knows its pattern: the envelope spans twice its speed.
        speed = 2.0 * cfg.trajectory.speed + 0.5
        learner = OnlineLearner(learner_settings(cfg, bool(clock.lockstep), ground_z, speed), slot, trainer, log, base)
        yield learner


def keep_learned_model(learner: OnlineLearner | None, log_path: Path, drone: str | None = None) -> dict[str, str]:
    """Write the model a flight's online learning ended with beside its log, for the next flight to start from
    (``--model``): ``<log>.learned.safetensors`` (``<log>.<drone>.learned.safetensors`` in a fleet). Returns the
    summary's field: ``learned_model`` (the path) or ``learned_model_error``; none when nothing learned flies."""
    model = learner.learned_model if learner is not None else None
    if model is None:
        return {}
    from cfknode.models.modelfile import ModelFileError, save_model

    stem = log_path.with_suffix("")
    path = stem.with_name(f"{stem.name}{'.' + drone if drone else ''}.learned.safetensors")
    try:
        return {"learned_model": str(save_model(path, model))}
    except (ModelFileError, OSError) as exc:  # the flight and its log stand; only this copy is missing
        return {"learned_model_error": f"the learned model was not written: {exc}"}


class _NoLog:
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None:
        pass


class OnlineLearning:
    """Online learning for a ``Controller`` flown by any loop (another simulator, a ROS 2 node).

    Use it as ``with online_learning(controller, cfg) as learner:`` or, in a plug-in with no
    end-of-run hook, ``session = online_learning(controller, cfg); learner = session.start()`` and
    ``session.stop()`` (also run at interpreter exit if never called, so no trainer is left behind).

    ``start`` starts the trainer (the calling script needs an ``if __name__ == "__main__":`` guard),
    gives the controller an empty model slot if it has none, and watches its ticks: call
    ``controller.publish()`` once each command is sent (or let the next ``step`` do it).
    ``lockstep``: the caller's time is simulated (models apply no earlier than their honest training
    delay); False on a wall clock. ``ground_z``: the floor's height, below which (plus 0.1 m) no
    window is learned; None takes the controller's (``Controller.ground_z``: given, or the first
    state's height, with a warning). ``speed``: the gate's envelope speed (None: from the data).
    """

    def __init__(self, controller: Controller, cfg: Config, *, lockstep: bool = True, log: Any = None,
                 ground_z: float | None = None, speed: float | None = None) -> None:
        self._controller = controller
        self._cfg = dataclasses.replace(cfg, online=dataclasses.replace(cfg.online, enabled=True))
        self._lockstep, self._log, self._ground_z, self._speed = lockstep, log, ground_z, speed
        self._trainer: contextlib.ExitStack | None = None
        self.learner: OnlineLearner | None = None

    def start(self) -> OnlineLearner:
        """Start the trainer and attach the learner; returns it (its ``stats``, ``rounds``, ``swaps``)."""
        if self.learner is not None:
            return self.learner
        controller = self._controller
        if controller.model is None:
            controller.model = ModelSlot(None, version=0)
        stack = contextlib.ExitStack()
        trainer = stack.enter_context(start_trainer(self._cfg))
        ground_z = self._ground_z if self._ground_z is not None else controller.ground_z
        if ground_z is None:
            warnings.warn("online_learning: no ground_z given and the controller has not seen a state yet, so "
                          "windows are learned at any height; pass ground_z=<floor height>", stacklevel=3)
        self.learner = OnlineLearner(learner_settings(self._cfg, self._lockstep, ground_z, self._speed),
                                     controller.model, trainer, self._log if self._log is not None else _NoLog())
        controller.observers.append(self.learner)
        self._trainer = stack
        atexit.register(self.stop)
        return self.learner

    def stop(self) -> None:
        """Detach the learner and stop the trainer (the last model swapped in stays in the slot)."""
        if self.learner is None or self._trainer is None:
            return
        atexit.unregister(self.stop)
        try:
            self._controller.publish()
        finally:
            if self.learner in self._controller.observers:
                self._controller.observers.remove(self.learner)
            stack, self._trainer = self._trainer, None
            self.learner = None  # a later start() starts a trainer and learner of its own
            stack.close()

    def __enter__(self) -> OnlineLearner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def online_learning(controller: Controller, cfg: Config, *, lockstep: bool = True, log: Any = None,
                    ground_z: float | None = None, speed: float | None = None) -> OnlineLearning:
    """Online learning for ``controller``: a ``with`` block, or ``start()`` / ``stop()`` (``OnlineLearning``)."""
    return OnlineLearning(controller, cfg, lockstep=lockstep, log=log, ground_z=ground_z, speed=speed)


__all__ = [
    "attitude_lag_identifier",
    "check_online",
    "OnlineLearning",
    "online_learning",
    "gate_limits",
    "learner_settings",
    "online_model_slot",
    "online_session",
    "start_trainer",
    "trainer_settings",
]
