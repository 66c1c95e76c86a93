"""``cfknode bench paper --mode hierarchical``: the paper's protocol flown by the hardware path.

Each cell flies the whole stack exactly as ``cfknode fly`` does (400 Hz loop, translational
MPC, Mellinger layer, the real cflib path into the simulated Crazyflie's firmware, mocap
noise), on the paper's circles and mass schedule (0.5x at 2 s, 1.33x at 5 s into the
pattern), with the four controllers of Table 1: nominal MPC, offline KNODE-MPC (trained on a
flight that saw only the first mass change, as the paper does), the geometric controller,
and KNODE-MPC-Online; beside them MPC and KNODE-MPC-Online with the fast adaptation layer
(dob), and the oracle: the same MPC told the true mass at every tick (and 20 ms late: a bound for
any estimator that must first see the change in the mocap frames). Online learning flies
with a reproducible latency by default (``--latency``, ``cfknode.app.bench.rows``). Only the safety limits are widened to the bench's circles (a 4 m
circle is outside a lab fence); every run is seeded.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


CELLS = tuple((r, v) for r in (2.0, 3.0, 4.0) for v in (0.8, 1.0, 1.2))
# The pattern's length in seconds: the paper's 8 s, and ``--quick``'s one cell of 4 s.
DURATION_S, QUICK_DURATION_S = 8.0, 4.0
CONTROLLERS = ("geometric", "nominal", "offline", "online", "dob", "online_dob", "oracle", "oracle_late")
# Table 1 of the paper, as printed (radius-major), for the bench's comparison column.
PAPER_ONLINE = dict(zip(CELLS, (0.0660, 0.1113, 0.1678, 0.0657, 0.1043, 0.1554, 0.0709, 0.1092, 0.1571)))
PAPER_MPC = dict(zip(CELLS, (0.0904, 0.1280, 0.1705, 0.0949, 0.1371, 0.1861, 0.0967, 0.1412, 0.1937)))


@dataclass(frozen=True)
class CellResult:
    radius: float
    speed: float
    mse: dict[str, float]
    mse_z: dict[str, float]
    outcome: dict[str, str]
    online: dict[str, Any]
    wall_s: float
    recovery: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # per controller, per mass step


def cell_overrides(radius: float, speed: float, duration: float, log_dir: str, seed: int) -> dict[str, Any]:
    from cfknode.app.bench.rows import BENCH_AERO

    span = radius + 1.5
    return {
        "trajectory.kind": "circle",
        "trajectory.radius": radius,
        "trajectory.speed": speed,
        "trajectory.duration": duration,
        "trajectory.height": 1.5,
        "trajectory.ramp_duration": 0.0,  # the paper's reference starts at full speed
        "safety.fence_min": [-span, -span, -0.2],
        "safety.fence_max": [span, span, 4.0],
        "safety.max_tracking_error": 3.0,  # a bench, not people: let every controller show its error
        "sim.aero": BENCH_AERO,
        "sim.seed": seed,
        "log.dir": log_dir,
    }


def run_cell(radius: float, speed: float, duration: float, seed: int, out_dir: str,
             extra: dict[str, Any] | None = None) -> CellResult:
    """Every controller on one cell (one process; flights in sequence); ``extra``: overrides for every flight
    (the online latency, the plant)."""
    import time

    from cfknode.app.config import load_config
    from cfknode.app.bench.mass_steps import CONTROLLER_OVERRIDES, mass_schedule, train_offline_model
    from cfknode.app.mission import run_flight

    start = time.perf_counter()
    base = {**cell_overrides(radius, speed, duration, out_dir, seed), **(extra or {})}
    schedule = mass_schedule(base, (2.0 * duration / 8.0, 5.0 * duration / 8.0))
    name = f"r{radius:g}-v{speed:g}"
    model = train_offline_model(base, schedule, Path(out_dir), name)
    mse, mse_z, outcome, online, recovery = {}, {}, {}, {}, {}
    for kind in CONTROLLERS:
        overrides = {**base, "sim.mass_changes": list(schedule.both),
                     **CONTROLLER_OVERRIDES[kind](model)}
        res = run_flight(load_config(overrides=overrides), name_hint=f"{name}-{kind}")
        mse[kind], mse_z[kind], outcome[kind] = res.summary.mse, res.summary.mse_z, res.outcome.message
        recovery[kind] = [dict(r) for r in res.summary.recovery]
        if kind == "online":
            online = {k: v for k, v in res.summary.extra.items() if k.startswith(("models_", "swap_", "train_wall"))}
            online["speed_factor"] = res.summary.speed_factor
    return CellResult(radius, speed, mse, mse_z, outcome, online, time.perf_counter() - start, recovery)


def run_cell_job(job: tuple[float, float, float, int, str, dict[str, Any]]) -> CellResult:
    """``run_cell`` on one argument, as the bench executor calls its tasks."""
    return run_cell(*job)


def markdown(results: list[CellResult], command: str, version: str, latency_note: str = "") -> str:
    from cfknode.app.bench.rows import LABELS, peak_text, recovery_legend, recovery_text, summary_lines

    lines = [
        "## Hierarchical mode (the hardware path)",
        "",
        f"`{command}`, cfknode {version}. MSE in m^2 on the pattern (mean over the axes), mass 0.5x at 2 s "
        "and 1.33x at 5 s into an 8 s circle, 29 g Crazyflie 2.1 (thrust/weight 1.5 at the 60000 clamp). "
        + latency_note,
        "",
        "| r [m] | v [m/s] | " + " | ".join(LABELS[k] for k in CONTROLLERS) + " | lowest | paper Online | paper MPC |",
        "|---|---|" + "---|" * (len(CONTROLLERS) + 3),
    ]
    for r in results:
        best = min(r.mse, key=r.mse.get)
        cells = [f"**{r.mse[k]:.4f}**" if k == best else f"{r.mse[k]:.4f}" if k in r.mse else "-" for k in CONTROLLERS]
        lines.append(f"| {r.radius:g} | {r.speed:g} | " + " | ".join(cells) +
                     f" | {best} | {PAPER_ONLINE[(r.radius, r.speed)]:.4f} | {PAPER_MPC[(r.radius, r.speed)]:.4f} |")
    wins = sum(min(r.mse, key=r.mse.get) == "online" for r in results)
    lines += ["", f"KNODE-MPC-Online has the lowest MSE in {wins} of {len(results)} cells.",
              *summary_lines([r.mse for r in results], CONTROLLERS), "",
              "Time to recover [s] (0.5x step / 1.33x step), peak error [m] in brackets. " + recovery_legend(), "",
              "| r [m] | v [m/s] | " + " | ".join(LABELS[k] for k in CONTROLLERS) + " |",
              "|---|---|" + "---|" * len(CONTROLLERS)]
    for r in results:
        rec = [f"{recovery_text(r.recovery.get(k, []))} ({peak_text(r.recovery.get(k, []))})" for k in CONTROLLERS]
        lines.append(f"| {r.radius:g} | {r.speed:g} | " + " | ".join(rec) + " |")
    return "\n".join(lines)


def run_hierarchical(args: argparse.Namespace, out: Path, version: str) -> int:
    from rich.console import Console

    from cfknode.app.bench.executor import ExecutorSettings, run_ordered
    from cfknode.app.bench.rows import (check_latency_arguments, latency_flags, latency_note, latency_overrides,
                                        plant_flags, plant_overrides)

    check_latency_arguments(args)
    executor = ExecutorSettings.from_args(args)
    cells = CELLS[:1] if args.quick else parse_cells(getattr(args, "cells", None))
    duration = QUICK_DURATION_S if args.quick else DURATION_S
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="cfknode-bench-", dir=out))
    command = (f"cfknode bench paper --mode hierarchical{' --quick' if args.quick else ''} {executor.command_flags()} "
               f"--seed {args.seed}{latency_flags(args)}{plant_flags(args)}" + (f" --cells {args.cells}" if getattr(args, "cells", None) else ""))
    console = Console()
    jobs = [(r, v, duration, args.seed, str(logs), {**latency_overrides(args), **plant_overrides(args)})
            for r, v in cells]
    results: list[CellResult] = run_ordered(
        run_cell_job, jobs, executor, "bench hierarchical", console=console,
        describe=lambda i, res: f"r={res.radius:g} v={res.speed:g}: online {res.mse['online']:.4f}")
    results.sort(key=lambda r: (r.radius, r.speed))
    md = markdown(results, command, version, latency_note(args))
    stem = "paper_hierarchical" + ("_quick" if args.quick else "")
    (out / f"{stem}.md").write_text(md + "\n")
    (out / f"{stem}.json").write_text(json.dumps({"command": command, "version": version,
                                                  "cells": [asdict(r) for r in results]}, indent=1))
    console.print(md)
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}; flight logs in {logs}")
    return 0


def parse_cells(text: str | None) -> tuple[tuple[float, float], ...]:
    """``--cells 2:0.8,3:1.0`` -> those of the paper's cells (None: all nine); anything else is a usage error."""
    from cfknode.app.errors import UsageError

    if not text:
        return CELLS
    chosen = []
    for item in text.split(","):
        try:
            r, v = (float(x) for x in item.split(":"))
        except ValueError:
            raise UsageError(f"--cells expects r:v pairs like 2:0.8,3:1.0, got {item!r}") from None
        if (r, v) not in CELLS:
            raise UsageError(f"--cells {item}: not one of the paper's cells (r in 2, 3, 4 m; v in 0.8, 1.0, 1.2 m/s)")
        chosen.append((r, v))
    return tuple(chosen)
