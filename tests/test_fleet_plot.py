"""cfknode plot and replay on a fleet log: the drones overlaid, --drones, one-line errors naming the drones."""

import argparse
import math
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.cli import UsageError
from cfknode.app.commands import plot as plot_command
from cfknode.app.commands import replay as replay_command
from cfknode.app.fleet.flight import fleet_channels
from cfknode.app.logs.fleet_log import drone_log, fleet_drones
from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.app.ui.plotting import PLOTS, plot_logs, read_for_plot, traces_from_log
from synthetic_log import CONFIG, write_synthetic_flight

NAMES = ("cf1", "cf2", "cf3")
RATE = 100.0


def write_fleet_log(directory: Path, seconds: float = 2.0) -> Path:
    """A fleet log as run_fleet writes it: each drone's channels under its name, the drones a third
    of the circle apart, drone i off its reference by (i + 1) mm in y."""
    config = {**CONFIG, "fleet": {"size": len(NAMES)}, "fleet_drones": {n: f"sim://{i}" for i, n in enumerate(NAMES)}}
    with FlightLog.create(directory, config, "test", "fleet3", channels=fleet_channels(NAMES)) as log:
        for k in range(int(seconds * RATE)):
            t = k / RATE
            for i, name in enumerate(NAMES):
                a = 0.8 * t + 2 * math.pi * i / len(NAMES)
                ref = [0.5 * math.cos(a), 0.5 * math.sin(a), 1.0]
                p = [ref[0], ref[1] + 1e-3 * (i + 1), ref[2]]
                log.write(f"/{name}/state", t, {"p": p, "v": [0.0, 0.0, 0.0], "q": [1.0, 0.0, 0.0, 0.0], "p_true": p})
                log.write(f"/{name}/reference", t, {"p": ref, "v": [0.0, 0.0, 0.0], "a": [0.0, 0.0, 0.0], "yaw": 0.0})
                log.write(f"/{name}/tick", t, {"compute_s": 4e-4 * (i + 1), "solve_s": 2e-4, "missed": False,
                                               "mpc_ok": True})
        for name in NAMES:
            log.write(f"/{name}/summary", seconds, {"window": [0.5, 1.5], "drone": name})
        log.write("/summary", seconds, {"fleet": list(NAMES), "min_separation_m": 0.86})
    return log.path


@pytest.fixture(scope="module")
def fleet_log(tmp_path_factory):
    return write_fleet_log(tmp_path_factory.mktemp("fleet"))


def test_a_fleet_log_gives_one_trace_per_drone_named_after_it(fleet_log):
    log = read_for_plot(fleet_log)
    assert fleet_drones(log) == list(NAMES)
    traces = traces_from_log(log)
    assert [tr.name for tr in traces] == list(NAMES) and [tr.drone for tr in traces] == list(NAMES)
    for i, tr in enumerate(traces):
        assert len(tr.t) == 200 and tr.true_positions and tr.window == (0.5, 1.5)
        assert np.allclose(tr.p[:, 1] - tr.p_ref[:, 1], 1e-3 * (i + 1))  # each drone its own data
        assert np.allclose(tr.compute_ms, 0.4 * (i + 1))
    assert len({tr.reference_key for tr in traces}) == 3  # three references drawn, not one


def test_plot_command_overlays_every_drone_in_each_png(fleet_log, tmp_path, capsys):
    out = tmp_path / "plots"
    args = argparse.Namespace(logs=[str(fleet_log)], out=str(out), dpi=40, drones=None)
    assert plot_command.run(args) == 0
    printed = capsys.readouterr().out
    assert all(f": {n}, 200 ticks" in printed for n in NAMES)
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}.png" for n in PLOTS)


