"""``cfknode bench learning``: cells where a learned residual should beat the fast layer alone.

The realistic plant (``sim.aero: realistic``) on the manoeuvres of ``learning_cells``; per cell four rows:
nominal MPC, MPC + the configured fast layer, KNODE-MPC-Online + that layer, and the paper's method
(KNODE-MPC-Online without a layer). Lockstep flights with a fixed online latency, so the numbers do not
depend on the machine's load; one flight per (cell, row, seed), run in parallel processes by the bench
executor (``--jobs``). The table gives per cell the median MSE over the seeds, online+layer / layer and
online+layer / nominal (medians), and falls and supervisor trips. A cell the Crazyflie cannot fly is
listed as refused, with the reason, and not flown.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.bench.learning_cells import (CELLS, CONTROLLERS, FLEET_ONLY, GROUPS, LABELS, QUICK_CELLS,
                                              QUICK_DURATION, LearnCell, ground_threshold, pass_errors, refusal)
from cfknode.app.bench.rows import DEFAULT_FIXED_LATENCY_S


@dataclass(frozen=True)
class Run:
    """One flight: ``mse`` of the drone the cell measures (the lowest of a fleet), ``mse_other`` of the
    fleet's other drones (NaN for one drone)."""

    cell: str
    controller: str
    seed: int
    mse: float
    mse_z: float
    max_error: float
    fell: bool  # below ground_threshold during the pattern
    tripped: bool  # the supervisor ended the flight otherwise than "flight complete"
    outcome: str
    models_accepted: int
    windows: int
    wall_s: float
    mse_other: float = math.nan
    passes: tuple[float, ...] = ()  # a crossing cell: MSE of the lower drone around each pass under the wake


@dataclass(frozen=True)
class Job:
    cell: LearnCell
    controller: str
    seed: int
    log_dir: str
    duration: float
    extra: tuple[tuple[str, Any], ...] = ()  # the command line's --set overrides, on every flight
    latency_s: float = DEFAULT_FIXED_LATENCY_S


def flight_overrides(job: Job) -> dict[str, Any]:
    """The flight's config overrides: the cell's, the row's, then the fixed latency and the user's --set."""
    return {**job.cell.config(job.controller, job.seed, job.log_dir, job.duration),
            "online.latency": "fixed", "online.fixed_latency_s": job.latency_s, **dict(job.extra)}


def _verdicts(cell: LearnCell, summary: Any, record: Any, outcome: Any) -> tuple[bool, bool]:
    t0, t1 = summary.window
    inside = (record.t >= t0) & (record.t <= t1)
    fell = bool(np.any(record.p[inside, 2] < ground_threshold(cell))) if inside.any() else True
    return fell, not outcome.message.startswith("flight complete")


def run_job(job: Job) -> Run:
    """One flight (a fleet flight for a stacked cell) and its verdicts; the bench executor's task. A flight that
    could not fly (its trainer did not start, say) is a row of its own, not the end of the bench."""
    start = time.perf_counter()
    try:
        return _fly(job, start)
    except Exception as exc:  # noqa: BLE001 - every other flight still flies; the error is reported in the table
        return Run(job.cell.name, job.controller, job.seed, math.nan, math.nan, math.nan, False, True,
                   f"did not fly: {exc}", 0, 0, time.perf_counter() - start)


