"""Flight plots from MCAP logs (matplotlib, Agg, no pyplot state): one PNG per view.

- ``top_view.png``: the path seen from above against the reference;
- ``altitude.png``: altitude against time, with mass-change and model-swap markers;
- ``error_xyz.png``: position error per axis against time;
- ``timing.png``: histograms of tick compute and MPC solve times;
- ``model_versions.png``: which model version flew when, with swaps, rejections and rollbacks.

Several logs overlay on the same axes to compare controllers; each legend entry names the
log and its controller. A fleet log (docs/fleet.md) overlays its drones, one line each named
after the drone (``drones`` chooses some). A truncated log (the process killed mid-flight)
plots up to its last complete record. Positions are the simulator's true ones when logged, else the estimate.

Logs are streamed and only the plotted fields are kept, as arrays (``read_for_plot``): a
10-minute flight plots in a few hundred MB at most.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, NullFormatter

from cfknode.app.logs.fleet_log import DroneColumns, FleetColumnSink, choose_drones, fleet_drones
from cfknode.app.logs.format import LogError
from cfknode.app.logs.reader import LogColumns, LogData, read_columns, require_messages

__all__ = ["DPI", "FlightTrace", "PLOTS", "PlotReport", "plot_logs", "plot_traces", "read_for_plot",
           "trace_from_log", "traces_from_log"]

PLOTS: tuple[str, ...] = ("top_view", "altitude", "error_xyz", "timing", "model_versions")
DPI = 100  # a 9 x 4.6 inch figure is 900 x 460 pixels
_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
# What the plots read of a log: these fields as arrays, the small topics whole.
PLOT_FIELDS: dict[str, tuple[str, ...]] = {"/state": ("p", "p_true"), "/reference": ("p",),
                                           "/tick": ("compute_s", "solve_s")}
PLOT_WHOLE: tuple[str, ...] = ("/model", "/summary")
_EVENT_STYLE = {"swap": ("tab:green", "o"), "reject": ("tab:red", "x"), "rollback": ("darkorange", "v"),
                "crash": ("black", "X"), "restart": ("0.45", "^")}


@dataclass(frozen=True)
class FlightTrace:
    """What the plots need from one log, per tick time (ticks with both a state and a reference)."""

    name: str  # legend label: log name and controller
    path: Path
    t: np.ndarray  # (n,) s
    p: np.ndarray  # (n, 3) m
    p_ref: np.ndarray  # (n, 3) m
    true_positions: bool  # p is the simulator's truth (else the estimate)
    compute_ms: np.ndarray  # per tick
    solve_ms: np.ndarray  # ticks that ran a solve
    deadline_ms: float  # the tick period
    window: tuple[float, float] | None  # pattern window
    reference_key: str  # flights with equal keys flew the same reference (trajectory config and start)
    mass_changes: tuple[tuple[float, float], ...]  # (t, factor of the nominal mass)
    model_events: tuple[tuple[float, int, str], ...]  # (t, version, swap | reject | rollback)
    t_end: float  # last flight time in the log
    truncated: bool
    damage: str = ""  # what the reader skipped or found missing (LogDamage.line()), "" for a clean log
    drone: str = ""  # the drone's name in a fleet log ("" for a single flight's log)


@dataclass(frozen=True)
class PlotReport:
    files: dict[str, Path]  # plot name (PLOTS) -> PNG written
    traces: tuple[FlightTrace, ...]


def read_for_plot(path: str | Path, drones: Sequence[str] | None = None) -> LogColumns:
    """Stream a log, keeping what the plots need; ``LogError`` (one line) for a file that cannot plot.

    A fleet log keeps every drone's channels (only ``drones``' when given).
    """
    log = read_columns(path, PLOT_FIELDS, PLOT_WHOLE, sink=FleetColumnSink(PLOT_FIELDS, PLOT_WHOLE, drones))
    names = fleet_drones(log)
    for prefix in [f"/{n}" for n in names if drones is None or n in drones] if names else [""]:
        require_messages(log, (f"{prefix}/state", f"{prefix}/reference"))
    return log


def traces_from_log(log: LogColumns, drones: Sequence[str] | None = None) -> tuple[FlightTrace, ...]:
    """One trace per drone of a fleet log (``drones`` only, in that order, when given), named after it;
    a single flight's log gives its one trace. ``LogError`` (one line) for a drone the log lacks."""
    names = fleet_drones(log)
    if not names:
        return (trace_from_log(log),)
    try:
        chosen = choose_drones(log.path, names, drones)
    except ValueError as exc:
        raise LogError(str(exc)) from None
    traces = []
    for name in chosen:
        tr = trace_from_log(DroneColumns(log, name))  # type: ignore[arg-type]
        # Each drone flew its own reference under the fleet's one trajectory config.
        traces.append(dataclasses.replace(tr, name=name, drone=name, reference_key=f"{tr.reference_key}/{name}"))
    return tuple(traces)


