"""Offline KNODE-MPC end to end: fly nominal at 1.3x mass, `cfknode train` on the log, fly with the model."""

import numpy as np
import pytest

from cfknode.app.cli import main
from cfknode.app.config import ConfigError, load_config
from cfknode.app.mission import run_flight

torch = pytest.importorskip("torch")

HEAVY = {
    "controller.adaptation": "none",  # the learned model alone against the nominal one, as the paper flies them
    "sim.mass_changes": [{"t": 0.0, "factor": 1.3}],
    "trajectory.duration": 6.0,
    "trajectory.takeoff_duration": 2.0,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 2.0,
    "trajectory.ramp_duration": 1.0,
}


def _fly(tmp_path, name, **overrides):
    cfg = load_config(overrides={**HEAVY, "log.dir": str(tmp_path), **overrides})
    return run_flight(cfg, name_hint=name)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("knode")
    nominal = _fly(d, "nominal")
    held_out = _fly(d, "heldout", **{"sim.seed": 11})
    model = d / "model.ckpt"
    assert main(["train", "--log", nominal.summary.log_path, "--out", str(model)]) == 0
    return nominal, held_out, model, d


def test_knode_mpc_halves_the_tracking_error(trained):
    nominal, _, model, d = trained
    knode = _fly(d, "knode", **{"controller.model": str(model)})
    assert knode.summary.extra["controller"] == "knode-mpc"
    assert knode.summary.mse <= 0.5 * nominal.summary.mse, (knode.summary.mse, nominal.summary.mse)
    assert knode.summary.extra["fallback_ticks"] == 0


def test_one_step_error_on_a_held_out_log_halves(trained):
    from cfknode.app.logs.training_data import segments_from_logs
    from cfknode.models.knode import to_torch_queue
    from cfknode.models.modelfile import load_model
    from cfknode.models.training import make_dataset, one_step_rmse

    _, held_out, model, _ = trained
    cfg = load_config()
    data = make_dataset(segments_from_logs([held_out.summary.log_path]), cfg.training.velocity_filter_hz, 0.0)
    queue = to_torch_queue(load_model(model))
    empty = to_torch_queue(load_model(model))
    empty.networks = torch.nn.ModuleList()  # no networks: the nominal model
    nominal_err = one_step_rmse(empty, data.train)
    model_err = one_step_rmse(queue, data.train)
    assert np.isfinite(model_err) and model_err <= 0.5 * nominal_err, (model_err, nominal_err)


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (b"", "model"),
        (b"\x00" * 64, "model"),
        (b"this is not a model file at all", "model"),
    ],
)
def test_flight_refuses_a_bad_model_file(tmp_path, content, fragment):
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(content)
    cfg = load_config(overrides={**HEAVY, "log.dir": str(tmp_path), "controller.model": str(bad)})
    with pytest.raises(ConfigError, match="refusing to fly") as err:
        run_flight(cfg)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)
    assert not list(tmp_path.glob("*.mcap")), "no flight log: the flight never started"


def test_knode_mpc_needs_a_model(tmp_path):
    with pytest.raises(ConfigError, match="needs a model file"):
        run_flight(load_config(overrides={"controller.kind": "knode-mpc", "log.dir": str(tmp_path)}))
