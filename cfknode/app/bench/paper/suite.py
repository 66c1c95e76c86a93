"""The benchmark plan and its parallel execution over worker processes.

A plan is formulations x cells x controllers.  Every (formulation, cell, controller) is one
task; the offline KNODE-MPC and (in the paper formulation, whose online queue starts from
it) KNODE-MPC-Online wait for that cell's offline-model task.  Tasks run on the bench
executor (``cfknode.app.bench.executor``: local spawned processes or Ray, one thread each), and
every task carries its own seed, so results do not depend on the schedule or the machine.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

from cfknode.app.bench.executor import ExecutorSettings, open_runner

from cfknode.app.bench.paper.rigid_body_knode import QueueWeights
from cfknode.app.bench.paper.controllers import CONTROLLERS, Formulation
from cfknode.app.bench.paper.protocol import MassEvent, PaperProtocol
from cfknode.app.bench.paper.runner import RunResult, offline_model, simulate

OFFLINE = "offline_model"  # the task that records the data run and trains the offline network


@dataclass(frozen=True)
class Cell:
    radius: float
    speed: float

    @property
    def label(self) -> str:
        return f"r={self.radius:g} v={self.speed:g}"


PAPER_CELLS: tuple[Cell, ...] = tuple(Cell(r, v) for r in (2.0, 3.0, 4.0) for v in (0.8, 1.0, 1.2))


@dataclass(frozen=True)
class BenchPlan:
    formulations: tuple[str, ...]
    cells: tuple[Cell, ...] = PAPER_CELLS
    controllers: tuple[str, ...] = CONTROLLERS
    duration: float = 8.0
    events: tuple[MassEvent, ...] = (MassEvent(2.0, -0.015), MassEvent(5.0, 0.025))
    seed: int = 0
    integrator: str = "rk45"
    fixed_latency: float | None = None  # default formulation: None = measured training wall time

    @classmethod
    def full(cls, formulations: tuple[str, ...], seed: int = 0) -> BenchPlan:
        return cls(formulations=formulations, seed=seed)

    @classmethod
    def quick(cls, formulations: tuple[str, ...], seed: int = 0) -> BenchPlan:
        """One cell, 3.5 s, the two mass events at 1 s and 2 s: every controller and learner path
        runs (offline model, both events, several online rounds) in well under a minute."""
        return cls(
            formulations=formulations,
            cells=(Cell(2.0, 0.8),),
            duration=3.5,
            events=(MassEvent(1.0, -0.015), MassEvent(2.0, 0.025)),
            seed=seed,
        )

    def protocol(self, cell: Cell) -> PaperProtocol:
        return PaperProtocol(
            radius=cell.radius, speed=cell.speed, duration=self.duration, events=self.events, integrator=self.integrator
        )

    def formulation(self, name: str) -> Formulation:
        form = Formulation.named(name)
        # The collector of the paper starts at the (known) first event; keep that in a short plan.
        if form.lockstep and self.events:
            form = replace(form, collect_from=self.events[0].time)
        return form

    def cell_seed(self, cell: Cell) -> int:
        return self.seed * 1000 + self.cells.index(cell)

    def tasks(self) -> list[Task]:
        out = []
        for name in self.formulations:
            for cell in self.cells:
                needs_offline = "knode_offline" in self.controllers or (
                    "knode_online" in self.controllers and self.formulation(name).online_starts_from == "offline"
                )
                if needs_offline:
                    out.append(Task(name, cell, OFFLINE))
                out += [Task(name, cell, kind) for kind in self.controllers]
        return out


@dataclass(frozen=True)
class Task:
    formulation: str
    cell: Cell
    kind: str  # a controller, or OFFLINE

    @property
    def label(self) -> str:
        return f"{self.formulation} {self.cell.label} {self.kind}"


@dataclass(frozen=True)
class OfflineInfo:
    weights: QueueWeights
    data_run_wall: float
    train_wall: float


@dataclass
class BenchResults:
    plan: BenchPlan
    runs: list[RunResult] = field(default_factory=list)
    offline: dict[tuple[str, float, float], OfflineInfo] = field(default_factory=dict)
    wall_time: float = 0.0
    jobs: int = 1
    where: str = "this process"  # the executor, as the report names it

    def get(self, formulation: str, cell: Cell, controller: str) -> RunResult | None:
        for r in self.runs:
            if (r.formulation, r.radius, r.speed, r.controller) == (formulation, cell.radius, cell.speed, controller):
                return r
        return None


def _needs(plan: BenchPlan, task: Task) -> bool:
    """True when the task must wait for its cell's offline model."""
    if task.kind == "knode_offline":
        return True
    return task.kind == "knode_online" and plan.formulation(task.formulation).online_starts_from == "offline"


