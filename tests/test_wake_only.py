"""A fleet drone's networks that see the neighbour alone (``fleet.wake_only``, docs/fleet.md#wake-only): the
trainer switches the drone's own inputs and the horizontal outputs off, the MPC flies the result as a known
force at each node, the layer's steps cut no window, the recorder learns while tracking on what the thrust sent
did, a swap re-bases the layer where the drone above was, and on the crossing the learned wake flies below the
fast layer alone."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from cfknode.app.config import ConfigError, load_config, packaged_settings, with_defaults
from cfknode.app.learning import check_online, learner_settings, trainer_settings
from cfknode.flight.adaptation.layer import FastAdaptation, LoopExtras
from cfknode.flight.adaptation.loop import where_flown
from cfknode.flight.adaptation.observer import rebase_offset
from cfknode.flight.adaptation.settings import settings_from_controller
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.windows import WakeOnly, WindowRecorder, flown_command
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.neighbours import NONE_ABOVE
from cfknode.models.knode import from_torch_queue
from cfknode.models.modelfile import MASKED_INPUT_SCALE, WAKE_INPUT_NAMES, Normalisation, load_model, save_model
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import TrainerSettings, TrainRequest, Window, _train, online_normalisation
from fakes import ListLog
from test_residual_np import random_queue

PROFILE = Path(__file__).parent.parent / "examples" / "learning-in-a-wake.yaml"


def _crossing_window(n: int = 1600, dt: float = 0.0025) -> Window:
    """Back and forth under a drone 0.3 m above, with a 2 m/s^2 jet 6 cm wide on the vertical, and a closed loop's
    answer to it: the vertical command rises with the wake, so the command alone would explain it too."""
    t = np.arange(n) * dt
    px = 0.3 * np.sin(2.0 * t)
    wake = -2.0 * np.exp(-px**2 / (2 * 0.06**2))
    u = np.zeros((n, 3))
    u[:, 0] = -1.2 * np.sin(2.0 * t)
    u[:, 2] = -0.8 * wake  # the controller answers most of the force
    x = np.zeros((n, 6))
    x[:, 0], x[:, 3] = px, 0.6 * np.cos(2.0 * t)
    x[:, 2] = 1.0
    for k in range(n - 1):
        x[k + 1, 5] = x[k, 5] + dt * (u[k, 2] + wake[k])
        x[k + 1, 2] = x[k, 2] + dt * x[k, 5]
    nb = np.column_stack((-px, np.zeros(n), 1.3 - x[:, 2]))
    return Window(1, t, x, u, 0, nb)


def _settings(wake_only: bool) -> TrainerSettings:
    cfg = load_config()
    training = dataclasses.replace(cfg.training, epochs=150, lr=0.01, weight_decay=0.01, method="euler",
                                   velocity_filter_hz=8.0)
    return TrainerSettings(cfg.knode, training, True, cfg.online.inject, wake_only=wake_only)


def test_the_own_inputs_are_switched_off_only_with_the_neighbour_input():
    fitted = Normalisation(np.zeros(9), np.full(9, 0.1), np.ones(3))
    masked = online_normalisation(fitted, wake_only=True)
    assert np.all(masked.input_scale[:6] == MASKED_INPUT_SCALE) and np.allclose(masked.input_scale[6:], 0.1)
    assert np.allclose(masked.output_scale, [1.0 / MASKED_INPUT_SCALE, 1.0 / MASKED_INPUT_SCALE, 1.0])
    plain = Normalisation(np.zeros(6), np.full(6, 0.1), np.ones(3))
    assert np.array_equal(online_normalisation(plain, wake_only=True).input_scale, online_normalisation(plain).input_scale)


def test_a_wake_only_round_learns_the_wake_from_the_neighbour_alone():
    window = _crossing_window()
    out = _train(TrainRequest(1, 1, window, (), None, 0.0), _settings(True))
    rq = ResidualQueue.from_model_file(out.model)
    assert rq.takes_neighbour and rq.wake_only
    x, u = window.x[::40], window.u[::40]
    p_nb = x[:, 0:3] + window.nb[::40]
    r = rq.evaluate(x, u, p_nb)
    # The drone's own velocity and command change nothing; where the drone above is changes everything.
    moved = rq.evaluate(x + [0, 0, 0, 0.5, -0.3, 0.4], u + [1.0, -1.0, 2.0], p_nb)
    assert np.allclose(moved, r, atol=1e-6)
    assert np.abs(r[:, 0:2]).max() < 1e-6  # the wake acts downward: nothing on x and y
    under = rq.evaluate(np.array([[0, 0, 1.0, 0, 0, 0]]), np.zeros((1, 3)), np.array([[0, 0, 1.3]]))[0, 2]
    aside = rq.evaluate(np.array([[0, 0, 1.0, 0, 0, 0]]), np.zeros((1, 3)), np.array([[0.25, 0, 1.3]]))[0, 2]
    assert under < aside - 1.0  # most of the 2 m/s^2 jet, from the relative position alone
    # The same round with the own inputs explains the jet by the command that answered it (measured: -1.1).
    plain = ResidualQueue.from_model_file(_train(TrainRequest(1, 1, window, (), None, 0.0), _settings(False)).model)
    _, _, ju = plain.linearise(x, u, p_nb)
    assert not plain.wake_only and ju[:, 2, 2].mean() < -0.5


def test_a_wake_network_sees_the_drone_above_about_its_axis(tmp_path):
    """A crossing's first window holds one side of the line: given the signed relative position, the network flew
    the other side by extrapolation. About the drone above's axis both sides are the same input."""
    full = _crossing_window()
    k = int(np.pi / 2 / 2.0 / 0.0025)  # a quarter swing: the drone on one side only
    one_side = Window(1, full.t[:k], full.x[:k], full.u[:k], 0, full.nb[:k])
    assert np.all(one_side.nb[:, 0] <= 0.0)
    out = _train(TrainRequest(1, 1, one_side, (), None, 0.0), _settings(True))
    assert out.model.inputs == WAKE_INPUT_NAMES
    save_model(tmp_path / "wake.safetensors", out.model)
    loaded = load_model(tmp_path / "wake.safetensors")
    assert loaded.inputs == WAKE_INPUT_NAMES
    rq = ResidualQueue.from_model_file(loaded)
    here = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])

    def wake(dx: float, dy: float = 0.0) -> float:
        return float(rq.evaluate(here, np.zeros((1, 3)), here[:, 0:3] + [dx, dy, 0.3])[0, 2])

    assert wake(0.0) < wake(-0.25) - 1.0  # the jet, learned on the side it saw
    assert wake(0.1) == wake(-0.1) == wake(0.0, 0.1) and wake(0.25) == wake(-0.25)  # and the same on the others