def trace_from_log(log: LogData | LogColumns) -> FlightTrace:
    """Extract a ``FlightTrace``; works on truncated logs (topics may end a message apart)."""
    config = log.config or {}
    states = log.count("/state")
    true = states > 0 and log.present("/state", "p_true") == states
    p_all = log.array("/state", "p_true" if true else "p") if states else np.zeros((0, 3))
    p_ref_all = log.array("/reference", "p") if log.count("/reference") else np.zeros((0, 3))
    t, i_state, i_ref = np.intersect1d(log.times("/state"), log.times("/reference"), return_indices=True)
    ticks = log.count("/tick")
    compute = log.array("/tick", "compute_s") * 1e3 if ticks else np.zeros(0)
    solve = log.array("/tick", "solve_s") * 1e3 if ticks else np.zeros(0)
    solve = solve[np.isfinite(solve) & (solve > 0)]
    rate = _number(_get(config, "controller.rate_hz", 400.0), 400.0)
    return FlightTrace(
        name=f"{log.path.stem} · {_controller_label(config, log)}",
        path=log.path,
        t=t,
        p=p_all[i_state].reshape(-1, 3),
        p_ref=p_ref_all[i_ref].reshape(-1, 3),
        true_positions=true,
        compute_ms=compute[np.isfinite(compute)],
        solve_ms=solve,
        deadline_ms=1e3 / float(rate),
        window=_pattern_window(log),
        reference_key=json.dumps([_get(config, "trajectory", None), _get(config, "sim.initial_position", None)],
                                 sort_keys=True),
        mass_changes=_mass_changes(_get(config, "sim.mass_changes", [])),
        model_events=tuple((float(m["t"]), int(m["version"]), str(m["event"])) for m in log.topic("/model")
                           if m["version"] is not None),
        t_end=log.end_time(),
        truncated=log.truncated,
        damage=log.damage.line(),
    )


def plot_logs(paths: Sequence[str | Path], out_dir: str | Path, dpi: int = DPI,
              drones: Sequence[str] | None = None) -> PlotReport:
    """Read the logs and write every plot of ``PLOTS`` into ``out_dir``; raises ``LogError`` for a bad file.

    A fleet log gives one trace per drone (``drones`` only, when given: every fleet log must have
    them; single flights' logs plot whole). With several logs a drone's legend names its log too.
    """
    logs = [read_for_plot(p, drones) for p in paths]
    if drones is not None and not any(fleet_drones(log) for log in logs):
        raise LogError(f"--drones: {'this log is' if len(logs) == 1 else 'none of the logs is'} a fleet's flight")
    traces = tuple(tr for log in logs for tr in traces_from_log(log, drones))
    if len(logs) > 1:
        traces = tuple(dataclasses.replace(tr, name=f"{tr.path.stem} · {tr.drone}") if tr.drone else tr
                       for tr in traces)
    return PlotReport(plot_traces(traces, out_dir, dpi), traces)


def plot_traces(traces: Sequence[FlightTrace], out_dir: str | Path, dpi: int = DPI) -> dict[str, Path]:
    if not traces:
        raise ValueError("no flights to plot")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    makers = {
        "top_view": _top_view,
        "altitude": _altitude,
        "error_xyz": _error_xyz,
        "timing": _timing,
        "model_versions": _model_versions,
    }
    files = {}
    for name in PLOTS:
        fig = makers[name](traces)
        path = out / f"{name}.png"
        fig.savefig(path, dpi=dpi)
        files[name] = path
    return files


# --- The plots -------------------------------------------------------------------------------


