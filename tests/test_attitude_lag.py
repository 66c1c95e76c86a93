"""The attitude loop's lag, identified in flight: the fit, the identifier on ticks, the command path it retunes, and a
fast loop where planning across the identified lag takes most of the layer's error away."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.bench.learning import Job, run_job
from cfknode.app.bench.learning_cells import CELLS
from cfknode.app.config import load_config
from cfknode.app.learning import LEARNED_RESIDUAL_TAU, attitude_lag_identifier
from cfknode.app.logs.reader import read_log
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.flight.latency import CommandDelayPredictor
from cfknode.flight.learning.attitude_lag import (
    MIN_KEPT, AttitudeLagIdentifier, AttitudeLagSettings, fit_lag, lagged, sent_body_z,
)
from cfknode.flight.adaptation.loop import body_z_floats
from cfknode.flight.mellinger import force_to_setpoint
from cfknode.models.quadrotor import euler_zyx_to_quat, quat_to_euler_zyx

DT = 0.0025
G = 9.81


def _excitation(n: int, seed: int = 0) -> np.ndarray:
    """Horizontal commands (n, 2) as a loop and the controller's corrections give them: a few tones, 0.3-3 Hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    out = np.zeros((n, 2))
    for f in (0.3, 0.8, 1.7, 3.0):
        out += rng.normal(0.0, 1.0, 2) * np.sin(2.0 * math.pi * f * t[:, None] + rng.uniform(0, 2 * math.pi, 2))
    return out


def test_the_fit_finds_the_lag_beside_a_gain_and_an_offset() -> None:
    u = _excitation(800)
    rng = np.random.default_rng(1)
    flown = 0.95 * lagged(u, 0.15, DT) + np.array([0.1, -0.05]) + rng.normal(0.0, 0.02, u.shape)
    fit = fit_lag(np.arange(800) * DT, u, flown)
    assert fit.tau == pytest.approx(0.15, abs=0.01)
    assert fit.fit > 0.99 and fit.fit_none < fit.fit - 0.05


def test_a_response_without_lag_fits_no_better_with_one() -> None:
    u = _excitation(800, seed=2)
    fit = fit_lag(np.arange(800) * DT, u, u + np.random.default_rng(3).normal(0.0, 0.02, u.shape))
    assert fit.tau <= 0.03 and fit.fit - fit.fit_none < 0.05


@pytest.mark.parametrize("force", [(0.4, -0.2, 0.3), (-1.0, 0.5, 2.9), (0.0, 0.0, 1.0)])
@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_the_attitude_sent_is_read_back_as_the_force_s_direction(force: tuple, yaw: float) -> None:
    controller, vehicle = load_config().controller, load_config().vehicle
    q = (math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0))
    sp = force_to_setpoint(force, yaw, q, vehicle, controller)
    n = np.asarray(force) / np.linalg.norm(force)
    assert sent_body_z(sp.roll_deg, sp.pitch_deg, q) == pytest.approx((n[0], n[1]), abs=1e-9)


def test_the_attitude_sent_is_the_rotation_s_body_z_at_any_yaw_and_tilt() -> None:
    # sent_body_z is a closed form: against the quaternion of the same roll, pitch and measured yaw.
    rng = np.random.default_rng(4)
    for _ in range(500):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        roll, pitch = rng.uniform(-60.0, 60.0, 2)
        yaw = quat_to_euler_zyx(q)[2]
        want = body_z_floats(euler_zyx_to_quat(math.radians(roll), math.radians(pitch), yaw))
        assert sent_body_z(roll, pitch, q) == pytest.approx(want[:2], abs=1e-12)


def _attitude(zx: float, zy: float) -> tuple[float, float, float, float]:
    """A yaw-free quaternion whose body z axis has the world x and y given."""
    zz = math.sqrt(max(1.0 - zx * zx - zy * zy, 0.0))
    w = math.sqrt((1.0 + zz) / 2.0)
    return (w, -zy / (2.0 * w), zx / (2.0 * w), 0.0)


def _ticks(tau: float, seconds: float, scale: float = 1.0, state: str = "TRACK", layer=None):
    """Ticks of a vehicle whose attitude follows the one sent through a lag of ``tau`` s (0: at once); ``layer``:
    the fast layer's estimate each tick carries."""
    cfg = load_config()
    n = int(seconds / DT)
    u = scale * _excitation(n, seed=4)
    flown = lagged(u, tau, DT) if tau > 0.0 else u
    for k in range(n):
        acc = np.array([u[k, 0], u[k, 1], 0.0])
        thrust = float(np.linalg.norm(acc + [0.0, 0.0, G]))
        q = _attitude(flown[k, 0] / thrust, flown[k, 1] / thrust)
        sp = force_to_setpoint(acc + [0.0, 0.0, G], 0.0, q, cfg.vehicle, cfg.controller)
        yield SimpleNamespace(t=k * DT, est=SimpleNamespace(q=q), acc=acc, source="mpc", supervisor_state=state,
                              setpoint=sp, layer=layer)