def _fly(job: Job, start: float) -> Run:
    from cfknode.app.config import load_config

    cfg = load_config(overrides=flight_overrides(job))
    slug = f"{job.cell.name}-{job.controller}-s{job.seed}".replace(" ", "_").replace("=", "").replace("+", "p")
    if job.cell.fleet > 1:
        from cfknode.app.fleet.flight import run_fleet

        res = run_fleet(cfg, name_hint=slug)
        # The lowest drone flies in the others' wake: it is the one measured.
        low = min(res.drones, key=lambda d: float(np.median(d.record.p_ref[:, 2])))
        others = [d for d in res.drones if d is not low]
        fell = tripped = False
        for d in res.drones:
            f, s = _verdicts(job.cell, d.summary, d.record, d.outcome)
            fell, tripped = fell or f, tripped or s
        s, outcome = low.summary, "; ".join(f"{d.name}: {d.outcome.message}" for d in res.drones)
        other = float(np.mean([d.summary.mse for d in others]))
        passes = crossing_passes(cfg, low.record) if job.cell.layout == "crossing" else ()
    else:
        from cfknode.app.mission import run_flight

        one = run_flight(cfg, name_hint=slug)
        s, outcome, other, passes = one.summary, one.outcome.message, math.nan, ()
        fell, tripped = _verdicts(job.cell, s, one.record, one.outcome)
    extra = s.extra
    return Run(job.cell.name, job.controller, job.seed, float(s.mse), float(s.mse_z), float(s.max_error), fell, tripped,
               outcome, int(extra.get("models_accepted") or 0), int(extra.get("windows_completed") or 0),
               time.perf_counter() - start, other, passes)


def crossing_passes(cfg: Any, record: Any) -> tuple[float, ...]:
    """MSE of ``record`` in the window around each time its line crosses the centre, under the drone above."""
    from cfknode.flight.trajectory import make_trajectory

    times = make_trajectory(cfg.trajectory, (0.0, 0.0, 0.0)).phase_times(math.pi)  # the crossings need no start
    err2 = np.sum((record.p - record.p_ref) ** 2, axis=1) / 3.0  # mean over the axes, as the MSE
    return tuple(float(v) for v in pass_errors(record.t, err2, times))


# --- report ------------------------------------------------------------------------------------


def median_mse(runs: list[Run], cell: str, controller: str) -> float:
    m = [r.mse for r in runs if r.cell == cell and r.controller == controller]
    return float(np.median(m)) if m else math.nan


def ratio(runs: list[Run], cell: str, num: str, den: str) -> float:
    """Median over the seeds of ``num``'s MSE over ``den``'s, seed by seed (NaN without a pair)."""
    by = {r.seed: r.mse for r in runs if r.cell == cell and r.controller == den and math.isfinite(r.mse)}
    r = [x.mse / by[x.seed] for x in runs
         if x.cell == cell and x.controller == num and math.isfinite(x.mse) and by.get(x.seed, 0.0) > 0.0]
    return float(np.median(r)) if r else math.nan


def _cell_heading(cell: LearnCell) -> str:
    what = {"circle": f"circle r = {cell.radius:g} m at {cell.speed:g} m/s ({cell.frequency_hz:.2f} laps/s)",
            "vertical": f"up and down +-{cell.radius:g} m about {cell.height:g} m, peak climb {cell.speed:.2f} m/s "
                        f"({cell.frequency_hz:.2f} Hz)",
            "line": f"back and forth +-{cell.radius:g} m along x at {100 * cell.height:g} cm, peak {cell.speed:g} m/s"}
    text = what.get(cell.kind, cell.kind) + f", peak acceleration {cell.peak_acceleration:.1f} m/s^2"
    if cell.layout == "crossing":
        text += f"; cf2 hovers {cell.spacing:g} m over the line's centre, cf1 (under it) measured"
    elif cell.fleet > 1:
        text += f"; {cell.fleet} drones stacked {cell.spacing:g} m apart, the lowest measured"
    return text