def _top_view(traces: Sequence[FlightTrace]) -> Figure:
    fig = Figure(figsize=(6.4, 6.6), layout="constrained")
    ax = fig.subplots()
    _references(ax, traces, lambda tr: (tr.p_ref[:, 0], tr.p_ref[:, 1]))
    for tr, color in _colored(traces):
        ax.plot(tr.p[:, 0], tr.p[:, 1], color=color, lw=1.1, label=_label(tr, traces))
        if len(tr.t):
            ax.plot(tr.p[0, 0], tr.p[0, 1], "o", color=color, ms=5)
            ax.plot(tr.p[-1, 0], tr.p[-1, 1], "s", color=color, ms=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    handles += [Line2D([], [], ls="", marker="o", color="0.3"), Line2D([], [], ls="", marker="s", color="0.3")]
    labels += ["start", "end"]
    # Below the axes: a pattern fills its whole box, so no corner inside is free.
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncols=2 if len(labels) <= 6 else 1)
    _title(fig, traces, "Top view")
    return fig


def _altitude(traces: Sequence[FlightTrace]) -> Figure:
    fig = Figure(figsize=(9.0, 4.6), layout="constrained")
    ax = fig.subplots()
    _window(ax, traces)
    _references(ax, traces, lambda tr: (tr.t, tr.p_ref[:, 2]))
    top = 0.0
    for tr, color in _colored(traces):
        ax.plot(tr.t, tr.p[:, 2], color=color, lw=1.1, label=_label(tr, traces))
        top = max(top, float(np.nanmax(tr.p[:, 2], initial=0.0)), float(np.nanmax(tr.p_ref[:, 2], initial=0.0)))
    if any(tr.model_events for tr in traces):  # headroom for the event ticks at the top
        ax.set_ylim(min(-0.05, ax.get_ylim()[0]), 1.18 * top + 0.05)
    ax.set_xlabel("flight time [s]")
    ax.set_ylabel("altitude z [m]")
    ax.grid(alpha=0.3)
    _markers(ax, traces)
    ax.legend(fontsize=8, loc="lower center", ncols=2)
    _title(fig, traces, "Altitude")
    return fig