def execute(plan: BenchPlan, task: Task, offline: QueueWeights | None) -> RunResult | OfflineInfo:
    """Run one task (in a worker process)."""
    _single_thread()
    protocol = plan.protocol(task.cell)
    form = plan.formulation(task.formulation)
    seed = plan.cell_seed(task.cell)
    if task.kind == OFFLINE:
        weights, data_wall, train_wall = offline_model(protocol, form, seed)
        return OfflineInfo(weights, data_wall, train_wall)
    result, _ = simulate(protocol, form, task.kind, offline=offline, seed=seed, fixed_latency=plan.fixed_latency)  # type: ignore[arg-type]
    return result


def execute_job(job: tuple[BenchPlan, Task, QueueWeights | None]) -> RunResult | OfflineInfo:
    """``execute`` on one argument, as the executor calls its tasks."""
    return execute(*job)


def _single_thread() -> None:
    # One thread per worker: two workers share two cores, and torch's or BLAS's own threads on
    # top oversubscribed them (training rounds up to 80x slower, docs/solver-timings.md#training).
    import torch

    torch.set_num_threads(1)


def _describe(task: Task, out: RunResult | OfflineInfo) -> str:
    mse = getattr(out, "mse", None)
    return task.label + (f": {mse:.4f}" if mse is not None else "")


def run_plan(
    plan: BenchPlan,
    executor: ExecutorSettings | None = None,
    on_done: Callable[[Task, RunResult | OfflineInfo], None] | None = None,
    progress: bool = False,
    console: Any = None,
) -> BenchResults:
    """Run every task of ``plan`` on ``executor`` (default: 2 local processes; 1 job: in this
    process, in order).  Runs are listed in plan order whatever order they finished in."""
    executor = executor or ExecutorSettings()
    t0 = time.perf_counter()
    results = BenchResults(plan, jobs=executor.jobs, where=executor.describe())
    tasks = plan.tasks()
    # Offline models first: the tasks that wait on them are the longest.
    ready = sorted((i for i, t in enumerate(tasks) if not _needs(plan, t)), key=lambda i: tasks[i].kind != OFFLINE)
    waiting = [i for i, t in enumerate(tasks) if _needs(plan, t)]
    runs: dict[int, RunResult] = {}
    offline: dict[int, OfflineInfo] = {}
    with open_runner(executor, "bench paper", len(tasks), lambda i, out: _describe(tasks[i], out), console,
                     progress) as runner:
        for i in ready:
            runner.submit(execute_job, (plan, tasks[i], None), i)
        for i, out in runner.as_completed():
            task = tasks[i]
            if isinstance(out, OfflineInfo):
                offline[i] = out
                for j in [j for j in waiting if (tasks[j].formulation, tasks[j].cell) == (task.formulation, task.cell)]:
                    waiting.remove(j)
                    runner.submit(execute_job, (plan, tasks[j], out.weights), j)
            else:
                runs[i] = out
            if on_done is not None:
                on_done(task, out)
    results.runs = [runs[i] for i in sorted(runs)]
    results.offline = {(tasks[i].formulation, tasks[i].cell.radius, tasks[i].cell.speed): offline[i] for i in sorted(offline)}
    results.wall_time = time.perf_counter() - t0
    return results


__all__ = ["BenchPlan", "BenchResults", "Cell", "OFFLINE", "OfflineInfo", "PAPER_CELLS", "Task", "execute", "execute_job", "run_plan"]
