"""``cfknode bench robustness``: every controller on plants it was not tuned on.

The controllers keep believing ``vehicle:``; each cell changes what the simulator flies
(``sim.`` plant keys: motor lag, thrust map, thrust-to-weight at the clamp, attitude and yaw
response, battery sag; mocap latency and noise; drag, wind, gusts; the paper's mass steps).
Every cell is flown on two patterns: the lab circle (0.5 m at 0.4 m/s, shortened to 8 s of
pattern instead of 30 s to keep the bench affordable) and the paper's r = 2 m, v = 0.8 m/s, 8 s circle.
Both fly at ``PATTERN_HEIGHT`` (1.5 m), every cell and controller alike: the simulator has no
ground effect or other dependence on altitude, so the height only decides whether a fall that
can be stopped is stopped before the ground. The hardest cell (T/W 1.05 at the clamp after the
1.33x step, 150 ms thrust lag) must lose 0.85 m even with the clamp commanded at the instant
of the step (``thrust_sag.step_sag``); 1.5 m leaves that and ``SAG_MARGIN`` for the reaction.

Per run: MSE on the pattern window, whether the vehicle hit the ground (z < 0.05 m during
the pattern), diverged (the geofence fired), or the supervisor ended the flight otherwise
(any outcome but "flight complete"), and, where the mass steps, the time to recover.
Flights are seeded and independent, so they run in a process pool (``--jobs``).

The controllers are the entries of ``CONTROLLERS`` (label -> config overrides): a new
variant (an oracle, say) is one more entry.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from cfknode.app.bench.rows import BENCH_AERO, add_plant_arguments, plant_flags, plant_overrides

import numpy as np

from cfknode.app.bench.mass_steps import PAPER_STEPS

# label -> overrides. Add a row here (e.g. "oracle") and every cell flies it.
CONTROLLERS: dict[str, dict[str, Any]] = {
    "geometric": {"controller.kind": "geometric", "controller.adaptation": "none"},
    "mpc": {"controller.kind": "mpc", "controller.adaptation": "none"},
    "mpc+dob": {"controller.kind": "mpc", "controller.adaptation": "dob"},
    "online": {"online.enabled": True, "controller.adaptation": "none"},
    "online+dob": {"online.enabled": True, "controller.adaptation": "dob"},
    "oracle": {"controller.kind": "mpc", "controller.adaptation": "oracle"},  # the true mass each tick: a reference
}
REFERENCES = ("oracle",)  # never counted as the lowest
ADAPTIVE = ("mpc+dob", "online", "online+dob")  # must never hit the ground, diverge or trip the supervisor

GROUND_Z = 0.05  # m: below this during the pattern is a ground hit
NEAR_TIE = 0.02  # the report also counts cells within this of the lowest MSE: the reproducibility bound
# Every pattern flies this high: room for the worst cell's unavoidable sag plus SAG_MARGIN
# (checked by tests), under the default 2.0 m geofence and a lab ceiling.
PATTERN_HEIGHT = 1.5  # m
SAG_MARGIN = 0.5  # m over the instant-reaction sag: ~35 ms of detection and command path at the worst cell
CEILING = 3.0  # m: the bench's fence top, a lab ceiling
CLIMB_S_PER_M = 2.0  # s of take-off (and landing) per metre of height: the climb rate the 1 m lab circle had
HEAVIEST = max(f for _, f in PAPER_STEPS)
TW_LAG = 0.150  # s, the thrust lag of the hardest thrust-to-weight cell
SAG_PER_S = 0.01  # an accelerated sag (10 % per 10 s) so a short flight shows what a whole pack does
DRAG = [0.01, 0.01, 0.01]  # N/(m/s): 0.34 m/s^2 per m/s on 29 g


@dataclass(frozen=True)
class Pattern:
    name: str
    radius: float
    speed: float
    duration: float
    height: float
    ramp: float


LAB = Pattern("lab", 0.5, 0.4, 8.0, PATTERN_HEIGHT, 2.0)
PAPER = Pattern("paper", 2.0, 0.8, 8.0, PATTERN_HEIGHT, 0.0)


@dataclass(frozen=True)
class Cell:
    """One plant: ``overrides`` (dotted keys), paper mass steps or not, gusts at pattern times,
    ``thrust_to_weight``: thrust-to-weight at the clamp after the heaviest step (sets the thrust map)."""

    name: str
    overrides: tuple[tuple[str, Any], ...] = ()
    mass_steps: bool = False
    gusts: tuple[tuple[float, float, tuple[float, float, float]], ...] = ()  # (s into the pattern, duration, wind)
    thrust_to_weight: float = 0.0  # 0: leave the thrust map alone


def _cells() -> tuple[Cell, ...]:
    cells = [Cell(f"motor lag {round(tau * 1000)} ms", (("sim.motor_time_constant", tau),)) for tau in (0.015, 0.04, 0.08, 0.15)]
    cells += [
        Cell("T/W 1.10 after 1.33x", mass_steps=True, thrust_to_weight=1.10),
        Cell("T/W 1.05 after 1.33x", mass_steps=True, thrust_to_weight=1.05),
        Cell("T/W 1.05 + 150 ms lag", (("sim.motor_time_constant", TW_LAG),), mass_steps=True, thrust_to_weight=1.05),
        Cell("attitude 0.8", (("sim.attitude_gain", 0.8),)),
        Cell("attitude 1.2", (("sim.attitude_gain", 1.2),)),
        Cell("yaw 1.8", (("sim.yaw_gain", 1.8),)),
        Cell("thrust map -15 %", (("sim.thrust_map_scale", 0.85),)),
        Cell("thrust map +15 %", (("sim.thrust_map_scale", 1.15),)),
    ]
    cells += [Cell(f"mocap latency {ms} ms", (("sim.mocap_latency", ms / 1000.0),)) for ms in (0, 10, 25)]
    cells += [Cell(f"mocap noise {mm:g} mm", (("sim.mocap_position_noise", mm / 1000.0),)) for mm in (0.3, 2.0)]
    cells += [
        Cell("drag + wind", (("sim.drag", DRAG), ("sim.wind", [1.0, 0.5, 0.0]))),
        Cell("gusts", (("sim.drag", DRAG),), gusts=((2.0, 0.5, (2.0, 0.0, 0.0)), (5.0, 0.3, (0.0, -2.0, 0.5)))),
        Cell("mass 0.5x then 1.33x", mass_steps=True),
        Cell("battery sag 1 %/s", (("sim.battery_sag_per_s", SAG_PER_S),)),
    ]
    return tuple(cells)


CELLS = _cells()
QUICK_CELLS = ("T/W 1.05 + 150 ms lag", "mocap latency 25 ms")


@dataclass(frozen=True)
class RunResult:
    cell: str
    pattern: str
    controller: str
    mse: float
    ground: bool
    diverged: bool
    tripped: bool
    outcome: str
    recover_s: float | None  # longest recovery over the mass steps; inf = never; None = no steps
    wall_s: float
    sag_m: float = math.nan  # largest altitude below the reference during the pattern (m)

    @property
    def failed(self) -> bool:
        return self.ground or self.diverged or self.tripped


def flight_overrides(cell: Cell, pattern: Pattern, controller: str, log_dir: str, seed: int) -> dict[str, Any]:
    """Everything one run sets, gusts and mass steps at times relative to the pattern's start."""
    from cfknode.app.config import load_config
    from cfknode.flight.trajectory import make_trajectory
    from cfknode.sim_backend.plant import thrust_scale_for_thrust_to_weight

    span = pattern.radius + 1.5
    base: dict[str, Any] = {
        "trajectory.kind": "circle",
        "trajectory.radius": pattern.radius,
        "trajectory.speed": pattern.speed,
        "trajectory.duration": pattern.duration,
        "trajectory.height": pattern.height,
        "trajectory.ramp_duration": pattern.ramp,
        # Shorter settle than a flight's (the pattern is what is measured); take-off and landing
        # at the lab circle's climb rate, whatever the height.
        "trajectory.takeoff_duration": CLIMB_S_PER_M * pattern.height,
        "trajectory.settle_duration": 0.5,
        "trajectory.land_duration": CLIMB_S_PER_M * pattern.height,
        # A bench, not people: a wide fence and tracking limit let every controller show its error.
        "safety.fence_min": [-span, -span, -0.2],
        "safety.fence_max": [span, span, max(CEILING, pattern.height + 0.5)],
        "safety.max_tracking_error": 3.0,
        "sim.aero": BENCH_AERO,
        "sim.seed": seed,
        "log.dir": log_dir,
        "dashboard.enabled": False,
        **dict(cell.overrides),
    }
    cfg = load_config(overrides=base)
    t0 = make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float)).segments["pattern"][0]
    scale = pattern.duration / 8.0 if pattern.duration < 8.0 else 1.0  # a shortened pattern scales the times
    if cell.mass_steps:
        base["sim.mass_changes"] = [{"t": t0 + t * scale, "factor": f} for t, f in PAPER_STEPS]
    if cell.gusts:
        base["faults.gusts"] = [{"t": t0 + t * scale, "duration": d, "wind": list(w)} for t, d, w in cell.gusts]
    if cell.thrust_to_weight > 0.0:
        base["sim.thrust_map_scale"] = thrust_scale_for_thrust_to_weight(cell.thrust_to_weight, cfg.vehicle, HEAVIEST)
    return {**base, **CONTROLLERS[controller]}


