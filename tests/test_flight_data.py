"""Other people's flight data: CSV and Parquet tables, their inputs, glitches and lags, and
``cfknode model check`` / ``cfknode train --data`` on a synthetic vehicle whose truth is known."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.cli import main
from cfknode.app.config import ConfigError, load_config
from cfknode.app.data import inputs
from cfknode.app.data.check import check, queue_residual, split_by_group, split_dataset
from cfknode.app.data.prepare import TableOptions, estimate_lag, prepare, shift_input
from cfknode.app.data.synthetic import Noise, flight_table
from cfknode.app.data.tables import parse_column_map, read_table
from cfknode.models.modelfile import load_model
from cfknode.models.residual_check import explained, layer_estimate, pair_residual
from cfknode.models.training import train_new_model

MASS = 0.034
OPTS = TableOptions(mass=MASS, gravity=9.81, newton_per_cmd=4 * 0.15 / 65535)


def write_csv(path: Path, table: dict[str, np.ndarray], rename: dict[str, str] | None = None) -> Path:
    names = list(table)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([(rename or {}).get(n, n) for n in names])
        for i in range(table["t"].size):
            w.writerow([table[n][i] for n in names])
    return path


@pytest.fixture(scope="module")
def table() -> dict[str, np.ndarray]:
    return flight_table(seed=1, manoeuvres=4, seconds=20, mass=MASS)


def test_hover_thrust_is_no_acceleration_for_every_input_kind():
    q = np.array([[1.0, 0, 0, 0]])
    assert np.allclose(inputs.body_z(q), [[0, 0, 1]])
    hover = np.array([MASS * 9.81])
    assert np.allclose(inputs.acceleration(inputs.body_z(q), hover, MASS, 9.81), 0)
    w = np.full((1, 4), np.sqrt(MASS * 9.81 / 4 / 2e-8))
    assert np.allclose(inputs.motor_thrust(w, 2e-8), hover)
    tilt = inputs.body_z_from_euler(np.radians([10.0]), np.radians([20.0]), np.radians([30.0]))
    # The same direction the firmware's ZYX attitude points its thrust along.
    cr, sr, cp, sp = np.cos(np.radians(10)), np.sin(np.radians(10)), np.cos(np.radians(20)), np.sin(np.radians(20))
    cy, sy = np.cos(np.radians(30)), np.sin(np.radians(30))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    assert np.allclose(tilt[0], (rz @ ry @ rx)[:, 2])


def test_csv_and_parquet_read_the_same_columns_and_names_can_be_mapped(table, tmp_path):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    path = write_csv(tmp_path / "f.csv", table, rename={"t": "time", "px": "x"})
    with pytest.raises(ConfigError, match="no column t, px"):
        read_table(path)
    got = read_table(path, parse_column_map("t=time,px=x"))
    pq.write_table(pa.table(table), tmp_path / "f.parquet")
    other = read_table(tmp_path / "f.parquet")
    for name in ("t", "px", "vz", "qw", "thrust"):
        assert np.allclose(got[name], table[name]) and np.allclose(other[name], table[name])
    assert list(other["manoeuvre"][:1]) == ["m0"]


@pytest.mark.parametrize("case", ["fifo", "not_numeric", "ragged", "bad_map", "suffix"])
def test_a_bad_table_is_one_line(table, tmp_path, case):
    path = tmp_path / "bad.csv"
    if case == "fifo":
        os.mkfifo(path)
    elif case == "not_numeric":
        path.write_text("t,px,py,pz\n0,a,0,0\n1,b,0,0\n")
    elif case == "ragged":
        path.write_text("t,px,py,pz\n0,0,0,0\n1,0,0\n")
    elif case == "suffix":
        path = tmp_path / "f.txt"
        path.write_text("t\n")
    with pytest.raises(ConfigError) as err:
        if case == "bad_map":
            parse_column_map("speed=v")
        else:
            read_table(path)
    assert "\n" not in str(err.value)


def test_glitches_are_masked_and_reported(table):
    t = {k: v.copy() for k, v in table.items()}
    t["px"][500:] += 0.3  # an estimate reset: the position jumps 30 cm between two samples
    t["thrust"][900] *= 3.0  # a telemetry spike
    segments, prep = prepare(t, "glitchy", OPTS)
    clean_segments, clean = prepare(table, "clean", OPTS)
    assert prep.jumps >= clean.jumps + 4 and prep.spikes >= 1 and clean.spikes == 0
    assert prep.segments > clean.segments  # the glitches cut runs
    kept = np.concatenate([s.t for s in segments])
    assert table["t"][900] not in kept and table["t"][500] not in kept


def test_the_input_lag_is_estimated_and_removed(table):
    t = table["t"]
    u, _ = __import__("cfknode.app.data.prepare", fromlist=["x"]).commanded_acceleration(table, OPTS, "x")
    v = np.stack([table[k] for k in ("vx", "vy", "vz")], axis=1)
    late = shift_input(t, u, -0.03)  # the recorded input runs 30 ms ahead of what acts
    assert estimate_lag(t, late, v, 0.1) == pytest.approx(0.03, abs=0.011)
    assert estimate_lag(t, u, v, 0.1) == pytest.approx(0.0, abs=0.011)


def test_subsampling_keeps_every_nth_sample(table):
    from dataclasses import replace

    full, _ = prepare(table, "f", OPTS)
    third, prep = prepare(table, "f", replace(OPTS, every=3))
    assert np.allclose(third[0].t, full[0].t[::3]) and prep.samples == sum(s.t.size for s in third)


def _fit_and_check(climb_gain: float) -> tuple[object, float]:
    cfg = load_config()
    tab = flight_table(seed=2, manoeuvres=4, seconds=25, climb_gain=climb_gain, noise=Noise(rms=0.3), mass=MASS)
    segments, _ = prepare(tab, "syn", OPTS)
    train, held = split_by_group(segments)
    ds = split_dataset(train, held, cfg.training.velocity_filter_hz)
    from dataclasses import replace

    queue, _ = train_new_model(ds, cfg.knode, replace(cfg.training, epochs=150))
    a = cfg.controller.adaptation_settings
    report = check(ds.val, queue_residual(queue), (a.bandwidth_xy_hz, a.bandwidth_hz),
                   (a.output_bandwidth_xy_hz, a.output_bandwidth_hz))
    r = pair_residual(ds.val)
    truth = float(np.mean((climb_gain * ds.val.x0[:, 5]) ** 2) / np.mean(r[:, 2] ** 2))
    return report, truth


def test_model_check_finds_a_state_dependent_term_within_five_points():
    report, truth = _fit_and_check(-1.0)
    assert 0.3 < truth < 0.9  # the climb term is a good part of the vertical residual here
    assert report.shares.model[2] == pytest.approx(truth, abs=0.05)
    assert abs(report.shares.model[0]) < 0.05 and abs(report.shares.model[1]) < 0.05  # noise: nothing to learn
    assert "worth learning on z" in report.verdict and "x (" not in report.verdict


def test_model_check_says_not_worth_learning_for_pure_noise():
    report, truth = _fit_and_check(0.0)
    assert truth == 0.0
    assert report.verdict.startswith("not worth learning")
    assert np.all(report.shares.beyond_layer < 0.05)


def test_the_layer_removes_a_constant_and_not_fast_noise():
    t = np.arange(0, 20, 0.01)
    rng = np.random.default_rng(0)
    slow = np.tile([0.2, -0.1, 0.5], (t.size, 1))
    fast = rng.normal(0, 0.3, (t.size, 3))
    est = layer_estimate(t, slow + fast, (0.5, 1.0), (0.5, 0.5))
    assert np.all(explained(slow, (slow - est)[200:]) > 0.9)  # after the first seconds
    assert np.all(explained(fast, fast - layer_estimate(t, fast, (0.5, 1.0), (0.5, 0.5))) < 0.05)


def test_model_check_and_train_from_the_command_line(table, tmp_path, capsys):
    path = write_csv(tmp_path / "flights.csv", table)
    assert main(["model", "check", "--data", str(path), "--set", f"vehicle.mass={MASS}", "--epochs", "20"]) == 0
    out = capsys.readouterr().out
    assert "held-out" in out and "open-loop" in out and "worth learning" in out
    model = tmp_path / "m.safetensors"
    assert main(["train", "--data", str(path), "--set", f"vehicle.mass={MASS}", "--epochs", "20",
                 "--out", str(model)]) == 0
    assert model.is_file()
    assert "stored score beyond the layer (x, y, z)" in capsys.readouterr().out
    score = load_model(model).extra["beyond_layer"]  # the flight beside the layer reads it
    assert len(score) == 3 and all(isinstance(v, float) for v in score)
    assert main(["model", "check", "--data", str(path), "--set", f"vehicle.mass={MASS}", "--model", str(model)]) == 0
    assert main(["model", "check", "--set", f"vehicle.mass={MASS}"]) == 2  # no data: one line
    assert "give flight data" in capsys.readouterr().err