def test_a_wake_only_queue_is_flown_as_a_known_force_at_each_node():
    window = _crossing_window()
    rq = ResidualQueue.from_model_file(_train(TrainRequest(1, 1, window, (), None, 0.0), _settings(True)).model)
    x, u = window.x[::100], window.u[::100]
    p_nb = x[:, 0:3] + window.nb[::100]
    c, jx, ju = rq.linearise(x, u, p_nb)
    assert np.abs(jx).max() < 1e-6 and np.abs(ju).max() < 1e-6  # no slope: not in the position, nor elsewhere
    assert np.allclose(c, rq.evaluate(x, u, p_nb), atol=1e-6)


def test_a_network_that_saw_the_own_inputs_is_not_warm_started_into_a_wake_only_one():
    base = from_torch_queue(random_queue(1, "tanh", (32, 32), 3, 0, n_in=9))
    assert not ResidualQueue.from_model_file(base).wake_only
    out = _train(TrainRequest(2, 2, _crossing_window(), (), base, 0.0), _settings(True))
    assert np.all(out.model.networks[-1].normalisation.input_scale[:6] == MASKED_INPUT_SCALE)
    # Not even kept beside it: its d is signed, a wake network's is about the axis, and a queue has one layout.
    assert len(out.model.networks) == 1 and out.model.inputs == WAKE_INPUT_NAMES
    newest = ResidualQueue.from_model_file(dataclasses.replace(out.model, networks=out.model.networks[-1:]))
    assert newest.wake_only


def _tick(t: float, stepping: bool, scale: float):
    est = SimpleNamespace(p=np.array([0.0, 0.0, 1.0]), v=np.zeros(3), q=np.array([1.0, 0.0, 0.0, 0.0]))
    layer = SimpleNamespace(stepping=stepping, thrust_scale=scale, frozen=False)
    return SimpleNamespace(t=t, est=est, acc=np.zeros(3), source="mpc", model_version=0, compute_s=0.0, layer=layer,
                           setpoint=SimpleNamespace(thrust=40000))