def unavoidable_sag(cell: Cell, reaction_s: float = 0.0) -> float:
    """Altitude [m] the plant of ``cell`` must lose at its mass steps even with the thrust clamp
    commanded ``reaction_s`` after each step (0 without steps): the thrust hovers the mass before
    the step and follows through the plant's motor lag (``thrust_sag.step_sag``)."""
    from cfknode.app.bench.thrust_sag import step_sag
    from cfknode.app.config import load_config
    from cfknode.sim_backend.plant import plant_motor_time_constant, thrust_to_weight

    if not cell.mass_steps:
        return 0.0
    cfg = load_config(overrides=flight_overrides(cell, LAB, "mpc", tempfile.gettempdir(), 0))
    tau = plant_motor_time_constant(cfg.vehicle, cfg.sim)
    worst, before = 0.0, 1.0
    for change in cfg.sim.mass_changes:
        tw = thrust_to_weight(cfg.vehicle, cfg.sim.thrust_map_scale, change.factor)
        if change.factor > before and tw <= 1.0:
            return math.inf  # it cannot stop falling at all
        worst = max(worst, step_sag(tw, before, change.factor, tau, reaction_s))
        before = change.factor
    return worst


def recovery_time(t: np.ndarray, err: np.ndarray, t_step: float, t_end: float, hold: float = 0.5) -> float:
    """Seconds after ``t_step`` until the position error is back under its pre-step level and
    stays there for ``hold`` seconds (before ``t_end``); inf if it never does.

    The level is 1.5x the error's 95th percentile over the second before the step, and at
    least 2 cm: a controller that tracks to 1 mm is not asked to return to 1 mm.
    """
    before = err[(t >= t_step - 1.0) & (t < t_step)]
    level = max(1.5 * float(np.percentile(before, 95)) if before.size else 0.0, 0.02)
    idx = np.flatnonzero((t >= t_step) & (t < t_end))
    if idx.size == 0:
        return math.inf
    bad = err[idx] > level
    last_bad_t = t_step
    for i, is_bad in zip(idx, bad):
        if is_bad:
            last_bad_t = t[i]
        elif t[i] - last_bad_t >= hold:
            return float(last_bad_t - t_step)
    return math.inf


