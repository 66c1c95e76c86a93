"""``cfknode bench online``: the online-learning acceptance protocol, flown by the whole stack.

Two cells with the paper's mass changes (``cfknode.app.bench.mass_steps``): the lab circle (0.5 m,
0.4 m/s, 30 s) and one paper cell (r = 2 m, 0.8 m/s, 8 s). Per cell: the offline KNODE-MPC is
trained on a flight that saw only the first change, then nominal MPC, offline KNODE-MPC and
KNODE-MPC-Online fly the same seeded scenario, once per seed. A third cell is the lab
protocol of docs/design.md#targets (the same circle, +4.1 % mass at 5 s), against nominal MPC
and the geometric controller. Every cell also flies the geometric controller, MPC and
KNODE-MPC-Online with the fast adaptation layer (dob), and the oracle (the same MPC told the
true mass at every tick), and reports each mass step's time to recover. Online learning runs
with a reproducible latency by default (``--latency fixed``: the same numbers on a loaded
machine); ``--latency wall`` flies its trainer's real wall time, which varies from run to run.
The table gives the median and the range over the seeds, and the online/baseline ratios of
each seed. Flights run one at a time.
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.bench.rows import (BENCH_AERO, LABELS, ORACLE, add_latency_arguments, add_plant_arguments,
                                check_latency_arguments, latency_flags, latency_note, latency_overrides, peak_text,
                                plant_flags, plant_overrides, recovery_legend, recovery_text, summary_lines)
from cfknode.app.bench.mass_steps import PAPER_STEPS

COMPARED = ("geometric", "nominal", "offline", "online", "dob", "online_dob", "oracle")
ACCEPTANCE = ("nominal", "offline", "geometric")  # online must beat these (the others are references)


@dataclass(frozen=True)
class CellSpec:
    name: str
    radius: float
    speed: float
    duration: float
    overrides: tuple[tuple[str, Any], ...] = ()
    steps: tuple[tuple[float, float], ...] = PAPER_STEPS
    controllers: tuple[str, ...] = COMPARED  # "offline" trains on a flight with the first step only

    def config(self, log_dir: str, seed: int) -> dict[str, Any]:
        return {
            "trajectory.kind": "circle",
            "trajectory.radius": self.radius,
            "trajectory.speed": self.speed,
            "trajectory.duration": self.duration,
            # A bench, not people: every controller may show its error (a lab fence would land the worst).
            "safety.max_tracking_error": 3.0,
            "safety.fence_min": [-self.radius - 1.5, -self.radius - 1.5, -0.2],
            "safety.fence_max": [self.radius + 1.5, self.radius + 1.5, 4.0],
            "sim.aero": BENCH_AERO,
            "sim.seed": seed,
            "log.dir": log_dir,
            **dict(self.overrides),
        }


LAB = CellSpec("lab circle", 0.5, 0.4, 30.0)
# The paper's cell as the hierarchical bench flies it: full speed from the start, 1.5 m up.
PAPER = CellSpec("paper r=2 v=0.8", 2.0, 0.8, 8.0, (("trajectory.ramp_duration", 0.0), ("trajectory.height", 1.5)))
QUICK = CellSpec("paper r=2 v=0.8, 4 s", 2.0, 0.8, 4.0, PAPER.overrides, ((1.0, 0.5), (2.5, 1.33)))
LAB_SMALL = CellSpec("lab circle +4.1 %", 0.5, 0.4, 30.0, steps=((5.0, 1.041),),
                     controllers=tuple(c for c in COMPARED if c != "offline"))


@dataclass(frozen=True)
class Run:
    controller: str
    seed: int
    mse: float
    mse_z: float
    outcome: str
    online: dict[str, Any] = field(default_factory=dict)
    recovery: tuple[dict[str, Any], ...] = ()  # per mass step: time to recover, peak error (FlightSummary.recovery)


@dataclass(frozen=True)
class CellReport:
    cell: CellSpec
    runs: tuple[Run, ...]
    wall_s: float

    @property
    def baselines(self) -> tuple[str, ...]:
        return tuple(c for c in self.flown if c in ACCEPTANCE)

    @property
    def flown(self) -> tuple[str, ...]:
        """The cell's controllers that have runs, in the cell's order."""
        return tuple(c for c in self.cell.controllers if any(r.controller == c for r in self.runs))

    def mse(self, controller: str) -> np.ndarray:
        return np.array([r.mse for r in self.runs if r.controller == controller])

    def ratios(self, baseline: str) -> np.ndarray:
        """Online MSE / baseline MSE, seed by seed."""
        by_seed = {r.seed: r.mse for r in self.runs if r.controller == baseline}
        return np.array([r.mse / by_seed[r.seed] for r in self.runs if r.controller == "online" and r.seed in by_seed])

    @property
    def met(self) -> bool:
        """Online's median MSE below every baseline's median."""
        on = float(np.median(self.mse("online")))
        return all(on < float(np.median(self.mse(b))) for b in self.baselines)


def run_cell(cell: CellSpec, seeds: tuple[int, ...], out: Path, progress: Any = None,
             extra: dict[str, Any] | None = None) -> CellReport:
    """Every controller and seed on one cell; ``extra``: overrides for every flight (the online latency, the plant)."""
    from cfknode.app.config import load_config
    from cfknode.app.bench.mass_steps import CONTROLLER_OVERRIDES, mass_schedule, train_offline_model
    from cfknode.app.mission import run_flight

    start = time.perf_counter()
    name = cell.name.replace(" ", "-").replace("=", "").replace(",", "").replace("%", "pc")
    base = {**cell.config(str(out), seeds[0]), **(extra or {})}
    at, factors = zip(*cell.steps)
    schedule = mass_schedule(base, at, factors)
    model = train_offline_model(base, schedule, out, name) if "offline" in cell.controllers else None
    runs = []
    for seed in seeds:
        for controller in cell.controllers:
            overrides = {**cell.config(str(out), seed), "sim.mass_changes": list(schedule.both), **(extra or {}),
                         **CONTROLLER_OVERRIDES[controller](model)}
            res = run_flight(load_config(overrides=overrides), name_hint=f"{name}-{controller}-s{seed}")
            online = {}
            if controller == "online":
                online = {k: v for k, v in res.summary.extra.items()
                          if k.startswith(("models_", "swap_", "install_", "train_wall", "latency_", "rounds_slower", "ticks_late"))}
                online.update(speed_factor=res.summary.speed_factor, missed_deadlines=res.summary.missed_deadlines,
                              ticks=res.summary.ticks, t_col=res.summary.extra.get("online_t_col_s"))
            runs.append(Run(controller, seed, res.summary.mse, res.summary.mse_z, res.outcome.message, online,
                            tuple(dict(r) for r in res.summary.recovery)))
            if progress is not None:
                progress(f"{cell.name} seed {seed} {controller}: MSE {res.summary.mse:.3g}")
    return CellReport(cell, tuple(runs), time.perf_counter() - start)


NAMES = LABELS


def markdown(reports: list[CellReport], command: str, version: str, latency_note: str = "") -> str:
    lines = [
        "## Online learning (acceptance protocol)",
        "",
        f"`{command}`, cfknode {version}. MSE in m^2 on the pattern (mean over the axes): median over the "
        "seeds, [min, max] in brackets; online / this: online's MSE over this row's, seed by seed. " + latency_note,
        "", "Time to recover: median over the seeds, per mass step; peak: from the first seed. " + recovery_legend(),
    ]
    for rep in reports:
        steps = ", ".join(f"{f:g}x at {t:g} s" for t, f in rep.cell.steps)
        lines += ["", f"**{rep.cell.name}** (r = {rep.cell.radius:g} m, {rep.cell.speed:g} m/s, {rep.cell.duration:g} s; "
                  f"mass {steps} into the pattern; {len(set(r.seed for r in rep.runs))} seeds)", "",
                  "| controller | MSE | / oracle | online / this | time to recover [s] | peak error [m] |",
                  "|---|---|---|---|---|---|"]
        oracle = rep.mse(ORACLE)
        for c in rep.flown:
            m = rep.mse(c)
            mse = f"{np.median(m):.4g} [{m.min():.3g}, {m.max():.3g}]" if m.size > 1 else f"{m[0]:.4g}"
            to_oracle = f"{np.median(m) / np.median(oracle):.2f}" if oracle.size and np.median(oracle) > 0 else "-"
            r = rep.ratios(c) if c != "online" else np.zeros(0)
            vs = f"{np.median(r):.2f} (wins {int((r < 1).sum())}/{r.size})" if r.size else "-"
            recs = [x.recovery for x in rep.runs if x.controller == c]
            lines.append(f"| {NAMES[c]} | {mse} | {to_oracle} | {vs} | {_median_recovery(recs)} | "
                         f"{peak_text(recs[0]) if recs else '-'} |")
        lines += ["", f"| acceptance: online's median below {', '.join(NAMES[b] for b in rep.baselines)} "
                  f"| {'yes' if rep.met else 'no'} |", "|---|---|"]
    medians = [{c: float(np.median(rep.mse(c))) for c in rep.flown} for rep in reports]
    lines += ["", *summary_lines(medians, COMPARED)]
    lines += ["", "| cell | swap median / max [ms] | install slice max [ms] | training round median / max [s] "
              "| t_col [s] | models trained / accepted / rejected / dropped | missed ticks (late from install) | speed |",
              "|---|---|---|---|---|---|---|---|"]
    for rep in reports:
        for r in (r for r in rep.runs if r.controller == "online"):
            o = r.online
            lines.append(
                f"| {rep.cell.name} (seed {r.seed}) | {_f(o.get('swap_median_ms'), 4)} / {_f(o.get('swap_max_ms'), 4)} "
                f"| {_f(o.get('install_slice_max_ms'), 3)} | {_f(o.get('train_wall_median_s'), 3)} / "
                f"{_f(o.get('train_wall_max_s'), 3)} | {_f(o.get('t_col'), 3)} | {o.get('models_trained')} / "
                f"{o.get('models_accepted')} / {o.get('models_rejected')} / {o.get('models_dropped')} | "
                f"{o.get('missed_deadlines')} of {o.get('ticks')} ({o.get('ticks_late_from_install')}) "
                f"| {_f(o.get('speed_factor'), 3)}x |")
    return "\n".join(lines)


def _median_recovery(recs: list[tuple[dict[str, Any], ...]]) -> str:
    """Median over the seeds of each step's time to recover ('never' counted as infinite)."""
    if not recs or not recs[0]:
        return "-"
    out = []
    for i in range(len(recs[0])):
        times = [r[i].get("time_to_recover_s") for r in recs if len(r) > i]
        med = float(np.median([np.inf if x is None else x for x in times]))
        out.append({"time_to_recover_s": med if np.isfinite(med) else None})
    return recovery_text(out)