def _error_xyz(traces: Sequence[FlightTrace]) -> Figure:
    fig = Figure(figsize=(9.0, 6.8), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    where = "pattern window" if _any_window(traces) else "whole flight"
    for i, (ax, axis) in enumerate(zip(axes, "xyz")):
        _window(ax, traces)
        for tr, color in _colored(traces):
            err_mm = (tr.p[:, i] - tr.p_ref[:, i]) * 1e3
            ax.plot(tr.t, err_mm, color=color, lw=0.9, label=f"RMS {_rms(err_mm, tr):.2f} mm")
        ax.axhline(0.0, color="0.3", lw=0.6)
        ax.set_ylabel(f"{axis} error [mm]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right", title=f"on the {where}" if i == 0 else None, title_fontsize=8)
    axes[-1].set_xlabel("flight time [s]")
    _names_legend(fig, traces)
    _title(fig, traces, "Position error per axis")
    return fig


def _timing(traces: Sequence[FlightTrace]) -> Figure:
    fig = Figure(figsize=(10.0, 4.4), layout="constrained")
    ax_tick, ax_solve = fig.subplots(1, 2)
    for ax, attr, what in ((ax_tick, "compute_ms", "tick compute"), (ax_solve, "solve_ms", "MPC solve")):
        values = [getattr(tr, attr) for tr in traces]
        finite = np.concatenate([v[v > 0] for v in values])
        if len(finite) == 0:
            ax.text(0.5, 0.5, f"no {what} times in the log", ha="center", va="center", transform=ax.transAxes)
        else:
            lo, hi = max(float(finite.min()), 1e-3), float(finite.max())
            bins = np.geomspace(lo * 0.9, max(hi * 1.1, lo * 2), 60)
            for (tr, color), v in zip(_colored(traces), values):
                if len(v):
                    med, p99 = np.percentile(v, (50, 99))
                    ax.hist(v, bins=bins, histtype="step", color=color, lw=1.2,
                            label=f"median {med:.3f}, p99 {p99:.3f} ms")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
            if attr == "compute_ms":
                deadline = traces[0].deadline_ms
                ax.axvline(deadline, color="tab:red", ls="--", lw=1, label=f"deadline {deadline:.2f} ms")
            ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
        ax.set_xlabel(f"{what} time [ms] (log scale)")
        ax.set_ylabel("ticks")
        ax.grid(alpha=0.3, which="major")
    _names_legend(fig, traces)
    _title(fig, traces, "Tick compute and MPC solve times")
    return fig


def _model_versions(traces: Sequence[FlightTrace]) -> Figure:
    fig = Figure(figsize=(9.0, 3.8), layout="constrained")
    ax = fig.subplots()
    top = 0
    for k, (tr, color) in enumerate(_colored(traces)):
        t, v = _version_steps(tr)
        top = max(top, int(v.max()), *(version for _, version, _ in tr.model_events))
        # Overlaid flights that fly the same versions are offset slightly so both stay visible.
        dy = 0.06 * (k - (len(traces) - 1) / 2)
        ax.step(t, v + dy, where="post", color=color, lw=1.4, label=_label(tr, traces))
        for t_e, version, event in tr.model_events:
            c, m = _EVENT_STYLE.get(event, ("0.3", "."))
            ax.plot(t_e, version + dy, ls="", marker=m, color=c, ms=6, mew=1.5)
    if not any(tr.model_events for tr in traces):
        ax.text(0.5, 0.55, "no model events: the nominal or an offline model flew throughout",
                ha="center", va="center", transform=ax.transAxes, color="0.35")
    handles, labels = ax.get_legend_handles_labels()
    for event, (c, m) in _EVENT_STYLE.items():
        if any(e == event for tr in traces for *_, e in tr.model_events):
            handles.append(Line2D([], [], ls="", marker=m, color=c, mew=1.5))
            labels.append(event)
    ax.legend(handles, labels, fontsize=8, loc="upper left")
    ax.set_ylim(-0.5, top + 1.5)
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("flight time [s]")
    ax.set_ylabel("model version flying")
    ax.grid(alpha=0.3)
    _title(fig, traces, "Model versions")
    return fig


# --- Helpers ---------------------------------------------------------------------------------


def _colored(traces: Sequence[FlightTrace]) -> list[tuple[FlightTrace, str]]:
    return [(tr, _COLORS[i % len(_COLORS)]) for i, tr in enumerate(traces)]


def _label(tr: FlightTrace, traces: Sequence[FlightTrace]) -> str:
    """Legend name of a flight: "flight" alone (the title names it), else its name."""
    return "flight" if len(traces) == 1 else tr.name


def _names_legend(fig: Figure, traces: Sequence[FlightTrace]) -> None:
    """With several flights, one legend below the plots says which colour is which."""
    if len(traces) > 1:
        handles = [Line2D([], [], color=color, lw=1.5) for _, color in _colored(traces)]
        fig.legend(handles, [tr.name for tr in traces], fontsize=8, loc="outside lower center", ncols=1)


def _references(ax: Axes, traces: Sequence[FlightTrace], xy: Any) -> None:
    # One dashed black line per distinct reference (flights of the same mission share one).
    distinct: dict[str, FlightTrace] = {}
    for tr in traces:
        distinct.setdefault(tr.reference_key, tr)
    styles = ("--", ":", "-.")
    colors = {id(o): c for o, c in _colored(traces)}
    for k, tr in enumerate(distinct.values()):
        label = "reference" if len(distinct) == 1 else f"reference of {tr.name}"
        # The longest flight of a mission carries its whole reference (others may be truncated).
        same = [o for o in traces if o.reference_key == tr.reference_key]
        # A fleet drone's own reference is dashed in its colour: the drones fly different ones.
        color, ls = (colors[id(tr)], "--") if tr.drone else ("black", styles[k % 3])
        ax.plot(*xy(max(same, key=lambda o: len(o.t))), color=color, ls=ls, lw=1.0, label=label)


def _window(ax: Axes, traces: Sequence[FlightTrace]) -> None:
    """Shade the pattern window: grey when the flights share it, else each in a tint of its colour."""
    windows = {tr.window for tr in traces if tr.window is not None}
    if len(windows) == 1:
        ax.axvspan(*windows.pop(), color="0.93", zorder=0, lw=0)
        return
    for tr, color in _colored(traces):
        if tr.window is not None:
            ax.axvspan(*tr.window, color=color, alpha=0.07, zorder=0, lw=0)


def _any_window(traces: Sequence[FlightTrace]) -> bool:
    return any(tr.window is not None for tr in traces)


def _markers(ax: Axes, traces: Sequence[FlightTrace]) -> None:
    """Mass changes as dotted lines with their factor; model events as short coloured ticks at the top."""
    seen: set[tuple[float, float]] = set()
    for tr in traces:
        for t, factor in tr.mass_changes:
            if (t, factor) in seen:
                continue
            seen.add((t, factor))
            ax.axvline(t, color="0.25", ls=":", lw=1.2)
            ax.annotate(f"mass x{factor:g}", (t, 0.5), xycoords=("data", "axes fraction"), xytext=(-4, 0),
                        textcoords="offset points", fontsize=8, color="0.25", rotation=90, ha="right",
                        va="center")
    for tr, color in _colored(traces):
        for t, version, event in tr.model_events:
            c, _ = _EVENT_STYLE.get(event, ("0.3", "."))
            ax.axvline(t, ymin=0.93, ymax=1.0, color=c, lw=1.5)
    if seen:
        ax.plot([], [], color="0.25", ls=":", lw=1.2, label="mass change")
    for event, (c, _) in _EVENT_STYLE.items():
        if any(e == event for tr in traces for *_, e in tr.model_events):
            ax.plot([], [], color=c, lw=1.5, label=f"model {event}")


def _version_steps(tr: FlightTrace) -> tuple[np.ndarray, np.ndarray]:
    """Flying version over time: 0 (nominal) until the first swap; swaps and rollbacks change it."""
    t0 = float(tr.t[0]) if len(tr.t) else 0.0
    times, versions = [t0], [0]
    for t, version, event in tr.model_events:
        if event in ("swap", "rollback"):
            times.append(t)
            versions.append(version)
    times.append(max(tr.t_end, times[-1]))
    versions.append(versions[-1])
    return np.asarray(times), np.asarray(versions, dtype=float)


def _rms(err: np.ndarray, tr: FlightTrace) -> float:
    if tr.window is not None:
        err = err[(tr.t >= tr.window[0]) & (tr.t <= tr.window[1])]
    err = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(err * err))) if len(err) else math.nan