class _Log:
    def __init__(self) -> None:
        self.events: list[dict] = []

    def write(self, topic: str, t: float, msg: dict) -> None:
        self.events.append({"topic": topic, "t": t, **msg})


def _identifier(path, slot=None) -> tuple[AttitudeLagIdentifier, _Log]:
    log = _Log()
    return AttitudeLagIdentifier(AttitudeLagSettings(1.0, 0.9, 0.45, 0.05), path, log, G, 400.0, slot), log


def test_the_identifier_retunes_the_command_path_to_the_lag_it_measured() -> None:
    path = CommandDelayPredictor(0.0)
    feed = SimpleNamespace(lead=None)
    slot = SimpleNamespace(neighbour=feed, vertical_lead=0.0)
    ident, log = _identifier(path, slot)
    ticks = list(_ticks(0.12, 6.0))
    for tick in ticks[: int((MIN_KEPT - 0.5) / DT)]:
        ident.on_tick(tick)
    assert not path.active and ident.flown is None  # fewer fits than it needs: nothing flown yet
    for tick in ticks[int((MIN_KEPT - 0.5) / DT):]:
        ident.on_tick(tick)
    assert path.active and path.lag == pytest.approx(0.12, abs=0.01)
    assert path.delay == pytest.approx(0.45 * path.lag) and path.delay_z == 0.0 and path.residual_tau == 0.05
    assert feed.lead == path.delay  # a fleet drone's drone above is taken as far ahead as the plan starts
    assert slot.vertical_lead == path.delay  # and a wake model's force where the drone is as the thrust acts
    assert len(log.events) == 1 and log.events[0]["topic"] == "/events" and "attitude loop lag" in log.events[0]["text"]
    fields = ident.summary_fields()
    assert fields["attitude_lag_s"] == path.lag and fields["attitude_lag_kept"] >= MIN_KEPT


def test_the_command_path_starts_from_the_force_the_layer_already_holds() -> None:
    # A wind the layer holds (0.3, -0.2) m/s^2 is in the plan from the switch on, not after a delay and a low-pass.
    path = CommandDelayPredictor(0.0)
    layer = SimpleNamespace(offset=np.array([0.3, -0.2, 0.8]))
    ident, _ = _identifier(path)
    for tick in _ticks(0.12, 6.0, layer=layer):
        ident.on_tick(tick)
    assert path.active and path.residual.tolist() == [0.3, -0.2, 0.0]  # the vertical has no delay: not its
    est = StateEstimate(t=10.0, p=np.zeros(3), v=np.zeros(3), q=np.array([1.0, 0.0, 0.0, 0.0]), yaw=0.0)
    path.note(10.0, np.zeros(3))
    ahead = path.ahead(est)
    d = path.delay
    assert ahead.p[:2] == pytest.approx([0.5 * 0.3 * d * d, -0.5 * 0.2 * d * d])  # the force over the delay
    assert ahead.v[:2] == pytest.approx([0.3 * d, -0.2 * d])


def test_without_a_layer_or_a_residual_model_the_command_path_starts_from_nothing() -> None:
    for start, tau in ((None, 0.05), ((0.3, -0.2), 0.0)):
        path = CommandDelayPredictor(0.0)
        path.retune(0.07, 0.15, tau, start)
        assert path.residual.tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("case", ["instant", "still", "landing"])
def test_the_identifier_flies_nothing_it_cannot_tell(case: str) -> None:
    path = CommandDelayPredictor(0.0)
    ident, log = _identifier(path)
    ticks = {"instant": _ticks(0.0, 6.0), "still": _ticks(0.12, 6.0, scale=0.01),
             "landing": _ticks(0.12, 6.0, state="LAND")}[case]
    for tick in ticks:
        ident.on_tick(tick)
    assert not path.active and ident.flown is None and log.events == []
    assert "attitude_lag_s" not in ident.summary_fields()


def test_retune_validates_and_starts_the_prediction_again() -> None:
    path = CommandDelayPredictor(0.0)
    path.note(0.0, np.zeros(3))
    path.retune(0.07, 0.15, 0.05)
    assert path.active and (path.delay, path.lag, path.delay_z, path.residual_tau) == (0.07, 0.15, 0.0, 0.05)
    est = SimpleNamespace(t=1.0, p=np.zeros(3), v=np.zeros(3))
    assert path.ahead(est) is est  # nothing sent since the retune: nothing to predict with
    with pytest.raises(ValueError, match="must be >= 0"):
        path.retune(-0.1, 0.15, 0.05)


