"""``cfknode bench``: reproducible benchmarks.  ``cfknode bench paper`` reproduces Table 1.

Each benchmark is an entry of ``BENCHES`` (name -> help, argument setup, runner), and the
paper benchmark's modes are entries of ``PAPER_MODES``: ``bench timing`` and
``--mode hierarchical`` are additions there, not edits of what exists.

A benchmark of independent seeded tasks gets ``--jobs``, ``--executor {local,ray}`` and
``--address`` from ``_add_executor_arguments(p)``, and runs its tasks (a module-level function of
one picklable argument) with ``cfknode.app.bench.executor.run_ordered(fn, tasks,
ExecutorSettings.from_args(args))``, on local processes or Ray alike.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path
from typing import Callable

from cfknode.app.errors import UsageError

HELP = ("benchmarks: 'paper' reproduces the paper's Table 1, 'timing' measures the real-time parts, "
        "'online' flies the online-learning acceptance protocol, 'learning' the cells where learning should win")


def _version() -> str:
    """cfknode's version, with the git commit and "+dirty" when the checkout has changes (read-only git)."""
    from cfknode import __version__

    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5, cwd=here)
        if rev.returncode == 0 and rev.stdout.strip():
            dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], capture_output=True, timeout=5, cwd=here).returncode
            return f"{__version__} (git {rev.stdout.strip()}{'+dirty' if dirty else ''})"
    except (OSError, subprocess.SubprocessError):
        pass
    return __version__


# --- bench paper ---------------------------------------------------------------------------


def _add_paper_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=sorted(PAPER_MODES), default="full", help="full: 13-state MPC on thrust and moments")
    p.add_argument(
        "--formulation", choices=["paper", "default", "both"], default="both",
        help="paper: the authors' code; default: cfknode's; both (default)",
    )
    p.add_argument("--quick", action="store_true", help="one cell, 3.5 s: a smoke test of every path (< 1 min)")
    p.add_argument("--out", default="bench_out", help="output directory (default ./bench_out)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cells", metavar="R:V,...", help="hierarchical mode: only these of the paper's cells, e.g. 2:0.8,3:1.0")
    from cfknode.app.bench.rows import add_latency_arguments, add_plant_arguments

    add_latency_arguments(p)  # hierarchical mode's online rows
    add_plant_arguments(p)  # hierarchical mode's plant (full mode flies the paper's own simulator)
    _add_executor_arguments(p)


def _add_executor_arguments(p: argparse.ArgumentParser, jobs: int = 2, jobs_help: str = "") -> None:
    from cfknode.app.bench.executor import add_executor_arguments

    add_executor_arguments(p, jobs, jobs_help)


def _run_paper(args: argparse.Namespace) -> int:
    from cfknode.app.bench.executor import ExecutorSettings

    ExecutorSettings.from_args(args)  # bad --jobs, --address or a missing Ray: before anything runs
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is not a directory")
    return PAPER_MODES[args.mode](args, out)


def _paper_full(args: argparse.Namespace, out: Path) -> int:
    from rich.console import Console

    from cfknode.app.bench.executor import ExecutorSettings
    from cfknode.app.bench.paper import report
    from cfknode.app.bench.paper.suite import BenchPlan, Cell, run_plan

    forms = ("paper", "default") if args.formulation == "both" else (args.formulation,)
    plan = BenchPlan.quick(forms, args.seed) if args.quick else BenchPlan.full(forms, args.seed)
    executor = ExecutorSettings.from_args(args)
    console = Console()
    out.mkdir(parents=True, exist_ok=True)
    command = (
        f"cfknode bench paper --mode {args.mode} --formulation {args.formulation}"
        + (" --quick" if args.quick else "") + f" {executor.command_flags()} --seed {args.seed}"
    )
    console.print(f"bench paper --mode {args.mode}: {len(plan.cells)} cell(s) x {len(forms)} formulation(s), "
                  f"{len(plan.tasks())} tasks on {executor.describe()}")
    results = run_plan(plan, executor, progress=True, console=console)
    version = _version()
    md = report.markdown(results, version, command)
    stem = f"paper_{args.mode}" + ("_quick" if args.quick else "")
    (out / f"{stem}.md").write_text(md + "\n")
    report.write_json(out / f"{stem}.json", report.to_json(results, version, command))
    plots = []
    fig_cell = plan.cells[0] if args.quick else Cell(3.0, 1.2)
    for name in forms:
        path = out / f"{stem}_fig2_{name}.png"
        if report.plot_fig2(results, name, fig_cell, path):
            plots.append(path)
    console.print(md)
    console.print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}" + "".join(f", {p}" for p in plots))
    return 0


