"""The neighbour input (docs/fleet.md#neighbour-input): the input layout, the model file's metadata, the
linearisation with the neighbour as a known parameter, the board the fleet shares, and the recorded windows."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.app.mission import refuse_neighbour_mismatch
from cfknode.flight.learning.windows import WindowRecorder
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.neighbours import NONE_ABOVE, NeighbourBoard
from cfknode.models.knode import KnodeQueue, from_torch_queue, residual_numpy
from cfknode.models.modelfile import (
    INPUT_NAMES,
    NEIGHBOUR_INPUT_NAMES,
    ModelFileError,
    load_model,
    save_model,
)
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.training import Segment, fit_normalisation, make_dataset, train_new_model
from test_residual_np import random_queue


def neighbour_queue(n_in: int = 9, seed: int = 0) -> KnodeQueue:
    return random_queue(2, "tanh", (16, 16), 3, seed, n_in=n_in)


def points(n: int = 7, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 6)), rng.normal(size=(n, 3)) * 3.0, rng.normal(size=(n, 3)) * 0.4


def test_the_layout_is_recorded_and_a_model_without_the_neighbour_keeps_the_old_one(tmp_path):
    with_nb, without = from_torch_queue(neighbour_queue(9)), from_torch_queue(neighbour_queue(6))
    assert with_nb.inputs == NEIGHBOUR_INPUT_NAMES and with_nb.takes_neighbour
    assert without.inputs == INPUT_NAMES and not without.takes_neighbour
    for name, mf in (("nb.knode", with_nb), ("plain.knode", without)):
        back = load_model(save_model(tmp_path / name, mf))
        assert back.inputs == mf.inputs
        assert np.array_equal(back.networks[0].layers[0][0], mf.networks[0].layers[0][0])
    x, u, nb = points()
    a, b = ResidualQueue.from_model_file(without), ResidualQueue.from_model_file(load_model(tmp_path / "plain.knode"))
    assert not a.takes_neighbour and np.array_equal(a.evaluate(x, u), b.evaluate(x, u))


def test_a_file_whose_layout_disagrees_with_its_weights_is_refused_in_one_line(tmp_path):
    import dataclasses

    mf = dataclasses.replace(from_torch_queue(neighbour_queue(9)), inputs=INPUT_NAMES)
    with pytest.raises(ModelFileError) as err:
        save_model(tmp_path / "bad.knode", mf)
    assert "\n" not in str(err.value) and "layer 0" in str(err.value)
    with pytest.raises(ModelFileError):
        save_model(tmp_path / "bad2.knode", dataclasses.replace(mf, inputs=("vx", "vy")))


def test_numpy_matches_torch_with_the_relative_position_beside_the_command():
    q = neighbour_queue(9)
    rq = ResidualQueue.from_model_file(from_torch_queue(q))
    x, u, nb = points()
    torch_r = residual_numpy(q, x, np.concatenate((u, nb - x[:, 0:3]), axis=1))
    assert np.allclose(rq.evaluate(x, u, nb), torch_r, atol=1e-12)


def test_the_linearisation_holds_the_neighbour_and_differentiates_the_own_position():
    rq = ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(9)))
    x, u, nb = points()
    c, jx, ju = rq.linearise(x, u, nb)
    r = rq.evaluate(x, u, nb)
    affine = c + np.einsum("nij,nj->ni", jx, x) + np.einsum("nij,nj->ni", ju, u)
    assert np.allclose(affine, r, atol=1e-12)  # exact at the nodes
    eps = 1e-6
    for k in range(6):  # position and velocity columns by central differences, the neighbour held
        dx = np.zeros(6)
        dx[k] = eps
        fd = (rq.evaluate(x + dx, u, nb) - rq.evaluate(x - dx, u, nb)) / (2 * eps)
        assert np.allclose(jx[:, :, k], fd, atol=1e-7)
    assert np.abs(jx[:, :, 0:3]).max() > 1e-3  # the wake depends on where the drone is under it
    # Moving with the neighbour changes nothing: -dr/dp is dr/dd.
    shift = np.array([0.03, -0.02, 0.01])
    moved = x.copy()
    moved[:, 0:3] += shift
    assert np.allclose(rq.evaluate(moved, u, nb + shift), r, atol=1e-12)


def test_without_a_neighbour_position_the_stand_in_is_held_and_position_stays_out():
    mf = from_torch_queue(neighbour_queue(9))
    rq = ResidualQueue.from_model_file(mf)
    x, u, _ = points()
    c, jx, ju = rq.linearise(x, u)
    assert np.array_equal(jx[:, :, 0:3], np.zeros_like(jx[:, :, 0:3]))
    stand_in = mf.networks[-1].normalisation.input_mean[6:9]
    assert np.allclose(rq.evaluate(x, u), rq.evaluate(x, u, x[:, 0:3] + stand_in), atol=1e-12)
    assert np.allclose(c + np.einsum("nij,nj->ni", jx, x) + np.einsum("nij,nj->ni", ju, u), rq.evaluate(x, u))


class _Ref:
    def sample(self, t):
        t = np.asarray(t, dtype=float)
        return SimpleNamespace(p=np.stack((0.5 * t, np.zeros_like(t), np.ones_like(t)), axis=1))


def test_the_board_gives_the_nearest_drone_above_and_moves_it_along_its_reference():
    board = NeighbourBoard([_Ref(), _Ref(), _Ref()], period=0.01, node_dt=0.05, nodes=4)
    board.update(0, 1.0, np.array([0.0, 0.0, 0.5]))
    board.update(1, 1.0, np.array([0.1, 0.0, 1.0]))  # above drone 0
    board.update(2, 1.0, np.array([0.0, 0.0, 2.0]))  # higher and further
    feed0, feed1 = board.feed(0), board.feed(1)
    assert np.allclose(feed0.relative(np.array([0.0, 0.0, 0.5])), [0.1, 0.0, 0.5])
    assert np.allclose(feed1.relative(np.array([0.1, 0.0, 1.0])), [-0.1, 0.0, 1.0])
    assert np.array_equal(board.feed(2).relative(np.array([0.0, 0.0, 2.0])), NONE_ABOVE)
    assert np.allclose(feed0.above(np.array([0.0, 0.0, 0.5])), [0.1, 0.0, 1.0])  # where it is (the layer's view)
    assert board.feed(2).above(np.array([0.0, 0.0, 2.0])) is None
    nodes = np.tile([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], (4, 1))
    nb = feed0.horizon(nodes)
    # From this tick (1.0 + one period) on, 0.5 m/s along x: the reference's displacement, from where it was seen.
    assert np.allclose(nb[:, 0], 0.1 + 0.5 * (0.01 + 0.05 * np.arange(4)))
    assert np.allclose(nb[:, 1:], [[0.0, 1.0]] * 4)
    assert board.feed(2).horizon(nodes + [0, 0, 1.5, 0, 0, 0]) is None


def test_a_plan_that_starts_ahead_takes_the_drone_above_as_far_ahead():
    # With estimator.command_delay the MPC plans from the state predicted that far ahead: its nodes are later than
    # the measured state, so the drone above is taken later too (0.1 s at 0.4 m/s is 4 cm, most of a 6 cm jet);
    # the fast layer's view of the model, at the measured state, takes it where it is now.
    board = NeighbourBoard([_Ref(), _Ref()], period=0.01, node_dt=0.05, nodes=3, lead=0.1)
    board.update(0, 1.0, np.array([0.0, 0.0, 0.5]))
    board.update(1, 1.0, np.array([0.1, 0.0, 1.0]))
    nodes = np.tile([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], (3, 1))
    assert np.allclose(board.feed(0).horizon(nodes)[:, 0], 0.1 + 0.5 * (0.01 + 0.1 + 0.05 * np.arange(3)))
    assert np.allclose(board.feed(0).horizon(nodes[:1], measured=True)[:, 0], 0.1 + 0.5 * 0.01)
    slot = ModelSlot(ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(9))))
    slot.neighbour = board.feed(0)
    x, u = nodes, np.zeros((3, 3))
    slot.residual(x, u)
    assert np.isclose(slot.last_neighbour[0], 0.1 + 0.5 * 0.11)
    at = slot.residual_at(x[0], u[0])
    assert at.c.shape == (1, 3) and np.isclose(slot.last_neighbour[0], 0.1 + 0.5 * 0.01)


def test_the_fleets_board_leads_by_the_command_delay():
    from cfknode.app.fleet.flight import neighbour_board

    cfg = load_config(overrides={"fleet.neighbour_input": True, "estimator.command_delay": 0.08})
    board = neighbour_board(cfg, [_Ref(), _Ref()], [ModelSlot(None), ModelSlot(None)])
    assert board is not None and board.lead == 0.08
    assert neighbour_board(load_config(overrides={"fleet.neighbour_input": True}), [_Ref()], [ModelSlot(None)]).lead == 0.0


def _pair(above_x: float):
    """Drone 0 at 0.5 m, drone 1 0.5 m above it and ``above_x`` aside; drone 0's nodes and commands."""
    board = NeighbourBoard([_Ref(), _Ref()], period=0.01, node_dt=0.05, nodes=3)
    board.update(0, 0.0, np.array([0.0, 0.0, 0.5]))
    board.update(1, 0.0, np.array([above_x, 0.0, 1.0]))
    x, u, _ = points(3)
    x[:, 0:3] = [0.0, 0.0, 0.5]
    return board, x, u