def run_one(cell: Cell, pattern: Pattern, controller: str, seed: int, log_dir: str) -> RunResult:
    """One flight and its verdicts."""
    from cfknode.app.config import load_config
    from cfknode.app.mission import run_flight

    start = time.perf_counter()
    overrides = flight_overrides(cell, pattern, controller, log_dir, seed)
    cfg = load_config(overrides=overrides)
    slug = f"{pattern.name}-{cell.name}-{controller}".replace(" ", "_").replace("/", "").replace("%", "pc").replace("+", "p")
    res = run_flight(cfg, name_hint=slug)
    rec, summary, outcome = res.record, res.summary, res.outcome
    t0, t1 = summary.window
    in_pattern = (rec.t >= t0) & (rec.t <= t1)
    ground = bool(np.any(rec.p[in_pattern, 2] < GROUND_Z)) if in_pattern.any() else True
    diverged = "fence" in outcome.cause
    tripped = not outcome.message.startswith("flight complete")
    recover = None
    if cell.mass_steps:
        err = np.linalg.norm(rec.p - rec.p_ref, axis=1)
        times = [c["t"] for c in overrides["sim.mass_changes"]] + [t1]
        recover = max(recovery_time(rec.t, err, a, b) for a, b in zip(times[:-1], times[1:]))
    sag = float(np.max(rec.p_ref[in_pattern, 2] - rec.p[in_pattern, 2])) if in_pattern.any() else math.nan
    return RunResult(cell.name, pattern.name, controller, float(summary.mse), ground, diverged, tripped,
                     outcome.message, recover, time.perf_counter() - start, sag)


# --- report ------------------------------------------------------------------------------------


def _flags(r: RunResult) -> str:
    return "".join(f for f, on in (("G", r.ground), ("D", r.diverged), ("S", r.tripped)) if on)


def _fmt_recover(v: float | None) -> str:
    if v is None:
        return ""
    return "never" if math.isinf(v) else f"{v:.2f} s"