def test_the_layers_steps_and_settling_cut_no_window_of_a_wake_only_recorder():
    feed = SimpleNamespace(relative=lambda p: np.array([0.0, 0.0, 0.3]))
    kept, cut = (WindowRecorder(0.5, 100.0, ground_z=0.0, neighbour=feed, wake_only=w) for w in (WakeOnly(9.81, 1e-4), None))
    for k in range(120):  # a pass: the layer alarms and its thrust scale moves by 10 %
        tick = _tick(0.01 * k, stepping=40 <= k < 60, scale=1.0 + 0.1 * k / 120)
        kept.add(tick)
        cut.add(tick)
    assert kept.windows == 2 and kept.unsettled == 0
    assert cut.windows == 0


def test_a_wake_only_recorder_records_what_the_thrust_sent_did():
    """The Mellinger layer sends the layer's thrust scale times the thrust the MPC asked for, along an attitude the
    attitude loop reaches late. A layer that took a wake's mean for a mass (thrust scale 1.2, the vehicle's own mass
    nominal) put 0.2 (u + g) into a target recorded against the MPC's command, where there is no wake; recorded as
    what the thrust sent gives the nominal mass along the measured attitude, the target holds nothing."""
    cfg = load_config()
    g, per_cmd = cfg.vehicle.gravity, cfg.vehicle.newton_per_cmd / cfg.vehicle.mass
    wake_only = WakeOnly(g, per_cmd)
    feed = SimpleNamespace(relative=lambda p: np.array([0.25, 0.0, 0.2]))  # beside the jet: no wake here
    wake, plain = (WindowRecorder(0.5, 100.0, ground_z=0.0, neighbour=feed, wake_only=w) for w in (wake_only, None))
    acc, scale = np.array([0.0, 0.0, -1.5]), 1.2
    tick = _tick(1.0, stepping=False, scale=scale)
    tick.acc = acc
    tick.setpoint = SimpleNamespace(thrust=scale * (acc[2] + g) / per_cmd)  # level: the thrust the layer sends
    wake.add(tick)
    plain.add(tick)
    flown = scale * (acc + [0.0, 0.0, g]) - [0.0, 0.0, g]  # what a vehicle of the nominal mass does
    assert np.allclose(wake.last_u, flown)
    assert np.allclose(plain.last_u, acc) and (flown - plain.last_u)[2] == pytest.approx(0.2 * (g - 1.5))
    # Tilted 10 degrees about y, the thrust's vertical share drops and a horizontal one appears.
    half = np.radians(10.0) / 2
    tilted = flown_command(g / per_cmd, np.array([np.cos(half), 0.0, np.sin(half), 0.0]), wake_only)
    assert tilted[0] == pytest.approx(g * np.sin(2 * half)) and tilted[2] == pytest.approx(g * (np.cos(2 * half) - 1))


def _jet(x: np.ndarray, nb: np.ndarray | None) -> np.ndarray:
    """A wake model's vertical force, 2.8 m/s^2 in a jet 6 cm wide; without a neighbour position: at its stand-in,
    straight under (the mean of a crossing's training data)."""
    d = np.tile([0.0, 0.0, 0.2], (x.shape[0], 1)) if nb is None else nb - x[:, 0:3]
    out = np.zeros((x.shape[0], 3))
    out[:, 2] = -2.8 * np.exp(-(d[:, 0] ** 2 + d[:, 1] ** 2) / (2 * 0.06**2))
    return out


class _WakeModel:
    takes_neighbour = True

    def evaluate(self, x, u, nb=None):
        return _jet(x, nb)

    def linearise(self, x, u, nb=None):
        return _jet(x, nb), np.zeros((x.shape[0], 3, 6)), np.zeros((x.shape[0], 3, 3))


def test_a_swap_rebases_the_layer_where_the_drone_above_was():
    """The layer's recent ticks keep the neighbour position the flying model saw; a new model is judged there. At
    its stand-in instead, a wake model predicted the jet's peak on every tick, and the swap moved it into the
    layer's constant (the offset jumped 0.7 m/s^2 after a pass, and the model monitor dropped the model)."""
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    layer = FastAdaptation(settings_from_controller(cfg.controller), 400.0, 9.81)
    upper = np.array([0.0, 0.0, 1.2])
    model = _WakeModel()
    for k in range(200):  # hovering 0.25 m beside the drone above, then half the ticks with no neighbour given
        x = np.array([0.25, 0.0, 1.0, 0.0, 0.0, 0.0])
        nb = upper if k < 150 else None
        a = _jet(x[None], None if nb is None else nb[None])[0]
        layer.update(k / 400.0, np.zeros(3), x, np.zeros(3), a, (False, False), True, LoopExtras(neighbour=nb))
    recent = layer.recent()
    given = np.all(np.isfinite(recent.neighbour), axis=1)
    assert given.sum() == 50 and np.allclose(recent.neighbour[given], upper)  # the newest 100 ticks (0.25 s)
    new = where_flown(model.evaluate, model, recent.x, recent.u, recent.neighbour)
    assert np.allclose(new, recent.a)  # the same model: continuous, no shift
    assert np.allclose(rebase_offset(np.zeros(3), recent.a, new, 10.0), 0.0)
    lin = where_flown(model.linearise, model, recent.x, recent.u, recent.neighbour)
    assert np.allclose(lin[0], recent.a)
    blind = model.evaluate(recent.x, recent.u)  # the stand-in on every tick: the peak
    assert rebase_offset(np.zeros(3), recent.a, blind, 10.0)[2] > 1.0
    plain = SimpleNamespace(takes_neighbour=False)
    assert np.allclose(where_flown(model.evaluate, plain, recent.x, recent.u, recent.neighbour), blind)


