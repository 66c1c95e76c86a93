"""cfknode plot: the named PNGs from a flight log, overlays of several flights, truncated logs."""

import argparse
import struct
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.cli import UsageError
from cfknode.app.commands import plot as plot_command
from cfknode.app.config import load_config
from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.app.mission import run_flight
from fakes import SHORT_FLIGHT
from cfknode.app.ui.plotting import PLOTS, plot_logs, trace_from_log

SHORT = {**SHORT_FLIGHT, "sim.mass_changes": [{"t": 2.0, "factor": 1.2}]}
MODEL_EVENTS = [
    (2.1, {"version": 1, "event": "swap", "val_error": 0.03, "queue": [1]}),
    (2.3, {"version": 2, "event": "reject", "reason": "validation error worse"}),
    (2.5, {"version": 3, "event": "swap", "val_error": 0.02, "queue": [1, 3]}),
    (2.7, {"version": 1, "event": "rollback", "reason": "solver failed", "queue": [1]}),
]


def fly(directory: Path, name: str, **overrides) -> Path:
    cfg = load_config(overrides={**SHORT, "log.dir": str(directory), **overrides})
    return Path(run_flight(cfg, name_hint=name).summary.log_path)


def with_model_events(src: Path, directory: Path) -> Path:
    """The same flight with /model events, as the online learner writes them."""
    log = read_log(src)
    msgs = [(m["t"], topic, {k: v for k, v in m.items() if k != "t"})
            for topic, ms in log.messages.items() if topic != "/config" for m in ms]
    msgs += [(t, "/model", m) for t, m in MODEL_EVENTS]
    msgs.sort(key=lambda x: x[0])
    with FlightLog.create(directory, log.config, "test", "online") as out:
        for t, topic, msg in msgs:
            out.write(topic, t, msg)
    return out.path


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    d = tmp_path_factory.mktemp("flights")
    mpc = fly(d, "mpc")
    return {"mpc": mpc, "geometric": fly(d, "geo", **{"controller.kind": "geometric"}),
            "online": with_model_events(mpc, d)}


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    return struct.unpack(">II", data[16:24])


def test_plot_command_gives_the_named_pngs_of_one_flight(flights, capsys):
    parser = argparse.ArgumentParser()
    plot_command.add_arguments(parser)
    assert plot_command.run(parser.parse_args([str(flights["online"])])) == 0
    out_dir = flights["online"].with_name(flights["online"].stem + "-plots")
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(f"{name}.png" for name in PLOTS)
    printed = capsys.readouterr().out
    for name in PLOTS:
        width, height = png_size(out_dir / f"{name}.png")
        assert 500 <= width <= 1100 and 300 <= height <= 800, (name, width, height)
        assert str(out_dir / f"{name}.png") in printed


def test_a_trace_holds_markers_window_and_controller(flights):
    trace = trace_from_log(read_log(flights["online"]))
    assert trace.mass_changes == ((2.0, 1.2),)
    assert [(v, e) for _, v, e in trace.model_events] == [(1, "swap"), (2, "reject"), (3, "swap"), (1, "rollback")]
    assert trace.name.endswith("mpc (rti) + KNODE online") and trace.true_positions
    assert trace.window == pytest.approx((1.2, 2.7))
    assert not trace.truncated and len(trace.t) == len(trace.p) == len(trace.p_ref) > 1000


def test_traces_hold_what_the_log_holds(flights):
    log = read_log(flights["mpc"])
    trace = trace_from_log(log)
    np.testing.assert_array_equal(trace.t, log.times("/state"))
    np.testing.assert_array_equal(trace.p, log.array("/state", "p_true"))
    assert trace.deadline_ms == pytest.approx(2.5)
    assert len(trace.compute_ms) == len(log.topic("/tick"))
    assert np.all(trace.solve_ms > 0) and len(trace.solve_ms) > 1000


def test_several_flights_overlay_and_a_truncated_one_plots_up_to_where_it_ends(flights, tmp_path):
    data = flights["mpc"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # the process killed mid-flight
    report = plot_logs([flights["mpc"], flights["geometric"], cut], tmp_path / "plots")
    assert set(report.files) == set(PLOTS) and all(png_size(p) for p in report.files.values())
    full, geometric, part = report.traces
    assert full.name.endswith("mpc (rti)") and geometric.name.endswith("geometric")
    assert geometric.solve_ms.size == 0  # the geometric controller solves nothing
    assert part.truncated and not full.truncated
    assert 0.5 < part.t_end < full.t_end
    assert part.window == full.window  # no /summary: from the logged trajectory config
    np.testing.assert_array_equal(part.p, full.p[: len(part.t)])


def test_plot_command_rejects_a_file_that_is_not_a_log(tmp_path):
    parser = argparse.ArgumentParser()
    plot_command.add_arguments(parser)
    bad = tmp_path / "not-a-log.mcap"
    bad.write_text("hello")
    with pytest.raises(UsageError, match="not an MCAP flight log"):
        plot_command.run(parser.parse_args([str(bad), "--out", str(tmp_path / "x")]))


def test_the_log_documentation_lists_every_channel():
    from cfknode.app.logs.writer import channels_markdown

    docs = (Path(__file__).parents[1] / "docs" / "logs.md").read_text()
    assert channels_markdown() in docs, (
        "docs/logs.md is out of date with flightlog.CHANNELS: paste the output of "
        "python -c 'from cfknode.app.logs.writer import channels_markdown; print(channels_markdown())'"
    )