def cell_table(cell: LearnCell, runs: list[Run], controllers: tuple[str, ...]) -> list[str]:
    mine = [r for r in runs if r.cell == cell.name]
    seeds = sorted({r.seed for r in mine})
    lines = [f"**{cell.name}**: {_cell_heading(cell)}; seeds {', '.join(map(str, seeds))}", "",
             "| controller | MSE [m^2] | max error [mm] | / layer | / nominal | models kept | falls | trips |",
             "|---|---|---|---|---|---|---|---|"]
    for c in controllers:
        rs = [r for r in mine if r.controller == c and math.isfinite(r.mse)]
        lost = [r for r in mine if r.controller == c and not math.isfinite(r.mse)]
        if lost and not rs:
            lines.append(f"| {LABELS[c]} | did not fly | - | - | - | - | 0 | {len(lost)} |")
        if not rs:
            continue
        m = np.array([r.mse for r in rs])
        mse = f"{np.median(m):.3g} [{m.min():.3g}, {m.max():.3g}]" if m.size > 1 else f"{m[0]:.3g}"
        if cell.fleet > 1:
            mse += f" (upper {np.median([r.mse_other for r in rs]):.3g})"
        vs = [ratio(runs, cell.name, c, d) for d in ("layer", "nominal")]
        lines.append(f"| {LABELS[c]} | {mse} | {1000 * np.median([r.max_error for r in rs]):.1f} | "
                     + " | ".join("-" if not math.isfinite(v) or c == d else f"{v:.2f}" for v, d in zip(vs, ("layer", "nominal")))
                     + f" | {int(np.median([r.models_accepted for r in rs]))} | {sum(r.fell for r in rs)} | "
                     f"{sum(r.tripped for r in rs)} |" + (pass_cells(rs) if cell.layout == "crossing" else ""))
    if cell.layout == "crossing":
        lines[2] += " pass 1 [m^2] | last pass [m^2] | last / first | passes |"
        lines[3] += "---|---|---|---|"
    lost = [r for r in mine if not math.isfinite(r.mse)]
    if lost:
        lines += ["", "Did not fly (counted as trips): " + "; ".join(f"{LABELS[r.controller]} seed {r.seed}: {r.outcome}"
                                                                    for r in lost)]
    return lines


def pass_cells(runs: list[Run]) -> str:
    """' first | last | last / first | n |': medians over the seeds of the first and the last pass's MSE."""
    firsts = [r.passes[0] for r in runs if r.passes and math.isfinite(r.passes[0])]
    lasts = [r.passes[-1] for r in runs if r.passes and math.isfinite(r.passes[-1])]
    if not firsts or not lasts:
        return " - | - | - | 0 |"
    first, last = float(np.median(firsts)), float(np.median(lasts))
    return f" {first:.3g} | {last:.3g} | {last / first:.2f} | {min(len(r.passes) for r in runs)} |"


def markdown(cells: list[LearnCell], refused: list[str], runs: list[Run], controllers: tuple[str, ...],
             command: str, version: str, mode: str, layer: str) -> str:
    lines = ["## Learning bench: where learning should win", "",
             f"`{command}`, cfknode {version}, mode {mode}. Realistic plant (`sim.aero: realistic`), lockstep, "
             f"online latency fixed; the layer rows fly `controller.adaptation: {layer}`. MSE in m^2 on the pattern "
             "(mean over the axes): median over the seeds [min, max]; / layer and / nominal: the row's MSE over "
             "that row's, seed by seed, median; models kept: models the online learner flew (median); falls: "
             "flights below half the height (5 cm at most) during the pattern; trips: flights the supervisor ended "
             "otherwise than \"flight complete\"."]
    for group in GROUPS:
        mine = [c for c in cells if c.group == group and any(r.cell == c.name for r in runs)]
        for cell in mine:
            lines += ["", *cell_table(cell, runs, controllers)]
    if refused:
        lines += ["", "Refused (the Crazyflie cannot fly them): " + "; ".join(refused) + "."]
    rows = [(c.name, ratio(runs, c.name, "online+layer", "layer"), ratio(runs, c.name, "online+layer", "nominal"),
             ratio(runs, c.name, "online", "nominal"), ratio(runs, c.name, "air+layer", "layer"),
             ratio(runs, c.name, "wake+layer", "layer"))
            for c in cells if any(r.cell == c.name for r in runs)]
    lines += ["", "| cell | online+layer / layer | online+layer / nominal | online (paper) / nominal | "
              "the plant's air + layer / layer (ceiling) | the plant's wake + layer / layer |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | " + " | ".join(f"{v:.2f}" if math.isfinite(v) else "-" for v in vs) + " |" for n, *vs in rows]
    return "\n".join(lines)


# --- command -----------------------------------------------------------------------------------


