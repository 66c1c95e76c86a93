"""``cfknode bench online``: the online-learning acceptance protocol, flown by the whole stack.

Two cells with the paper's mass changes (``cfknode.app.bench.mass_steps``): the lab circle (0.5 m,
0.4 m/s, 30 s) and one paper cell (r = 2 m, 0.8 m/s, 8 s). Per cell: the offline KNODE-MPC is
trained on a flight that saw only the first change, then nominal MPC, offline KNODE-MPC and
KNODE-MPC-Online fly the same seeded scenario, once per seed. A third cell is the lab
protocol of docs/design.md#targets (the same circle, +4.1 % mass at 5 s), against nominal MPC
and the geometric controller. Online learning
runs with honest latency (its trainer's real wall time), so its result varies from run to
run; the table gives the median and the range over the seeds, and the online/baseline
ratios of each seed. Flights run one at a time: a second flight on the other core would
slow the trainer and so change what is measured.
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.bench.mass_steps import PAPER_STEPS

COMPARED = ("nominal", "offline", "online")


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
            "sim.seed": seed,
            "log.dir": log_dir,
            **dict(self.overrides),
        }


LAB = CellSpec("lab circle", 0.5, 0.4, 30.0)
# The paper's cell as the hierarchical bench flies it: full speed from the start, 1.5 m up.
PAPER = CellSpec("paper r=2 v=0.8", 2.0, 0.8, 8.0, (("trajectory.ramp_duration", 0.0), ("trajectory.height", 1.5)))
QUICK = CellSpec("paper r=2 v=0.8, 4 s", 2.0, 0.8, 4.0, PAPER.overrides, ((1.0, 0.5), (2.5, 1.33)))
LAB_SMALL = CellSpec("lab circle +4.1 %", 0.5, 0.4, 30.0, steps=((5.0, 1.041),),
                     controllers=("nominal", "geometric", "online"))


@dataclass(frozen=True)
class Run:
    controller: str
    seed: int
    mse: float
    mse_z: float
    outcome: str
    online: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CellReport:
    cell: CellSpec
    runs: tuple[Run, ...]
    wall_s: float

    @property
    def baselines(self) -> tuple[str, ...]:
        return tuple(c for c in self.cell.controllers if c != "online")

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


def run_cell(cell: CellSpec, seeds: tuple[int, ...], out: Path, progress: Any = None) -> CellReport:
    from cfknode.app.config import load_config
    from cfknode.app.bench.mass_steps import CONTROLLER_OVERRIDES, mass_schedule, train_offline_model
    from cfknode.app.mission import run_flight

    start = time.perf_counter()
    name = cell.name.replace(" ", "-").replace("=", "").replace(",", "").replace("%", "pc")
    base = cell.config(str(out), seeds[0])
    at, factors = zip(*cell.steps)
    schedule = mass_schedule(base, at, factors)
    model = train_offline_model(base, schedule, out, name) if "offline" in cell.controllers else None
    runs = []
    for seed in seeds:
        for controller in cell.controllers:
            overrides = {**cell.config(str(out), seed), "sim.mass_changes": list(schedule.both),
                         **CONTROLLER_OVERRIDES[controller](model)}
            res = run_flight(load_config(overrides=overrides), name_hint=f"{name}-{controller}-s{seed}")
            online = {}
            if controller == "online":
                online = {k: v for k, v in res.summary.extra.items()
                          if k.startswith(("models_", "swap_", "install_", "train_wall", "latency_", "rounds_slower", "ticks_late"))}
                online.update(speed_factor=res.summary.speed_factor, missed_deadlines=res.summary.missed_deadlines,
                              ticks=res.summary.ticks, t_col=res.summary.extra.get("online_t_col_s"))
            runs.append(Run(controller, seed, res.summary.mse, res.summary.mse_z, res.outcome.message, online))
            if progress is not None:
                progress(f"{cell.name} seed {seed} {controller}: MSE {res.summary.mse:.3g}")
    return CellReport(cell, tuple(runs), time.perf_counter() - start)


NAMES = {"nominal": "nominal MPC", "offline": "offline KNODE-MPC", "geometric": "geometric", "online": "KNODE-MPC-Online"}


def markdown(reports: list[CellReport], command: str, version: str) -> str:
    lines = [
        "## Online learning (acceptance protocol)",
        "",
        f"`{command}`, cfknode {version}. MSE in m^2 on the pattern (mean over the axes): median over the "
        "seeds, [min, max] in brackets; ratios are online over the baseline, seed by seed.",
    ]
    for rep in reports:
        steps = ", ".join(f"{f:g}x at {t:g} s" for t, f in rep.cell.steps)
        lines += ["", f"**{rep.cell.name}** (r = {rep.cell.radius:g} m, {rep.cell.speed:g} m/s, {rep.cell.duration:g} s; "
                  f"mass {steps} into the pattern; {len(set(r.seed for r in rep.runs))} seeds)", "",
                  "| " + " | ".join(NAMES[c] for c in rep.cell.controllers) + " | "
                  + " | ".join(f"online / {b}" for b in rep.baselines) + " | met |",
                  "|" + "---|" * (len(rep.cell.controllers) + len(rep.baselines) + 1)]
        cells = []
        for c in rep.cell.controllers:
            m = rep.mse(c)
            cells.append(f"{np.median(m):.4g} [{m.min():.3g}, {m.max():.3g}]" if m.size > 1 else f"{m[0]:.4g}")
        ratios = [rep.ratios(b) for b in rep.baselines]
        rtext = [f"{np.median(r):.2f} (wins {int((r < 1).sum())}/{r.size})" for r in ratios]
        lines.append("| " + " | ".join(cells + rtext) + f" | {'yes' if rep.met else 'no'} |")
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


def _f(value: Any, digits: int) -> str:
    return "-" if value is None else f"{float(value):.{digits}g}"


def add_online_arguments(p: Any) -> None:
    p.add_argument("--quick", action="store_true", help="one 4 s paper cell, one seed: a smoke test (< 1 min)")
    p.add_argument("--seeds", type=int, default=3, help="seeded flights per controller and cell (default 3)")
    p.add_argument("--out", default="bench_out", help="output directory (default ./bench_out)")


def run_online(args: Any, version: str) -> int:
    from rich.console import Console

    from cfknode.app.cli import UsageError

    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="cfknode-bench-online-", dir=out))
    console = Console()
    cells = (QUICK,) if args.quick else (LAB, PAPER, LAB_SMALL)
    seeds = (0,) if args.quick else tuple(range(args.seeds))
    command = "cfknode bench online" + (" --quick" if args.quick else f" --seeds {args.seeds}")
    from functools import partial

    from cfknode.app.bench.executor import ExecutorSettings, run_ordered

    # A cell's flights and its trainer: two CPUs each on Ray; one cell at a time by default.
    executor = ExecutorSettings.from_args(args, cpus_per_task=2, default_jobs=1)
    note = (lambda text: console.print(f"[dim]{text}[/]")) if executor.runs_here else None
    reports = run_ordered(partial(run_cell, seeds=seeds, out=logs, progress=note), cells, executor, "bench online",
                          describe=lambda i, rep: f"{rep.cell.name}: {rep.wall_s:.0f} s", console=console)
    md = markdown(reports, command, version)
    stem = "online" + ("_quick" if args.quick else "")
    (out / f"{stem}.md").write_text(md + "\n")
    (out / f"{stem}.json").write_text(json.dumps(
        {"command": command, "version": version, "cells": [asdict(r) for r in reports]}, indent=1, default=str))
    console.print(md)
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}; flight logs in {logs}")
    return 0


__all__ = ["COMPARED", "CellReport", "CellSpec", "LAB", "LAB_SMALL", "PAPER", "QUICK", "Run", "markdown", "run_cell",
           "run_online"]