def _paper_hierarchical(args: argparse.Namespace, out: Path) -> int:
    from cfknode.app.bench.hierarchical import run_hierarchical

    return run_hierarchical(args, out, _version())


PAPER_MODES: dict[str, Callable[[argparse.Namespace, Path], int]] = {
    "full": _paper_full,
    "hierarchical": _paper_hierarchical,
}


def _add_timing_arguments(p: argparse.ArgumentParser) -> None:
    from cfknode.app.bench.timing import add_timing_arguments

    add_timing_arguments(p)


def _run_timing(args: argparse.Namespace) -> int:
    from cfknode.app.bench.timing import run_timing

    return run_timing(args)

def _add_online_arguments(p: argparse.ArgumentParser) -> None:
    from cfknode.app.bench.online import add_online_arguments

    add_online_arguments(p)
    # One cell at a time by default: a flight beside another would slow its trainer and so change
    # what is measured; on Ray each cell reserves two CPUs (the flight and its trainer).
    _add_executor_arguments(p, jobs=1, jobs_help="cells at once (default 1: one after another, in this process)")


def _run_online(args: argparse.Namespace) -> int:
    from cfknode.app.bench.executor import ExecutorSettings
    from cfknode.app.bench.online import run_online

    ExecutorSettings.from_args(args, default_jobs=1)  # bad --jobs, --address or a missing Ray: before anything runs

    return run_online(args, _version())


def _add_robustness_arguments(p: argparse.ArgumentParser) -> None:
    from cfknode.app.bench.robustness import add_robustness_arguments

    add_robustness_arguments(p)


def _run_robustness(args: argparse.Namespace) -> int:
    from cfknode.app.bench.robustness import run_robustness

    return run_robustness(args, _version())


def _add_learning_arguments(p: argparse.ArgumentParser) -> None:
    from cfknode.app.bench.learning import add_learning_arguments

    add_learning_arguments(p)


def _run_learning(args: argparse.Namespace) -> int:
    from cfknode.app.bench.learning import run_learning

    return run_learning(args, _version())


BENCHES: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "paper": ("reproduce the paper's Table 1 (and the oracle limit)", _add_paper_arguments, _run_paper),
    "timing": ("solver, tick, swap and training times: medians and p99 from one run", _add_timing_arguments,
               _run_timing),
    "online": ("the online-learning protocol: online vs the other controllers and the oracle under the paper's mass changes",
               _add_online_arguments, _run_online),
    "robustness": ("every controller on plants it was not tuned on: motor lag, thrust-to-weight, attitude response, "
                   "thrust map, mocap latency and noise, wind, gusts, mass steps, battery sag",
                   _add_robustness_arguments, _run_robustness),
    "learning": ("where learning should win: fast loops, vertical manoeuvres, surface transit, a stacked pair, on the "
                 "realistic plant; nominal MPC, MPC + layer, KNODE-MPC-Online with and without the layer",
                 _add_learning_arguments, _run_learning),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", required=True)
    for name, (help_text, add, _) in BENCHES.items():
        add(sub.add_parser(name, help=help_text, description=help_text))


def run(args: argparse.Namespace) -> int:
    return BENCHES[args.bench][2](args)