def add_learning_arguments(p: argparse.ArgumentParser) -> None:
    from cfknode.app.bench.executor import add_executor_arguments

    p.add_argument("--quick", action="store_true",
                   help=f"one seed, {QUICK_DURATION:g} s of pattern, cell {', '.join(QUICK_CELLS)} unless --cells names others")
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 per cell and controller (default 3)")
    p.add_argument("--groups", default="", help=f"comma-separated subset of {', '.join(GROUPS)} (default: all)")
    p.add_argument("--cells", default="", help="comma-separated cell names (default: every cell of the groups)")
    p.add_argument("--duration", type=float, default=0.0, help="s of pattern, overriding the cells' (0: theirs)")
    p.add_argument("--rows", default="", help=f"comma-separated subset of the rows {', '.join(CONTROLLERS)} (default: all)")
    p.add_argument("--config", default="", metavar="FILE",
                   help="a YAML file overriding the defaults on every flight (e.g. "
                        "examples/learning-in-a-wake.yaml); --set comes after it")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override on every flight (e.g. a layer to bench), repeatable")
    p.add_argument("--fixed-latency", type=float, default=DEFAULT_FIXED_LATENCY_S, metavar="S",
                   help=f"s from a window's end to its model flying (default {DEFAULT_FIXED_LATENCY_S:g})")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    p.add_argument("--out", default="bench_out", help="output directory (default ./bench_out)")
    add_executor_arguments(p, 2, "")


def select_cells(args: argparse.Namespace) -> list[LearnCell]:
    from cfknode.app.errors import UsageError

    groups = tuple(g.strip() for g in args.groups.split(",") if g.strip()) or GROUPS
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise UsageError(f"unknown group(s) {', '.join(unknown)}; known: {', '.join(GROUPS)}")
    names = tuple(n.strip() for n in args.cells.split(",") if n.strip()) or (QUICK_CELLS if args.quick else ())
    known = {c.name for c in CELLS}
    if any(n not in known for n in names):
        raise UsageError(f"unknown cell(s) {', '.join(n for n in names if n not in known)}; known: {', '.join(known)}")
    return [c for c in CELLS if (c.name in names) or (not names and c.group in groups)]


def select_rows(text: str) -> tuple[str, ...]:
    """``--rows``: the named rows in the table's order (all of them for an empty string)."""
    from cfknode.app.errors import UsageError

    names = {n.strip() for n in text.split(",") if n.strip()}
    unknown = sorted(names - set(CONTROLLERS))
    if unknown:
        raise UsageError(f"unknown row(s) {', '.join(unknown)}; known: {', '.join(CONTROLLERS)}")
    return tuple(c for c in CONTROLLERS if not names or c in names)


def cell_refusal(cell: LearnCell, extra: tuple[tuple[str, Any], ...] = ()) -> str | None:
    """Why ``cell`` is not flown (None: it is): the pattern's peak acceleration against the Crazyflie's thrust
    (``refusal``), then the pre-flight check every flight passes (which also keeps a reserve for tilt)."""
    from cfknode.app.config import load_config
    from cfknode.app.trajectory_fit import trajectory_problem

    cfg = load_config(overrides=flight_overrides(Job(cell, "layer", 0, tempfile.gettempdir(), cell.duration, extra)))
    why = refusal(cell, cfg.vehicle, cfg.controller.min_thrust_fraction, cfg.controller.max_thrust_fraction)
    problem = None if why else trajectory_problem(cfg)
    return why or (f"{cell.name}: {problem}" if problem else None)


def _parse_sets(items: list[str]) -> tuple[tuple[str, Any], ...]:
    """``--set KEY=VALUE`` flags, parsed as ``cfknode fly`` parses them."""
    from cfknode.app.config import parse_override

    return tuple(parse_override(item) for item in items)


def _file_overrides(path: str) -> tuple[tuple[str, Any], ...]:
    """A config file's keys as dotted overrides (checked whole first: a bad file is a one-line error)."""
    if not path:
        return ()
    from cfknode.app.config import dotted, load_config, read_yaml_mapping

    load_config(path)
    return tuple(dotted(read_yaml_mapping(Path(path))).items())


