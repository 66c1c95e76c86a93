"""What the mass-step benches (``bench online``, ``bench paper --mode hierarchical``) share: the
compared controllers' names, the online latency they fly with, and the report's extra columns
(time to recover per mass step, wins, ratio to the oracle)."""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from cfknode.flight.learning.latency import LATENCY_MODES
from cfknode.flight.recovery import RECOVERY_THRESHOLD_M

LABELS = {
    "geometric": "geometric",
    "nominal": "nominal MPC",
    "offline": "offline KNODE-MPC",
    "online": "KNODE-MPC-Online",
    "dob": "MPC + adaptation (dob)",
    "online_dob": "KNODE-MPC-Online + adaptation (dob)",
    "oracle": "oracle (MPC told the true mass)",
    "oracle_late": "oracle told 20 ms late",
}
ORACLE = "oracle"
ORACLE_LATE = "oracle_late"  # a bound for estimators that must see a change first: two 100 Hz mocap frames
REFERENCES = (ORACLE, ORACLE_LATE)  # rows that read the simulator's truth: never "the lowest"
# The benches fly lockstep with a fixed training latency: a round's CPU time grows a little under load, and a
# round near a rounding step of `cpu` can cross it and move a swap, which a fixed delay cannot
# (docs/history.md#reproducible-online-benchmarks).
DEFAULT_LATENCY = "fixed"
DEFAULT_FIXED_LATENCY_S = 0.1  # s: the trainer's CPU time per round measured here, rounded up


def add_latency_arguments(p: Any) -> None:
    p.add_argument("--latency", choices=LATENCY_MODES, default=DEFAULT_LATENCY,
                   help=f"online learning's training latency in lockstep (default {DEFAULT_LATENCY}: reproducible; "
                        "cpu: the trainer's CPU time; wall: its real round trip, machine-dependent)")
    p.add_argument("--fixed-latency", type=float, default=DEFAULT_FIXED_LATENCY_S, metavar="S",
                   help=f"s, the delay with --latency fixed (default {DEFAULT_FIXED_LATENCY_S:g})")


# The mass-step benches reproduce the paper's protocol on the plant their tables were measured on; the
# realistic plant (docs/realistic-plant.md) is one flag away.
BENCH_AERO = "ideal"


def add_plant_arguments(p: Any) -> None:
    p.add_argument("--aero", choices=("ideal", "realistic"), default=BENCH_AERO,
                   help=f"the simulated plant (default {BENCH_AERO}: the paper's protocol; realistic: drag, inflow, "
                        "ground effect, downwash and a fast force, docs/realistic-plant.md)")


def plant_overrides(args: Any) -> dict[str, Any]:
    """Config overrides for the plant from ``--aero``."""
    return {"sim.aero": getattr(args, "aero", BENCH_AERO)}


def plant_flags(args: Any) -> str:
    """The flag that reproduces the plant, empty for the bench's default."""
    aero = getattr(args, "aero", BENCH_AERO)
    return "" if aero == BENCH_AERO else f" --aero {aero}"


def check_latency_arguments(args: Any) -> None:
    from cfknode.app.errors import UsageError

    if not 0.0 <= args.fixed_latency <= 60.0:
        raise UsageError(f"--fixed-latency must be in [0, 60] s, got {args.fixed_latency}")


def latency_overrides(args: Any) -> dict[str, Any]:
    """Config overrides for the online flights' latency policy from ``--latency``/``--fixed-latency``."""
    return {"online.latency": args.latency, "online.fixed_latency_s": float(args.fixed_latency)}


def latency_flags(args: Any) -> str:
    """The command-line flags that reproduce the latency policy (for the report's command line)."""
    return f" --latency {args.latency}" + (f" --fixed-latency {args.fixed_latency:g}" if args.latency == "fixed" else "")


def latency_note(args: Any) -> str:
    """One line for the report's header: which latency the online rows flew with."""
    if args.latency == "fixed":
        return f"Online latency: fixed {args.fixed_latency:g} s from a window's end to its model (reproducible)."
    if args.latency == "cpu":
        return "Online latency: the trainer's CPU time per round, rounded up (online.latency_quantum_s)."
    return "Online latency: the trainer's wall round trip, simulation paced by the wall (varies with machine load)."


def recovery_text(steps: Sequence[Mapping[str, Any]]) -> str:
    """'0.42 / never' : time to recover [s] for each mass step."""
    if not steps:
        return "-"
    return " / ".join("never" if s.get("time_to_recover_s") is None else f"{s['time_to_recover_s']:.2f}" for s in steps)


def peak_text(steps: Sequence[Mapping[str, Any]]) -> str:
    """'0.21 / 0.35' : peak error [m] after each mass step."""
    if not steps:
        return "-"
    return " / ".join("-" if s.get("peak_error_m") is None else f"{s['peak_error_m']:.3f}" for s in steps)


def recovery_legend() -> str:
    return (f"Time to recover: s from each mass step until the position error is under {100 * RECOVERY_THRESHOLD_M:g} cm "
            "and stays there until the next step, or until one MPC horizon (1 s) before the pattern's end, where the "
            "MPC already brakes for the stop (never: it does not); peak: the largest error in that interval, m.")


def wins(cells: Iterable[Mapping[str, float]], exclude: tuple[str, ...] = REFERENCES) -> dict[str, int]:
    """How many cells each controller has the lowest MSE in, the oracles (references) left out."""
    counts: dict[str, int] = {}
    for mse in cells:
        rivals = {k: v for k, v in mse.items() if k not in exclude and math.isfinite(v)}
        if rivals:
            best = min(rivals, key=rivals.__getitem__)
            counts[best] = counts.get(best, 0) + 1
    return counts


def oracle_ratios(cells: Sequence[Mapping[str, float]], controllers: Sequence[str]) -> dict[str, float]:
    """Median over the cells of each controller's MSE over the oracle's (cells without an oracle skipped)."""
    out = {}
    for c in controllers:
        r = [m[c] / m[ORACLE] for m in cells if c in m and m.get(ORACLE, 0.0) > 0.0]
        if r:
            out[c] = float(np.median(r))
    return out


def summary_lines(cells: Sequence[Mapping[str, float]], controllers: Sequence[str]) -> list[str]:
    """'wins' and 'ratio to the oracle' lines for the report."""
    counts = wins(cells)
    n = len(cells)
    lines = ["Lowest MSE (oracles left out): " + ", ".join(
        f"{LABELS.get(c, c)} {counts.get(c, 0)} of {n}" for c in controllers if c not in REFERENCES) + "."]
    ratios = oracle_ratios(cells, controllers)
    if ratios:
        lines.append("MSE over the oracle's (median over cells): " + ", ".join(
            f"{LABELS.get(c, c)} {r:.2f}" for c, r in ratios.items() if c != ORACLE) + ".")
    return lines


__all__ = ["DEFAULT_FIXED_LATENCY_S", "DEFAULT_LATENCY", "LABELS", "ORACLE", "ORACLE_LATE", "REFERENCES",
           "add_latency_arguments",
           "check_latency_arguments", "latency_flags", "latency_note", "latency_overrides", "oracle_ratios",
           "peak_text", "recovery_legend", "recovery_text", "summary_lines", "wins"]
