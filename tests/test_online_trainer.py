"""The online trainer (the paper's Algorithm 2): one round in-process, and the real trainer process with faults."""

from __future__ import annotations

import dataclasses
import math
import multiprocessing.forkserver
import os
import sys

import numpy as np
import pytest
import torch

from cfknode.app.config import FaultInjection, load_config
from cfknode.flight.learning import trainer_client
from cfknode.flight.learning.trainer_client import TrainerClient, TrainerFault, trainer_context
from cfknode.models.knode import KnodeQueue, to_torch_queue
from cfknode.models.modelfile import Normalisation
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import (
    CHILD_IMPORTS,
    CRASH_EXIT_CODE,
    TrainerReady,
    TrainOutcome,
    TrainRequest,
    Window,
    _train_round,
    renormalise,
)
from cfknode.app.learning import trainer_settings

RATE = 400.0


def window(residual: np.ndarray, index: int = 1, t0: float = 2.0, n: int = 201, version: int = 0, seed: int = 0) -> Window:
    """A 400 Hz window of v' = u + residual (noise-free velocities, a wandering command)."""
    t = t0 + np.arange(n) / RATE
    u = np.stack([0.8 * np.sin(4 * t), 0.6 * np.cos(3 * t), 0.5 * np.sin(6 * t + seed)], axis=1)
    v = np.zeros((n, 3))
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + residual) / RATE
    p = np.cumsum(v, axis=0) / RATE
    return Window(index, t, np.concatenate((p, v), axis=1), u, version)


@pytest.fixture(scope="module")
def settings():
    cfg = load_config(overrides={"online.enabled": True})
    return trainer_settings(cfg)


def test_renormalise_keeps_the_function() -> None:
    torch.manual_seed(0)
    queue = KnodeQueue((16, 16), "tanh", 3, Normalisation(np.zeros(6), np.ones(6), np.full(3, 0.5)))
    net = queue.push()
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.normal_(0.0, 0.5)
            layer.bias.normal_(0.0, 0.1)
    z = torch.randn(50, 6, dtype=torch.float64)
    before = net(z).detach().clone()
    renormalise(net, Normalisation(np.array([0.1, -0.2, 0.0, 1.0, 0.0, -4.9]), np.array([0.3, 0.4, 0.25, 1.5, 0.7, 2.0]),
                                   np.array([2.0, 3.0, 9.0])))
    torch.testing.assert_close(net(z), before, rtol=1e-12, atol=1e-12)
    assert float(net.output_scale[2]) == 9.0


def test_a_round_learns_the_residual_and_reports_its_metadata(settings) -> None:
    r = np.array([0.0, 0.0, 4.9])  # half the mass: the commanded acceleration falls 4.9 m/s^2 short... upwards
    w = window(r, version=0)
    out = _train_round(TrainRequest(1, 1, w, (), None, 0.0), settings)
    assert out.error == "" and out.model is not None
    assert (out.round, out.version, out.base_version) == (1, 1, 0)
    assert (out.window_t0, out.window_t1) == (w.t0, w.t1) and out.train_t1 == pytest.approx(w.t1)
    assert out.pairs == 200 and out.wall_s > 0 and out.cpu_s > 0 and math.isfinite(out.loss)
    assert len(out.model.networks) == 1 and out.model.extra["version"] == 1
    learned = ResidualQueue.from_model_file(out.model).evaluate(w.x, w.u)
    assert np.abs(learned.mean(axis=0) - r).max() < 0.2 * 4.9  # 30 Adam steps from a zero output: most of it

    # Round 2, warm start on round 1's queue: the new network starts as the old function and improves on it.
    w2 = window(r, index=2, t0=2.6, version=1, seed=1)
    out2 = _train_round(TrainRequest(2, 2, w2, (), out.model, 0.0), settings)
    assert out2.base_version == 1 and len(out2.model.networks) == 2
    learned2 = ResidualQueue.from_model_file(out2.model).evaluate(w2.x, w2.u)
    assert np.abs(learned2.mean(axis=0) - r).max() < np.abs(learned.mean(axis=0) - r).max()
    # The frozen network is unchanged in the new queue.
    old = to_torch_queue(out.model).networks[0].layers[-1].weight.detach().numpy()
    np.testing.assert_array_equal(out2.model.networks[0].layers[-1][0], old)


def test_a_round_with_a_held_out_tail_and_a_replayed_window(settings) -> None:
    r = np.array([1.0, 0.0, 0.0])
    older, newest = window(r, index=1), window(r, index=2, t0=2.6, seed=2)
    out = _train_round(TrainRequest(3, 3, newest, (older,), None, 0.2), settings)
    assert out.error == ""
    assert out.pairs == 200 + 160  # the whole older window, 80 % of the newest
    assert newest.t0 < out.train_t1 < newest.t1 - 0.09
    assert math.isfinite(out.val_rmse_model) and out.val_rmse_model < out.val_rmse_nominal


def test_a_round_that_cannot_train_reports_an_error(settings) -> None:
    w = window(np.zeros(3), n=1)
    out = _train_round(TrainRequest(4, 4, w, (), None, 0.0), settings)
    assert out.model is None and "no usable sample pairs" in out.error