def test_the_slot_passes_the_neighbour_only_to_a_model_that_takes_it():
    board, x, u = _pair(0.0)
    nb_model = ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(9)))
    plain = ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(6)))
    for model in (nb_model, plain):
        slot = ModelSlot(model)
        alone = slot.residual(x, u)
        slot.neighbour = board.feed(0)
        fed = slot.residual(x, u)
        assert (np.abs(fed.jx[:, :, 0:3]).max() > 0) == model.takes_neighbour
        if not model.takes_neighbour:
            assert np.array_equal(fed.c, alone.c) and np.array_equal(fed.jx, alone.jx)


def test_the_slot_notes_where_the_drone_above_is_while_nothing_flown_sees_it():
    """A first swap to a model of the neighbour is re-based at the neighbour's real positions: flying nominal (or a
    model without the input), the slot still notes where the drone above was; with none above, the stand-in gap."""
    board, x, u = _pair(0.04)
    plain = ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(6)))
    for model in (None, plain):
        slot = ModelSlot(model)
        slot.residual(x, u)
        assert slot.last_neighbour is None  # no feed: nothing to note
        slot.neighbour = board.feed(0)
        slot.residual(x, u)
        assert np.allclose(slot.last_neighbour, [0.04, 0.0, 1.0])
        slot.neighbour = board.feed(1)  # drone 1 has none above it
        slot.residual(np.tile([0.04, 0.0, 1.0, 0.0, 0.0, 0.0], (3, 1)), u)
        assert np.allclose(slot.last_neighbour, np.array([0.04, 0.0, 1.0]) + NONE_ABOVE)