def test_a_wake_only_recorder_learns_only_while_tracking():
    """In a take-off the drone's own climb and the floor change its force while the drone above seems to move with
    it; a network of the neighbour alone would learn them as wake."""
    feed = SimpleNamespace(relative=lambda p: np.array([0.0, 0.0, 0.3]))
    wake, plain = (WindowRecorder(0.5, 100.0, ground_z=0.0, neighbour=feed, wake_only=w) for w in (WakeOnly(9.81, 1e-4), None))
    for k in range(200):
        tick = _tick(0.01 * k, stepping=False, scale=1.0)
        tick.supervisor_state = "TAKEOFF" if k < 100 else "TRACK"
        wake.add(tick)
        plain.add(tick)
    assert plain.windows == 3 and wake.windows == 1  # 0.5 s windows: the 1 s of tracking holds one and a bit
    assert wake.fresh(0.0)[0][0] >= 1.0


def _wake_learner(above: dict):
    """A wake-only learner with a scripted trainer, and ``fly(seconds)``: tracking ticks with the drone above at
    ``above["d"]`` (a callable of the tick's index, or a fixed relative position)."""
    from test_online_learner import ScriptedTrainer, outcome_with

    cfg = _wake_drone(**{"fleet.size": 2, "online.enabled": True})
    settings = dataclasses.replace(learner_settings(cfg, True), replay_windows=2)
    k = 0
    slot = ModelSlot(None, version=0)
    slot.neighbour = SimpleNamespace(relative=lambda p: np.array(above["d"](k) if callable(above["d"]) else above["d"]))
    trainer = ScriptedTrainer(lambda req: outcome_with(None, req))
    learner = OnlineLearner(settings, slot, trainer, ListLog())

    def fly(seconds: float) -> None:
        nonlocal k
        for _ in range(int(round(seconds / settings.period))):
            tick = _tick(k * settings.period, stepping=False, scale=1.0)
            tick.supervisor_state, tick.source, tick.guarded, tick.saturated = "TRACK", "mpc", False, False
            learner.on_tick(tick)
            k += 1

    return learner, trainer, fly, settings.t_col


def test_a_drone_with_nothing_above_sends_no_round_and_one_that_was_under_a_drone_does():
    """A fleet's top drone has no wake to learn: its rounds would only take the shared trainer from the drones
    below (on the 7-pass crossing they doubled the flight's wall time, and every one was rejected)."""
    above = {"d": NONE_ABOVE}
    learner, trainer, fly, t_col = _wake_learner(above)
    fly(3 * t_col + 0.1)
    assert learner.recorder.windows == 3 and trainer.requests == []
    assert learner.stats.windows_no_drone_above == 3 and learner.summary_fields()["windows_no_drone_above"] == 3
    above["d"] = np.array([0.1, 0.0, 0.3])  # a drone comes over for a moment: that window is sent
    fly(0.05)
    above["d"] = NONE_ABOVE
    fly(t_col)
    assert len(trainer.requests) == 1 and np.any(trainer.requests[0].window.nb != NONE_ABOVE)
    fly(t_col)  # the next window had nothing above, but its replay holds the pass: sent too
    assert len(trainer.requests) == 2 and not np.any(trainer.requests[1].window.nb != NONE_ABOVE)
    assert learner.stats.windows_one_point_above == 0


