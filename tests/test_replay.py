"""cfknode replay: the controller re-run on a flight log's states reproduces the logged commands."""

import argparse
import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.cli import UsageError
from cfknode.app.commands import replay as replay_command
from cfknode.app.config import ConfigError, load_config
from cfknode.app.logs.writer import read_log
from cfknode.app.mission import run_flight
from fakes import SHORT_FLIGHT
from cfknode.models.modelfile import ModelFile, NetworkWeights, Normalisation, save_model
from cfknode.app.replay import COMMAND_FIELDS, ReplayError, load_residual_model, logged_config, replay_log, write_csv

SHORT = SHORT_FLIGHT


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory):
    cfg = load_config(overrides={**SHORT, "log.dir": str(tmp_path_factory.mktemp("flights"))})
    return read_log(run_flight(cfg, name_hint="replay").summary.log_path)


@pytest.fixture(scope="module")
def plain_log(tmp_path_factory):
    """A flight without the fast layer: replayed with another model, the layer (on by default) would re-estimate
    what the new model changes from states the new commands never flew, and take it out."""
    cfg = load_config(overrides={**SHORT, "controller.adaptation": "none",
                                 "log.dir": str(tmp_path_factory.mktemp("plain"))})
    return read_log(run_flight(cfg, name_hint="replay-plain").summary.log_path)


@pytest.fixture(scope="module")
def replayed(flight_log):
    cfg, dropped = logged_config(flight_log)
    assert dropped == []
    return replay_log(flight_log, cfg)


def constant_model(path: Path, residual: tuple[float, float, float]) -> Path:
    """A one-network queue whose residual on v' is the constant ``residual`` (m/s^2)."""
    layers = ((np.zeros((4, 6)), np.zeros(4)), (np.zeros((3, 4)), np.asarray(residual, dtype=float)))
    net = NetworkWeights(layers, Normalisation.identity())
    return save_model(path, ModelFile(hidden=(4,), activation="tanh", queue_size=1, networks=(net,)))


def test_replay_reproduces_the_logged_commands(flight_log, replayed):
    commands = flight_log.topic("/command")
    mpc_ticks = [i for i, m in enumerate(commands) if m["source"] == "mpc"]
    assert replayed.ticks == len(mpc_ticks) > 1000
    assert sum(replayed.skipped.values()) == len(commands) - replayed.ticks
    assert replayed.source_changes() == 0 and replayed.reference_mismatch_m == 0.0
    # Same inputs, same warm-start sequence, same compiled solver: bit for bit.
    assert max(replayed.max_abs().values()) == 0.0
    np.testing.assert_array_equal(replayed.logged[:, :3], flight_log.array("/command", "acc")[mpc_ticks])


def test_a_zero_model_changes_nothing_and_a_constant_residual_is_compensated(flight_log, plain_log, tmp_path):
    zero, name = load_residual_model(constant_model(tmp_path / "zero.safetensors", (0.0, 0.0, 0.0)))
    assert "1 network" in name
    for log in (flight_log, plain_log):  # with the fast layer (the default) and without
        cfg, _ = logged_config(log)
        assert max(replay_log(log, cfg, zero).max_abs().values()) == 0.0
    # A model predicting +0.5 m/s^2 upward: the MPC asks that much less acceleration (mid-flight).
    up, _ = load_residual_model(constant_model(tmp_path / "up.safetensors", (0.0, 0.0, 0.5)))
    cfg, _ = logged_config(plain_log)
    result = replay_log(plain_log, cfg, up)
    mid = (result.t > 0.8) & (result.t < 3.0)
    assert np.mean(result.difference[mid, 2]) == pytest.approx(-0.5, abs=0.05)
    assert np.max(np.abs(result.difference[mid, :2])) < 0.05


def test_unusable_model_and_override_errors_are_one_line(flight_log, tmp_path):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a model")
    with pytest.raises(ReplayError) as err:
        load_residual_model(bad)
    assert "bad.safetensors" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="unknown config key 'controller.nope'"):
        logged_config(flight_log, {"controller.nope": 1})


def test_logged_config_ignores_keys_this_version_does_not_know(flight_log):
    config = {**flight_log.config, "retired": {"x": 1},
              "controller": {**flight_log.config["controller"], "old_gain": 2.0}}
    cfg, dropped = logged_config(dataclasses.replace(flight_log, config=config))
    assert sorted(dropped) == ["controller.old_gain", "retired"]
    assert cfg.trajectory.duration == 1.5


def test_truncated_log_replays_up_to_where_it_ends(flight_log, tmp_path):
    data = flight_log.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.5)])
    log = read_log(cut)
    cfg, _ = logged_config(log)
    result = replay_log(log, cfg)
    assert log.truncated and 100 < result.ticks
    assert result.t[-1] <= log.times("/command")[-1]
    assert max(result.max_abs().values()) == 0.0


def test_csv(replayed, tmp_path):
    with open(write_csv(replayed, tmp_path / "r.csv")) as f:
        rows = list(csv.reader(f))
    assert rows[0][:3] == ["t", "logged_source", "replay_source"] and len(rows[0]) == 3 + 2 * len(COMMAND_FIELDS)
    assert len(rows) == replayed.ticks + 1
    assert float(rows[1][0]) == replayed.t[0] and float(rows[1][3]) == replayed.logged[0, 0]


def test_command_line_with_other_weights_json_and_png(flight_log, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    replay_command.add_arguments(parser)
    png = tmp_path / "r.png"
    # In CasADi's VM: other weights are another compiled library, seconds of gcc for what this test checks.
    argv = [str(flight_log.path), "--set", "controller.q_position=[20, 20, 30]", "--set", "controller.codegen=false",
            "--json", "--png", str(png)]
    assert replay_command.run(parser.parse_args(argv)) == 0
    out = json.loads(capsys.readouterr().out)
    # Other weights command otherwise: the replay recomputes, it does not copy.
    assert 1e-3 < out["rms"]["acc_x"] < 1.0 and out["rms"]["thrust"] > 1.0 and out["source_changes"] == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(UsageError, match="model file .*missing.safetensors: not found"):
        replay_command.run(parser.parse_args([str(flight_log.path), "--model", str(tmp_path / "missing.safetensors")]))