def _tick(t, p):
    est = SimpleNamespace(p=np.array(p, dtype=float), v=np.zeros(3))
    return SimpleNamespace(t=t, est=est, acc=np.zeros(3), source="mpc", model_version=0, compute_s=0.0)


def test_windows_record_the_relative_position_and_training_takes_it():
    board = NeighbourBoard([_Ref(), _Ref()], period=0.01, node_dt=0.05, nodes=3)
    rec = WindowRecorder(0.5, 100.0, ground_z=0.0, neighbour=board.feed(0))
    plain = WindowRecorder(0.5, 100.0, ground_z=0.0)
    window = none = None
    for k in range(60):
        t = 0.01 * k
        board.update(1, t, [0.02 * np.sin(t), 0.0, 1.0])
        tick = _tick(t, [0.0, 0.0, 0.5])
        window = rec.add(tick) or window
        none = plain.add(tick) or none
    assert window is not None and none is not None and none.nb is None
    assert window.nb.shape == (window.t.shape[0], 3)
    assert np.allclose(window.nb[:, 2], 0.5) and np.allclose(window.nb[:, 0], 0.02 * np.sin(window.t))
    assert window.inputs.shape == (window.t.shape[0], 6)
    # A residual that depends on the neighbour's offset only: the network learns on (v, u, d).
    t = np.arange(200) * 0.01
    d = np.stack((0.05 * np.sin(3 * t), np.zeros_like(t), 0.5 + 0 * t), axis=1)
    vz = np.cumsum(-2.0 * np.exp(-d[:, 0] ** 2 / (2 * 0.03**2))) * 0.01
    x = np.zeros((200, 6))
    x[:, 5] = vz
    x[:, 2] = np.cumsum(vz) * 0.01
    data = make_dataset([Segment(t, x, np.concatenate((np.zeros((200, 3)), d), axis=1))], 0.0)
    norm = fit_normalisation(data)
    assert norm.input_mean.shape == (9,) and norm.input_scale[6] >= 0.05
    cfg = load_config()
    training = cfg.training.__class__(**{**cfg.training.__dict__, "epochs": 5})
    queue, result = train_new_model(data, cfg.knode, training)
    assert from_torch_queue(queue).takes_neighbour and np.isfinite(result.loss)