def test_the_overlay_draws_one_line_per_drone_with_a_legend_by_name(fleet_log, tmp_path, monkeypatch):
    from cfknode.app.ui import plotting

    figures = {}
    for name in ("_top_view", "_error_xyz"):
        maker = getattr(plotting, name)
        monkeypatch.setattr(plotting, name, lambda traces, maker=maker, name=name: figures.setdefault(name,
                                                                                                      maker(traces)))
    plot_logs([fleet_log], tmp_path / "p", dpi=40)
    top = figures["_top_view"]
    labels = [t.get_text() for t in top.legends[0].get_texts()]
    assert all(n in labels and f"reference of {n}" in labels for n in NAMES)
    assert "fleet: cf1, cf2, cf3" in top._suptitle.get_text()
    err = figures["_error_xyz"]
    y_axis = err.axes[1]
    assert len(y_axis.get_lines()) == 3 + 1  # a line per drone and the zero line
    rms = [t.get_text() for t in y_axis.get_legend().get_texts()]
    assert rms == [f"RMS {1.0 * (i + 1):.2f} mm" for i in range(3)]  # y error on the pattern window
    assert [t.get_text() for t in err.legends[0].get_texts()] == list(NAMES)


def test_drones_chooses_a_subset_in_the_order_asked(fleet_log, tmp_path):
    report = plot_logs([fleet_log], tmp_path / "sub", dpi=40, drones=["cf3", "cf1"])
    assert [tr.name for tr in report.traces] == ["cf3", "cf1"]
    log = read_for_plot(fleet_log, drones=["cf2"])  # only the chosen drone's columns are kept
    assert "/cf2/state" in log.sink.columns and "/cf1/state" not in log.sink.columns


def test_an_unknown_drone_is_a_one_line_error_listing_the_logs_drones(fleet_log, tmp_path):
    args = argparse.Namespace(logs=[str(fleet_log)], out=str(tmp_path / "x"), dpi=40, drones="cf1,cf9")
    with pytest.raises(UsageError) as err:
        plot_command.run(args)
    assert str(err.value) == f"{fleet_log}: no drone cf9 in this fleet log; it has cf1, cf2, cf3"
    with pytest.raises(UsageError, match="drone names separated by commas"):
        plot_command.run(argparse.Namespace(**{**vars(args), "drones": "cf1,"}))


def test_a_single_flight_plots_as_before_and_drones_needs_a_fleet_log(fleet_log, tmp_path):
    single = write_synthetic_flight(tmp_path, 0.5)
    report = plot_logs([single], tmp_path / "one", dpi=40)
    assert len(report.traces) == 1 and report.traces[0].drone == "" and "synthetic" in report.traces[0].name
    args = argparse.Namespace(logs=[str(single)], out=str(tmp_path / "y"), dpi=40, drones="cf1")
    with pytest.raises(UsageError, match="--drones: this log is a fleet's flight"):
        plot_command.run(args)
    # Beside a fleet log, a single flight plots whole and each drone's legend names its log.
    both = plot_logs([fleet_log, single], tmp_path / "both", dpi=40, drones=["cf2"])
    assert [tr.name.split(" · ")[-1] for tr in both.traces] == ["cf2", report.traces[0].name.split(" · ")[-1]]
    assert both.traces[0].name == f"{fleet_log.stem} · cf2"


def test_replay_of_a_fleet_log_needs_a_drone_named_in_one_line(fleet_log):
    base = dict(log=str(fleet_log), model=None, solver=None, qp_solver=None, set=[], csv=None, png=None, json=False)
    with pytest.raises(UsageError) as err:
        replay_command.run(argparse.Namespace(**base, drone=None))
    assert str(err.value) == f"{fleet_log} is a fleet log: choose a drone with --drone (cf1, cf2, cf3)"
    with pytest.raises(UsageError, match="no drone cf7 in this fleet log; it has cf1, cf2, cf3"):
        replay_command.run(argparse.Namespace(**base, drone="cf7"))


def test_a_drones_part_of_a_fleet_log_reads_as_a_single_flight(fleet_log):
    log = read_log(fleet_log)
    one = drone_log(log, "cf2")
    assert set(one.messages) >= {"/state", "/reference", "/tick", "/summary", "/config"}
    assert one.count("/state") == 200 and one.topic("/summary")[0]["drone"] == "cf2"
    assert "fleet_drones" not in one.config and one.config["fleet"] == {"size": 3}