def test_a_drone_that_stays_at_one_point_of_the_wake_sends_no_round_until_the_drone_above_moves():
    """A stacked pair on one pattern: the drone above wanders 2 cm about one point 0.5 m up, on every side. A network
    learns only a constant there (the layer's) and predicts the wake on after the drone above has gone."""
    rng = np.random.default_rng(0)
    above = {"d": lambda k: np.array([0.01 * np.cos(0.01 * k), 0.01 * np.sin(0.01 * k), 0.5]) + rng.uniform(-0.005, 0.005, 3)}
    learner, trainer, fly, t_col = _wake_learner(above)
    fly(3 * t_col + 0.1)
    assert learner.recorder.windows == 3 and trainer.requests == []
    assert learner.stats.windows_one_point_above == 3 and learner.summary_fields()["windows_one_point_above"] == 3
    assert learner.summary_fields()["online_wake_only"]  # the fleet's summary line says "wake models"
    assert learner.stats.windows_no_drone_above == 0
    above["d"] = lambda k: np.array([0.002 * (k % 400), 0.0, 0.5])  # it flies off sideways, 0.8 m in a second
    fly(t_col)
    assert len(trainer.requests) == 1


def test_wake_only_without_the_neighbour_input_is_refused_in_one_line():
    cfg = load_config(overrides={"fleet.size": 2, "fleet.wake_only": True})
    with pytest.raises(ConfigError) as err:
        check_online(cfg)
    assert "fleet.neighbour_input" in str(err.value) and "\n" not in str(err.value)


def test_the_profile_sets_wake_only_for_a_fleet_and_nothing_for_one_drone():
    overrides = _flat(yaml.safe_load(PROFILE.read_text()))
    fleet = _wake_drone(**{"fleet.size": 2, "online.enabled": True})
    one = load_config(overrides={**overrides, "online.enabled": True})
    assert trainer_settings(fleet).wake_only and learner_settings(fleet, True).wake_only
    assert not trainer_settings(one).wake_only and not learner_settings(one, True).wake_only
    assert learner_settings(fleet, True).command_lag_s == (0.015, 0.015)  # the thrust sent, through the motors' lag


def _wake_drone(**overrides) -> object:
    """A fleet drone's config as the fleet builds it for a drone learning a wake: the profile's switches, then the
    packaged wake settings wherever the config keeps the default (cfknode/app/fleet/wake_below.py)."""
    cfg = load_config(overrides={**_flat(yaml.safe_load(PROFILE.read_text())), **overrides})
    return with_defaults(cfg, packaged_settings("wake"))


def _flat(tree: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in tree.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def test_on_the_crossing_the_learned_wake_flies_below_the_layer_alone(tmp_path):
    from cfknode.app.bench.learning import Job, run_job
    from cfknode.app.bench.learning_cells import CELLS, CROSSING_RADIUS, line_duration

    # Seed 0, 5 passes, lockstep with a fixed latency: the same flights on any machine. 0.2 m under the drone
    # above, in the wake's strongest part: the cell the layer alone loses most in (pass 2 at 6x pass 1's error).
    cell = next(c for c in CELLS if c.name == "crossing dz=0.2 v=0.5")
    extra = tuple(_flat(yaml.safe_load(PROFILE.read_text())).items()) + (("safety.estop_dir", str(tmp_path / "e")),)
    duration = line_duration(CROSSING_RADIUS, cell.speed, 5)
    # The wake network's own share: the profile without the attitude loop's lag identified (planning ahead from the
    # switch on moves the flight's whole error, not the passes').
    wake_alone = extra + (("online.layer_attitude_lag", False),)
    layer, online, profile = (run_job(Job(cell, row, 0, str(tmp_path / name), duration, e, 0.1))
                              for row, name, e in (("layer", "layer", extra), ("online+layer", "wake", wake_alone),
                                                   ("online+layer", "profile", extra)))
    for run in (layer, online, profile):
        assert not run.fell and not run.tripped, run.outcome
    assert online.models_accepted >= 1 and profile.models_accepted >= 1
    # Measured (the networks see the drone above about its axis): passes 3-5 at 0.15 of the layer's, the flight at
    # 0.38, 2 models kept, the first at 6.5 s. Given the signed relative position the first network, fitted on one
    # side of the line, was turned away and the first swap came at 10.5 s (over 7 passes the flight flew 0.55).
    late = np.mean(online.passes[-3:]) / np.mean(layer.passes[-3:])
    assert late < 0.4 and online.mse < 0.5 * layer.mse, (late, online.mse, layer.mse)
    # The profile as shipped, the lag identified too (measured: passes 3-5 at 0.08, the flight at 0.60; over the
    # bench's 10 passes 0.36): below the layer by the learning cells' target of a quarter.
    late = np.mean(profile.passes[-3:]) / np.mean(layer.passes[-3:])
    assert late < 0.4 and profile.mse < 0.75 * layer.mse, (late, profile.mse, layer.mse)