def run_learning(args: argparse.Namespace, version: str) -> int:
    from rich.console import Console

    from cfknode.app.bench.executor import ExecutorSettings, run_ordered
    from cfknode.app.config import load_config
    from cfknode.app.errors import UsageError

    executor = ExecutorSettings.from_args(args)
    if args.seeds < 1 or args.duration < 0 or not 0.0 <= args.fixed_latency <= 60.0:
        raise UsageError("--seeds must be >= 1, --duration >= 0 and --fixed-latency in [0, 60] s")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is not a directory")
    extra = _file_overrides(args.config) + _parse_sets(args.set)
    base = load_config(overrides=dict(extra))
    cells, refused = [], []
    for cell in select_cells(args):
        why = cell_refusal(cell, extra)
        (refused.append(why) if why else cells.append(cell))
    seeds = (0,) if args.quick else tuple(range(args.seeds))
    duration = args.duration or (QUICK_DURATION if args.quick else 0.0)
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="cfknode-bench-learning-", dir=out))
    controllers = select_rows(args.rows)
    jobs = [Job(c, k, s, str(logs), duration or c.duration, extra, args.fixed_latency)
            for c in cells for s in seeds for k in controllers if c.fleet >= 2 or k not in FLEET_ONLY]
    mode = "quick" if args.quick else "full"
    command = _command(args, executor)
    console = Console(stderr=args.json)
    console.print(f"bench learning: {len(cells)} cell(s) x {len(controllers)} controllers x {len(seeds)} seed(s) = "
                  f"{len(jobs)} flights on {executor.describe()}" + (f"; {len(refused)} refused" if refused else ""))
    stem = "learning" + ("_quick" if args.quick else "")
    done = out / f"{stem}_runs.jsonl"  # each flight as it lands: a bench stopped midway keeps what it flew
    done.write_text("")

    def landed(i: int, r: Run) -> str:
        with done.open("a") as f:
            f.write(json.dumps(_finite(asdict(r))) + "\n")
        return f"{r.cell} / {r.controller} / seed {r.seed}: {r.mse:.3g}"

    runs: list[Run] = run_ordered(run_job, jobs, executor, "bench learning", console=console, describe=landed)
    shown = [replace(c, duration=duration or c.duration) for c in cells]
    md = markdown(shown, refused, runs, controllers, command, version, mode, base.controller.adaptation)
    payload = {"command": command, "version": version, "mode": mode, "layer": base.controller.adaptation,
               "seeds": list(seeds), "refused": refused, "cells": [asdict(c) for c in shown],
               "runs": [asdict(r) for r in runs]}
    (out / f"{stem}.md").write_text(md + "\n")
    text = json.dumps(_finite(payload), indent=1, default=str)
    (out / f"{stem}.json").write_text(text)
    if args.json:
        print(text)
    else:
        console.print(md, markup=False, highlight=False)  # "[m^2]", "[min, max]" are text, not markup
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}; flight logs in {logs}")
    return 0


def _finite(value: Any) -> Any:
    """``value`` with every NaN or infinity as None: strict JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _command(args: argparse.Namespace, executor: Any) -> str:
    cmd = "cfknode bench learning" + (" --quick" if args.quick else f" --seeds {args.seeds}") + f" {executor.command_flags()}"
    for flag, value in (("--groups", args.groups), ("--cells", args.cells), ("--rows", args.rows)):
        if value:
            cmd += f" {flag} '{value}'"
    if args.duration:
        cmd += f" --duration {args.duration:g}"
    if args.fixed_latency != DEFAULT_FIXED_LATENCY_S:
        cmd += f" --fixed-latency {args.fixed_latency:g}"
    cmd += f" --config {args.config}" if args.config else ""
    return cmd + "".join(f" --set {s}" for s in args.set)


__all__ = ["Job", "Run", "add_learning_arguments", "cell_table", "flight_overrides", "markdown", "median_mse", "ratio",
           "run_job", "run_learning", "select_cells", "select_rows"]