def wins(results: list[RunResult], controllers: tuple[str, ...], within: float = 0.0) -> dict[str, int]:
    """Cells (cell x pattern) where each controller has the lowest MSE among the runs that did not fail; an
    exact tie counts for each (beside the fast layer the learner often keeps no model, and then flies as the
    layer alone, to the last digit).

    ``within`` > 0 counts every controller within that fraction of the lowest instead (a near tie: on a
    plant with nothing to adapt to, the adaptive variants can at best match the exact model)."""
    out = {c: 0 for c in controllers}
    for key in sorted({(r.cell, r.pattern) for r in results}):
        ok = [r for r in results if (r.cell, r.pattern) == key and not r.failed and math.isfinite(r.mse)
              and r.controller not in REFERENCES]
        if not ok:
            continue
        best = min(ok, key=lambda r: r.mse)
        for r in ok:
            out[r.controller] += int(r.mse <= best.mse * (1.0 + within))
    return out


def markdown(results: list[RunResult], controllers: tuple[str, ...], command: str, version: str, mode: str,
             patterns: tuple[Pattern, ...]) -> str:
    pats = ", ".join(f"{p.name}: r = {p.radius:g} m at {p.speed:g} m/s at {p.height:g} m, {p.duration:g} s of pattern"
                     for p in patterns)
    lines = [
        "## Robustness: plants the controllers were not tuned on",
        "",
        f"`{command}`, cfknode {version}, mode {mode}. MSE in m^2 on the pattern (mean over the axes); "
        f"patterns {pats} (every cell and controller at the same height: no ground effect in the simulator). "
        f"Flags: G hit the ground (z < {GROUND_Z} m during the pattern), D diverged (geofence), "
        "S the supervisor ended the flight (not \"flight complete\"). Recovery: the longest time after a mass "
        "step until the error is back under its pre-step level for 0.5 s. Lowest MSE of each row in bold "
        "(an exact tie in bold for each).",
        "",
        "| cell | pattern | " + " | ".join(controllers) + " |",
        "|---|---|" + "---|" * len(controllers),
    ]
    by = {(r.cell, r.pattern, r.controller): r for r in results}
    keys = []
    for r in results:
        if (r.cell, r.pattern) not in keys:
            keys.append((r.cell, r.pattern))
    for cell, pat in keys:
        runs = [by.get((cell, pat, c)) for c in controllers]
        ok = [r for r in runs if r is not None and not r.failed]
        best = min(r.mse for r in ok) if ok else None
        cols = []
        for c, r in zip(controllers, runs):
            if r is None:
                cols.append("")
                continue
            text = f"{r.mse:.4g}"
            text = f"**{text}**" if r.mse == best and not r.failed else text
            flags = _flags(r)
            rec = _fmt_recover(r.recover_s)
            cols.append(text + (f" {flags}" if flags else "") + (f" ({rec})" if rec else ""))
        lines.append(f"| {cell} | {pat} | " + " | ".join(cols) + " |")
    lines += ["", "**Worst case per controller** (highest MSE; failures listed)", "",
              f"| controller | worst MSE | cell | failures | cells won | within {NEAR_TIE:.0%} of the lowest |",
              "|---|---|---|---|---|---|"]
    won, near = wins(results, controllers), wins(results, controllers, NEAR_TIE)
    for c in controllers:
        runs = [r for r in results if r.controller == c]
        if not runs:
            continue
        worst = max(runs, key=lambda r: r.mse if math.isfinite(r.mse) else math.inf)
        fails = [f"{r.cell} / {r.pattern} {_flags(r)}: {r.outcome}" for r in runs if r.failed]
        lines.append(f"| {c} | {worst.mse:.4g} | {worst.cell} / {worst.pattern} | "
                     f"{'; '.join(fails) if fails else 'none'} | {won[c]} of {len(keys)} | {near[c]} of {len(keys)} |")
    bad = [r for r in results if r.controller in ADAPTIVE and r.failed]
    lines += ["", ("Adaptive variants: no ground hit, divergence or supervisor trip in any cell." if not bad else
                   "Adaptive variants FAILED in: " + "; ".join(f"{r.controller} on {r.cell} / {r.pattern} ({_flags(r)})"
                                                               for r in bad))]
    return "\n".join(lines)


# --- command -----------------------------------------------------------------------------------


