"""Tables, JSON and the Fig. 2 plot for ``cfknode bench paper``.

The published values are Table 1 of the paper, as printed.  The paper's
"outperforms by X %" is the relative difference of the averages over the nine runs
(58.8 % and 53.3 % for KNODE-MPC and geometric follow exactly from the printed rows that
way; its 18.6 % for MPC does not: the printed rows give 24.7 %).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.bench.paper.protocol import ChordCircle, MassEvent, improvement_percent
from cfknode.app.bench.paper.suite import BenchResults, Cell

# Table 1 as printed: row -> {(radius, speed): MSE}.
_SPEEDS = (0.8, 1.0, 1.2)
_RADII = (2.0, 3.0, 4.0)


def _row(values: tuple[float, ...]) -> dict[tuple[float, float], float]:
    return {(r, v): values[3 * i + j] for i, r in enumerate(_RADII) for j, v in enumerate(_SPEEDS)}


PUBLISHED: dict[str, dict[tuple[float, float], float]] = {
    "mpc": _row((0.0904, 0.1280, 0.1705, 0.0949, 0.1371, 0.1861, 0.0967, 0.1412, 0.1937)),
    "knode_offline": _row((0.1222, 0.1945, 0.2555, 0.1974, 0.1769, 0.2098, 0.5303, 0.4175, 0.3418)),
    "geometric": _row((0.2168, 0.2572, 0.3253, 0.2067, 0.2267, 0.2606, 0.2046, 0.2194, 0.2416)),
    "knode_online": _row((0.0660, 0.1113, 0.1678, 0.0657, 0.1043, 0.1554, 0.0709, 0.1092, 0.1571)),
}
PUBLISHED_IMPROVEMENT = {"mpc": 18.6, "knode_offline": 58.8, "geometric": 53.3}
_PAPER_EVENTS = (MassEvent(2.0, -0.015), MassEvent(5.0, 0.025))

LABELS = {
    "mpc": "MPC (nominal)",
    "knode_offline": "KNODE-MPC (offline)",
    "geometric": "Geometric",
    "knode_online": "KNODE-MPC-Online",
    "oracle": "Oracle (true mass)",
}


def _fmt(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.4g}"


def _ratio(a: float | None, b: float | None) -> str:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0:
        return "-"
    return f"{a / b:.2f}"


def markdown(results: BenchResults, version: str, command: str) -> str:
    plan = results.plan
    cells = plan.cells
    out = [
        f"Command: `{command}`  ",
        f"cfknode {version}; {len(results.runs)} runs on {results.where}, "
        f"{results.wall_time / 60:.1f} min wall.  MSE in m^2 (mean over all samples and the 3 axes).",
        "",
    ]
    header = "| controller | " + " | ".join(c.label for c in cells) + " |"
    rule = "|---|" + "---|" * len(cells)
    for name in plan.formulations:
        out += [f"### formulation: {name}", "", header, rule]
        for kind in plan.controllers:
            vals = [results.get(name, c, kind) for c in cells]
            out.append(f"| {LABELS.get(kind, kind)} | " + " | ".join(_fmt(r.mse if r else None) for r in vals) + " |")
        published = plan.duration == 8.0 and plan.events == _PAPER_EVENTS
        for kind in ("mpc", "knode_offline", "geometric", "knode_online"):
            if kind in plan.controllers and published:
                vals = [PUBLISHED[kind].get((c.radius, c.speed)) for c in cells]
                out.append(f"| paper: {LABELS[kind]} | " + " | ".join(_fmt(v) for v in vals) + " |")
        online = [results.get(name, c, "knode_online") for c in cells]
        oracle = [results.get(name, c, "oracle") for c in cells]
        if published and any(online):
            pub = [PUBLISHED["knode_online"].get((c.radius, c.speed)) for c in cells]
            out.append("| paper's Online / this Online | " + " | ".join(
                _ratio(p, o.mse if o else None) for p, o in zip(pub, online)) + " |")
        if any(online) and any(oracle):
            out.append("| this Online / Oracle | " + " | ".join(
                _ratio(o.mse if o else None, q.mse if q else None) for o, q in zip(online, oracle)) + " |")
        out.append("")
        imp = improvements(results, name)
        if imp:
            parts = [f"{LABELS[k]} {v:.1f} %" for k, v in imp.items()]
            out.append("KNODE-MPC-Online outperforms, by (mean baseline - mean Online) / mean baseline over the "
                       "cells as the paper computes it: " + "; ".join(parts) + ".")
            if published:
                pub = "; ".join(f"{LABELS[k]} {v:.1f} %" for k, v in PUBLISHED_IMPROVEMENT.items())
                out.append(f"The paper reports: {pub}.")
            out.append("")
        out += _timing_lines(results, name)
    return "\n".join(out)


def improvements(results: BenchResults, formulation: str) -> dict[str, float]:
    """(mean baseline - mean online) / mean baseline over the cells where both ran, in %."""
    cells = results.plan.cells
    online = [results.get(formulation, c, "knode_online") for c in cells]
    if any(r is None for r in online):
        return {}
    out = {}
    for kind in ("mpc", "knode_offline", "geometric"):
        base = [results.get(formulation, c, kind) for c in cells]
        if all(b is not None for b in base):
            out[kind] = improvement_percent(
                float(np.mean([b.mse for b in base])), float(np.mean([r.mse for r in online]))  # type: ignore[union-attr]
            )
    return out


def _timing_lines(results: BenchResults, formulation: str) -> list[str]:
    runs = [r for r in results.runs if r.formulation == formulation]
    lines = []
    for kind in results.plan.controllers:
        rs = [r for r in runs if r.controller == kind]
        if not rs:
            continue
        wall = float(np.median([r.wall_time for r in rs]))
        text = f"- {LABELS.get(kind, kind)}: median run {wall:.1f} s wall for {rs[0].sim_time:g} s simulated"
        if kind != "geometric":
            text += f"; MPC solve median {np.median([r.solve_ms_median for r in rs]):.1f} ms"
            text += f", p99 {np.max([r.solve_ms_p99 for r in rs]):.1f} ms, {np.mean([r.iterations_mean for r in rs]):.1f} IPOPT iterations"
            fails = sum(r.failures for r in rs)
            fb = sum(r.fallbacks for r in rs)
            if fails or fb:
                text += f"; {fails} failed solves, {fb} nominal fallbacks"
        if kind == "knode_online":
            rounds = [x for r in rs for x in r.rounds]
            swapped = [x for x in rounds if math.isfinite(x.swap)]
            text += f"; {len(rounds)} training rounds, {len(swapped)} swapped in"
            if rounds:
                text += f", training {np.median([x.wall_time for x in rounds]) * 1e3:.0f} ms median"
            if swapped:
                lat = np.median([x.swap - x.window_end for x in swapped])
                text += f", window end to first use {lat * 1e3:.0f} ms median (sim time)"
            drops = sum(len(r.model_drops) for r in rs)
            if drops:
                text += f"; the monitor dropped a model {drops} times"
        lines.append(text)
    return [f"Timings ({formulation}):", *lines, ""] if lines else []


def to_json(results: BenchResults, version: str, command: str) -> dict[str, Any]:
    plan = results.plan
    published = plan.duration == 8.0 and plan.events == _PAPER_EVENTS
    runs = []
    for r in results.runs:
        runs.append(
            {
                "formulation": r.formulation,
                "controller": r.controller,
                "radius": r.radius,
                "speed": r.speed,
                "mse": r.mse,
                "mse_per_axis": list(r.per_axis),
                "published": PUBLISHED.get(r.controller, {}).get((r.radius, r.speed)) if published else None,
                "wall_time_s": r.wall_time,
                "sim_time_s": r.sim_time,
                "solve_ms_median": _num(r.solve_ms_median),
                "solve_ms_p99": _num(r.solve_ms_p99),
                "ipopt_iterations_mean": _num(r.iterations_mean),
                "failed_solves": r.failures,
                "nominal_fallbacks": r.fallbacks,
                "training_wall_s": r.training_wall,
                "model_drops": list(r.model_drops),
                "rounds": [
                    {
                        "window_end": x.window_end,
                        "start": x.start,
                        "ready": x.ready,
                        "swap": _num(x.swap),
                        "wall_time_s": x.wall_time,
                        "samples": x.samples,
                        "accepted": x.accepted,
                        "val_candidate": _num(x.val_candidate),
                        "val_current": _num(x.val_current),
                    }
                    for x in r.rounds
                ],
            }
        )
    return {
        "command": command,
        "version": version,
        "plan": {
            "formulations": list(plan.formulations),
            "cells": [[c.radius, c.speed] for c in plan.cells],
            "controllers": list(plan.controllers),
            "duration_s": plan.duration,
            "events": [[e.time, e.delta] for e in plan.events],
            "seed": plan.seed,
            "integrator": plan.integrator,
        },
        "wall_time_s": results.wall_time,
        "jobs": results.jobs,
        "executor": results.where,
        "improvement_percent": {f: improvements(results, f) for f in plan.formulations},
        "offline_models": [
            {"formulation": k[0], "radius": k[1], "speed": k[2], "data_run_wall_s": v.data_run_wall, "train_wall_s": v.train_wall}
            for k, v in results.offline.items()
        ],
        "runs": runs,
    }


def _num(x: float) -> float | None:
    return x if math.isfinite(x) else None


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")


def plot_fig2(results: BenchResults, formulation: str, cell: Cell, path: Path) -> bool:
    """The paper's Fig. 2 for one cell: top view (x, y) and altitude over time. False if runs are missing."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k in ("mpc", "knode_offline", "knode_online", "oracle") if results.get(formulation, cell, k)]
    if not kinds:
        return False
    protocol = results.plan.protocol(cell)
    circle = ChordCircle(protocol)
    t = np.linspace(0.0, protocol.duration, 801)
    ref = circle.sample(t)[0]
    fig, (top, alt) = plt.subplots(1, 2, figsize=(11, 4.6))
    # The reference is drawn last and dashed: with preview the runs lie on it and would hide it.
    top.plot(ref[:, 0], ref[:, 1], color="red", lw=1.2, ls="--", label="reference", zorder=5)
    alt.plot(t, ref[:, 2], color="red", lw=1.2, ls="--", label="reference", zorder=5)
    for kind in kinds:
        run = results.get(formulation, cell, kind)
        assert run is not None
        tr = run.trajectory
        label = f"{LABELS[kind]} (MSE {run.mse:.4g})"
        top.plot(tr[:, 1], tr[:, 2], lw=1.2, label=label)
        alt.plot(tr[:, 0], tr[:, 3], lw=1.2, label=label)
    for ev in protocol.events:
        alt.axvline(ev.time, color="grey", lw=0.8, ls=":")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.set_title(f"top view, {cell.label} ({formulation} formulation)")
    alt.set_xlabel("t [s]")
    alt.set_ylabel("z [m]")
    alt.set_title("altitude (mass events dotted)")
    alt.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


__all__ = ["LABELS", "PUBLISHED", "PUBLISHED_IMPROVEMENT", "improvements", "markdown", "plot_fig2", "to_json", "write_json"]