def _f(value: Any, digits: int) -> str:
    return "-" if value is None else f"{float(value):.{digits}g}"


def add_online_arguments(p: Any) -> None:
    p.add_argument("--quick", action="store_true", help="one 4 s paper cell, one seed: a smoke test (< 1 min)")
    p.add_argument("--seeds", type=int, default=3, help="seeded flights per controller and cell (default 3)")
    p.add_argument("--out", default="bench_out", help="output directory (default ./bench_out)")
    add_latency_arguments(p)
    add_plant_arguments(p)


def run_online(args: Any, version: str) -> int:
    from rich.console import Console

    from cfknode.app.errors import UsageError

    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    check_latency_arguments(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="cfknode-bench-online-", dir=out))
    console = Console()
    cells = (QUICK,) if args.quick else (LAB, PAPER, LAB_SMALL)
    seeds = (0,) if args.quick else tuple(range(args.seeds))
    command = "cfknode bench online" + (" --quick" if args.quick else f" --seeds {args.seeds}") + latency_flags(args) + plant_flags(args)
    from functools import partial

    from cfknode.app.bench.executor import ExecutorSettings, run_ordered

    # A cell's flights and its trainer: two CPUs each on Ray; one cell at a time by default.
    executor = ExecutorSettings.from_args(args, cpus_per_task=2, default_jobs=1)
    note = (lambda text: console.print(f"[dim]{text}[/]")) if executor.runs_here else None
    extra = {**latency_overrides(args), **plant_overrides(args)}
    reports = run_ordered(partial(run_cell, seeds=seeds, out=logs, progress=note, extra=extra), cells, executor, "bench online", describe=lambda i, rep: f"{rep.cell.name}: {rep.wall_s:.0f} s",
                          console=console)
    md = markdown(reports, command, version, latency_note(args))
    stem = "online" + ("_quick" if args.quick else "")
    (out / f"{stem}.md").write_text(md + "\n")
    (out / f"{stem}.json").write_text(json.dumps(
        {"command": command, "version": version, "cells": [asdict(r) for r in reports]}, indent=1, default=str))
    console.print(md)
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}; flight logs in {logs}")
    return 0


__all__ = ["ACCEPTANCE", "COMPARED", "CellReport", "CellSpec", "LAB", "LAB_SMALL", "PAPER", "QUICK", "Run", "markdown", "run_cell",
           "run_online"]