def add_robustness_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true",
                   help=f"{len(QUICK_CELLS)} cells on a 4 s lab circle: a smoke test (< 2 min)")
    from cfknode.app.bench.executor import add_executor_arguments

    add_executor_arguments(p, 2, "")
    p.add_argument("--out", default="bench_out", help="output directory (default ./bench_out)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cells", default="", help="comma-separated cell names to fly (default: all, or the quick set)")
    p.add_argument("--controllers", default="", help=f"comma-separated subset of {', '.join(CONTROLLERS)}")
    p.add_argument("--patterns", default="", help="comma-separated subset of lab, paper")
    p.add_argument("--duration", type=float, default=0.0, help="s of pattern, overriding both patterns' (0: theirs)")
    add_plant_arguments(p)


def _select(text: str, known: tuple[str, ...], what: str) -> tuple[str, ...]:
    from cfknode.app.errors import UsageError

    if not text:
        return known
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in known]
    if unknown:
        raise UsageError(f"unknown {what} {', '.join(unknown)}; known: {', '.join(known)}")
    return names


def run_one_job(job: tuple[Any, ...]) -> RunResult:
    """``run_one`` on one argument, as the bench executor calls its tasks."""
    return run_one(*job)


def run_robustness(args: argparse.Namespace, version: str) -> int:
    from dataclasses import replace

    from rich.console import Console

    from cfknode.app.errors import UsageError

    from cfknode.app.bench.executor import ExecutorSettings, run_ordered

    executor = ExecutorSettings.from_args(args)  # bad --jobs, --address or a missing Ray: before anything runs
    if args.duration < 0:
        raise UsageError(f"--duration must be >= 0, got {args.duration}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is not a directory")
    all_names = tuple(c.name for c in CELLS)
    names = _select(args.cells, all_names, "cell(s)") if args.cells else (QUICK_CELLS if args.quick else all_names)
    # The plant goes first among a cell's overrides, so a cell's own settings still apply on top of it.
    cells = [replace(c, overrides=(("sim.aero", plant_overrides(args)["sim.aero"]), *c.overrides))
             for c in CELLS if c.name in names]
    controllers = _select(args.controllers, tuple(CONTROLLERS), "controller(s)")
    patterns = tuple({"lab": LAB, "paper": PAPER}[n] for n in _select(args.patterns, ("lab", "paper"), "pattern(s)"))
    if args.quick and not args.patterns:
        patterns = (LAB,)
    duration = args.duration or (4.0 if args.quick else 0.0)
    if duration:
        patterns = tuple(replace(p, duration=duration) for p in patterns)
    mode = "quick" if args.quick else "full"
    command = "cfknode bench robustness" + (" --quick" if args.quick else "") + f" {executor.command_flags()} --seed {args.seed}"
    for flag, value in (("--cells", args.cells), ("--controllers", args.controllers), ("--patterns", args.patterns)):
        if value:
            command += f" {flag} '{value}'"
    if args.duration:
        command += f" --duration {args.duration:g}"
    command += plant_flags(args)
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="cfknode-robust-", dir=out))
    tasks = [(cell, pat, c) for cell in cells for pat in patterns for c in controllers]
    console = Console()
    console.print(f"bench robustness: {len(cells)} cell(s) x {len(patterns)} pattern(s) x {len(controllers)} "
                  f"controller(s) = {len(tasks)} flights")
    jobs = [(cell, pat, c, args.seed, str(logs)) for cell, pat, c in tasks]
    results: list[RunResult] = run_ordered(
        run_one_job, jobs, executor, "bench robustness", console=console,
        describe=lambda i, res: f"{res.cell} / {res.pattern} / {res.controller}: {res.mse:.3g} {_flags(res)}")
    order = {(cell.name, pat.name, c): i for i, (cell, pat, c) in enumerate(tasks)}
    results.sort(key=lambda r: order[(r.cell, r.pattern, r.controller)])
    md = markdown(results, controllers, command, version, mode, patterns)
    stem = "robustness" + ("_quick" if args.quick else "")
    (out / f"{stem}.md").write_text(md + "\n")
    (out / f"{stem}.json").write_text(json.dumps(
        {"command": command, "version": version, "mode": mode,
         "runs": [{**asdict(r), "recover_s": None if r.recover_s is None else
                   (None if math.isinf(r.recover_s) else r.recover_s), "never_recovered": r.recover_s == math.inf}
                  for r in results]}, indent=1))
    console.print(md)
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}; flight logs in {logs}")
    return 0


__all__ = ["ADAPTIVE", "CELLS", "CONTROLLERS", "Cell", "PATTERN_HEIGHT", "Pattern", "RunResult", "SAG_MARGIN",
           "add_robustness_arguments", "markdown", "recovery_time", "run_one", "run_robustness", "unavoidable_sag", "wins"]