def _title(fig: Figure, traces: Sequence[FlightTrace], what: str) -> None:
    if len({tr.path for tr in traces}) == 1 and traces[0].drone:
        tr = traces[0]
        sub = f"{tr.path.stem} · fleet: {', '.join(t.drone for t in traces)}" + (
            "" if tr.true_positions else " (estimated positions)")
    elif len(traces) == 1:
        tr = traces[0]
        sub = tr.name + ("" if tr.true_positions else " (estimated positions)")
    else:
        sub = f"{len(traces)} flights"
    cut = [tr for tr in traces if tr.truncated]
    if cut:
        ends = {tr.path.stem: tr.t_end for tr in cut}  # a fleet log's drones: once
        sub += "; truncated: " + ", ".join(f"{stem} at {t_end:.2f} s" for stem, t_end in ends.items())
    fig.suptitle(f"{what}\n{sub}", fontsize=10)


def _controller_label(config: dict[str, Any], log: LogData | LogColumns) -> str:
    kind = _get(config, "controller.kind", "?")
    label = f"{kind} ({_get(config, 'controller.solver', '?')})" if kind == "mpc" else str(kind)
    if any(m.get("event") == "swap" for m in log.topic("/model")):
        label += " + KNODE online"
    return label


def _pattern_window(log: LogData | LogColumns) -> tuple[float, float] | None:
    summary = log.topic("/summary")
    try:
        t0, t1 = summary[-1]["window"]
        return float(t0), float(t1)
    except (IndexError, KeyError, TypeError, ValueError):
        pass
    try:  # a truncated log has no summary: the window follows from the trajectory config
        from cfknode.flight.trajectory import make_trajectory
        from cfknode.app.replay import logged_config

        cfg, _ = logged_config(log)
        return make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float)).pattern_window
    except (ValueError, KeyError, TypeError):
        return None


def _number(value: Any, default: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        return default
    return x if math.isfinite(x) and x > 0 else default


def _mass_changes(changes: Any) -> tuple[tuple[float, float], ...]:
    """``sim.mass_changes`` of the logged config; entries that are not {t, factor} numbers are left out."""
    out = []
    for change in changes if isinstance(changes, list) else []:
        try:
            out.append((float(change["t"]), float(change["factor"])))
        except (KeyError, TypeError, ValueError):
            continue
    return tuple(out)


def _get(config: dict[str, Any], dotted: str, default: Any) -> Any:
    node: Any = config
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return default
        node = node[part]
    return node