def test_the_trainer_process_trains_and_survives_a_crash(settings) -> None:
    client = TrainerClient(dataclasses.replace(settings, inject=FaultInjection(crash_at_round=2, hang_at_round=0,
                                                                               nan_at_round=3)), timeout=30.0)
    client.start()
    try:
        assert client.wait_ready(120.0) and client.state == "idle"
        r = np.array([0.0, 0.0, -2.0])
        client.submit(TrainRequest(1, 7, window(r), (), None, 0.0))
        assert client.busy
        out = _wait(client)
        assert isinstance(out, TrainOutcome) and out.version == 7 and out.model is not None
        assert client.state == "idle"

        client.submit(TrainRequest(2, 8, window(r, index=2), (), out.model, 0.0))  # injected crash
        fault = _wait(client)
        assert isinstance(fault, TrainerFault) and fault.kind == "crash"
        assert f"code {CRASH_EXIT_CODE}" in fault.reason and client.state == "stopped"

        client.start()  # the learner's restart
        assert client.wait_ready(120.0)
        client.submit(TrainRequest(3, 9, window(r, index=3), (), out.model, 0.0))  # injected NaN
        nan_out = _wait(client)
        assert isinstance(nan_out, TrainOutcome) and nan_out.model is not None
        assert not np.all(np.isfinite(nan_out.model.networks[-1].layers[-1][0]))
        assert client.starts == 2
    finally:
        client.close()
    assert client.state == "stopped"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="trainers are forked from a server on Linux only")
def test_trainers_are_forked_from_one_server_that_imported_torch(settings) -> None:
    parents = []
    for _ in range(2):  # a flight's trainer and the next one's (or a restart)
        client = TrainerClient(settings, timeout=30.0)
        client.start()
        try:
            assert client.wait_ready(120.0)
            with open(f"/proc/{client.pid}/stat") as f:
                parents.append(int(f.read().rsplit(")", 1)[1].split()[1]))
        finally:
            client.close()
    assert parents[0] == parents[1] != os.getpid()
    with open(f"/proc/{parents[0]}/cmdline", "rb") as f:
        server = f.read().decode()
    assert "multiprocessing.forkserver" in server
    assert all(repr(name) in server for name in (*CHILD_IMPORTS, *settings.preload))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="trainers are forked from a server on Linux only")
def test_a_trainer_is_spawned_when_no_fork_server_can_be_reached(settings, monkeypatch) -> None:
    def unreachable(fds):
        raise OSError("no fork server")

    monkeypatch.setattr(multiprocessing.forkserver, "connect_to_new_process", unreachable)
    client = TrainerClient(settings, timeout=30.0)
    client.start()
    try:
        assert client.wait_ready(120.0) and client.state == "idle"
        with open(f"/proc/{client.pid}/stat") as f:
            assert int(f.read().rsplit(")", 1)[1].split()[1]) == os.getpid()  # this process's own child
    finally:
        client.close()


def test_a_trainer_that_cannot_re_import_a_script_read_from_stdin_says_so(monkeypatch) -> None:
    monkeypatch.setattr(sys.modules["__main__"], "__file__", "<stdin>", raising=False)
    monkeypatch.setattr(sys.modules["__main__"], "__spec__", None, raising=False)
    problem = trainer_client._start_failure(TrainerFault("crash", "trainer process exited (code 1)"))
    assert "<stdin> is not a file" in problem and "\n" not in problem


def test_trainers_are_spawned_where_forking_is_not_safe(monkeypatch) -> None:
    monkeypatch.setattr(trainer_client.sys, "platform", "darwin")
    assert trainer_context().get_start_method() == "spawn"


def test_a_hung_trainer_is_reported_after_the_timeout(settings) -> None:
    client = TrainerClient(dataclasses.replace(settings, inject=FaultInjection(0, 1, 0)), timeout=1.0)
    client.start()
    try:
        assert client.wait_ready(120.0)
        client.submit(TrainRequest(1, 1, window(np.zeros(3)), (), None, 0.0))
        fault = _wait(client)
        assert isinstance(fault, TrainerFault) and fault.kind == "hang"
        assert client.state == "stopped"
    finally:
        client.close()


def _wait(client: TrainerClient) -> TrainOutcome | TrainerFault | TrainerReady | None:
    for _ in range(1000):
        event = client.poll(0.5)
        if event is not None:
            return event
    return None


class _Conn:
    """The flight's end of a trainer's pipe, counting the reads (``poll``) that reach it."""

    def __init__(self, conn) -> None:
        self.conn, self.reads = conn, 0

    def poll(self, timeout: float | None = None) -> bool:
        self.reads += 1
        return self.conn.poll(timeout) if timeout else self.conn.poll()

    def recv(self):
        return self.conn.recv()

    def close(self) -> None:
        self.conn.close()


class _DeadChild:
    exitcode = -9

    def is_alive(self) -> bool:
        return False

    def join(self, timeout: float | None = None) -> None:
        pass

    def close(self) -> None:
        pass


def test_an_idle_trainer_s_pipe_is_read_every_so_many_polls_and_its_death_is_still_found(settings) -> None:
    client = TrainerClient(settings, 5.0)
    ours, theirs = multiprocessing.Pipe()
    conn = _Conn(ours)
    client._conn, client._proc, client.state = conn, _DeadChild(), "idle"
    every = trainer_client.IDLE_READ_EVERY
    assert all(client.poll() is None for _ in range(2 * every))
    assert conn.reads == 2  # a system call every so many ticks, not at each
    client.state = "busy"  # a round out: its result is read at the first poll after it comes
    client.sent_wall = client._wall()
    theirs.send(None)
    assert client.poll() is None and conn.reads == 3  # the message was read (None: not a result)
    client.state = "idle"
    theirs.close()  # the trainer died while idle: its end of the pipe is gone
    for n in range(1, every + 1):
        fault = client.poll()
        if fault is not None:
            break
    assert isinstance(fault, TrainerFault) and fault.kind == "crash" and "code -9" in fault.reason and n <= every
    assert client.state == "stopped"