def test_a_model_with_the_wrong_layout_for_the_flight_is_refused_in_one_line():
    nb_file, plain_file = from_torch_queue(neighbour_queue(9)), from_torch_queue(neighbour_queue(6))
    single = load_config(overrides={"controller.model": "m.knode"})
    fleet = load_config(overrides={"controller.model": "m.knode", "fleet.size": 2, "online.enabled": True,
                                   "fleet.neighbour_input": True})
    for cfg, mf, words in ((single, nb_file, "takes the neighbour input"), (fleet, plain_file, "has no neighbour")):
        with pytest.raises(ConfigError) as err:
            refuse_neighbour_mismatch(cfg, mf)
        assert words in str(err.value) and "\n" not in str(err.value)
    refuse_neighbour_mismatch(single, plain_file)  # a single drone flies its model as before
    refuse_neighbour_mismatch(fleet, nb_file)
    off = load_config(overrides={"controller.model": "m.knode", "fleet.size": 2, "online.enabled": True,
                                 "fleet.neighbour_input": False})
    refuse_neighbour_mismatch(off, plain_file)


def test_the_gate_and_the_monitor_judge_with_the_recorded_relative_position():
    from cfknode.flight.learning.gate import gate_pairs, rollout_rmse
    from cfknode.flight.learning.monitor import mean_acceleration_error

    rq = ResidualQueue.from_model_file(from_torch_queue(neighbour_queue(9)))
    n = 120
    t = np.arange(n) * 0.0025
    d = np.stack((0.1 * np.sin(8 * t), 0.05 * np.cos(5 * t), 0.5 + 0 * t), axis=1)
    u = np.zeros((n, 3))
    x = np.zeros((n, 6))
    for k in range(n - 1):  # the plant is exactly nominal + the model with the neighbour at d
        a = u[k] + rq.evaluate(x[k : k + 1], u[k : k + 1], x[k : k + 1, 0:3] + d[k])[0]
        x[k + 1, 3:6] = x[k, 3:6] + 0.0025 * a
        x[k + 1, 0:3] = x[k, 0:3] + 0.0025 * x[k, 3:6]
    with_d, without = gate_pairs(t, x, u, 0.0, d), gate_pairs(t, x, u, 0.0)
    assert with_d.nb is not None and without.nb is None
    assert rollout_rmse(rq, with_d, 5) < 0.2 * rollout_rmse(rq, without, 5)
    e_with = np.linalg.norm(mean_acceleration_error(rq, t, x[:, 3:6], u, d))
    e_without = np.linalg.norm(mean_acceleration_error(rq, t, x[:, 3:6], u))
    assert e_with < 0.2 * e_without