def test_the_identifier_runs_beside_the_layer_with_online_learning_only() -> None:
    base = load_config()
    learner = SimpleNamespace(log=_Log(), attitude_lag=None)

    def made(cfg, who=learner) -> bool:
        return attitude_lag_identifier(cfg, who, VelocityEstimator(cfg.estimator), None) is not None

    assert made(base) and learner.attitude_lag is not None
    assert not made(base, None)  # no online learning
    assert not made(load_config(overrides={"online.layer_attitude_lag": False}))
    assert not made(load_config(overrides={"controller.adaptation": "none"}))  # the paper's online row: as the paper
    assert not made(load_config(overrides={"estimator.command_delay": 0.1}))  # the configuration gives the path
    assert LEARNED_RESIDUAL_TAU == 0.05


def test_on_a_fast_loop_planning_across_the_learned_lag_beats_the_layer_alone(tmp_path) -> None:
    """`circle r=0.3 v=1.5`, 6 s of the bench's cell, seed 0: the layer alone meets the attitude loop's lag with a
    position error; once the lag is identified (after three 1 s fits) the MPC plans across it."""
    cell = next(c for c in CELLS if c.name == "circle r=0.3 v=1.5")
    layer = run_job(Job(cell, "layer", 0, str(tmp_path), 6.0))
    online = run_job(Job(cell, "online+layer", 0, str(tmp_path), 6.0))
    for run in (layer, online):
        assert run.outcome.startswith("flight complete") and not run.fell and not run.tripped, run.outcome
    assert online.mse < 0.75 * layer.mse, (online.mse, layer.mse)  # 25 % lower at least
    logs = sorted(tmp_path.rglob("*online*.mcap"))
    said = [e["text"] for e in read_log(logs[-1]).topic("/events") if "attitude loop lag" in e["text"]]
    assert said, "no lag identified"
    lag_ms = float(said[0].split("attitude loop lag ")[1].split(" ms")[0])
    assert 110.0 <= lag_ms <= 200.0  # the simulated firmware's attitude loop (a flight's median: 0.14-0.16 s)


class _WakeModel:
    takes_neighbour = True

    def __init__(self, wake_only: bool) -> None:
        self.wake_only = wake_only
        self.seen: list[np.ndarray] = []

    def linearise(self, x_nodes, u_nodes, nb):
        self.seen.append(np.array(x_nodes))
        n = len(x_nodes)
        return np.zeros((n, 3)), np.zeros((n, 3, 6)), np.zeros((n, 3, 3))


class _Feed:
    def __init__(self) -> None:
        self.asked: list[tuple[np.ndarray, bool]] = []

    def horizon(self, x_nodes, measured=False):
        self.asked.append((np.array(x_nodes), measured))
        return np.zeros((len(x_nodes), 3)) + [0.0, 0.0, 0.3]

    def relative(self, p):
        return np.array([0.0, 0.0, 0.3])


@pytest.mark.parametrize("wake_only", [True, False])
def test_a_wake_only_model_is_taken_where_the_drone_is_when_the_thrust_acts(wake_only: bool) -> None:
    """The plan's horizontal nodes lead by the command delay; the thrust acts at once (``vertical_lead``)."""
    from cfknode.flight.model_slot import ModelSlot

    model = _WakeModel(wake_only)
    slot = ModelSlot(model, version=1)
    slot.neighbour = _Feed()
    x = np.zeros((4, 6))
    x[:, 0] = [0.0, 0.05, 0.10, 0.15]
    x[:, 3] = 1.0  # 1 m/s along x
    slot.residual(x, np.zeros((4, 3)))
    assert np.array_equal(model.seen[-1], x) and slot.neighbour.asked[-1][1] is False  # no lead: the plan's nodes
    slot.vertical_lead = 0.065
    slot.residual(x, np.zeros((4, 3)))
    if wake_only:
        assert model.seen[-1][:, 0] == pytest.approx(x[:, 0] - 0.065)  # 65 mm back along the track
        assert slot.neighbour.asked[-1][1] is True  # and the drone above where it is now, not the plan's lead later
    else:  # a model of the drone's own state too: its horizontal outputs fly with the plan
        assert np.array_equal(model.seen[-1], x) and slot.neighbour.asked[-1][1] is False
    slot.residual_at(x[0], np.zeros(3))
    assert np.array_equal(model.seen[-1], x[:1])  # at the measured state: as measured
