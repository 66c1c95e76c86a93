"""Where the benchmarks' tasks run: a local process pool (the default) or a Ray cluster.

A task is a picklable argument of a picklable module-level function ``fn(task)``; every task
carries its own seed, so the numbers do not depend on where or in which order tasks run.
``run_tasks`` yields ``(index, result)`` as tasks complete; ``run_ordered`` returns the results in
task order; ``open_runner`` lets a caller submit more tasks while results arrive (the paper
bench's tasks that wait for their cell's offline model).  Each has a rich progress bar.

- local, ``jobs`` > 1: a ``ProcessPoolExecutor`` with the spawn start method, one BLAS/OpenMP
  thread per worker.  A worker that dies (killed, out of memory) breaks the whole pool: every
  task it lost is resubmitted to a fresh pool, at most ``max_retries`` times each.
- local, ``jobs`` = 1: in this process, in submission order.
- ray: an existing cluster at ``address`` (or ``RAY_ADDRESS``), else a local Ray started for the
  run with ``jobs`` x ``cpus_per_task`` CPUs and shut down after (a Ray this process already
  joined is used as it is).  Ray retries a task whose worker died (``max_retries``).  Nodes
  of a cluster need cfknode installed in the same version.

A bench adds the options with ``add_executor_arguments`` and reads them with
``ExecutorSettings.from_args``.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import importlib.util
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol

KINDS = ("local", "ray")
RAY_MISSING = "--executor ray needs Ray, which is not installed: pip install 'cfknode[ray]'"
# One thread per worker: workers share the cores, and torch's or BLAS's own threads on top
# oversubscribe them (docs/solver-timings.md#training).
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _usage_error(message: str) -> Exception:
    # Imported here: spawned workers import this module for their initializer, before numpy
    # loads, and the command line's module would load it.
    from cfknode.app.errors import UsageError

    return UsageError(message)


@dataclass(frozen=True)
class ExecutorSettings:
    kind: str = "local"
    jobs: int = 2  # concurrent tasks: local worker processes, or the CPUs of a local Ray
    address: str | None = None  # ray: an existing cluster; None = start a local one
    max_retries: int = 1  # resubmissions of a task whose worker died
    cpus_per_task: int = 1  # ray: CPUs a task reserves (a flight with its trainer process needs 2)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise _usage_error(f"--executor must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.jobs < 1:
            raise _usage_error(f"--jobs must be >= 1, got {self.jobs}")
        if self.max_retries < 0 or self.cpus_per_task < 1:
            raise _usage_error("max_retries must be >= 0 and cpus_per_task >= 1")
        if self.address is not None and self.kind != "ray":
            raise _usage_error("--address needs --executor ray")

    @classmethod
    def from_args(cls, args: argparse.Namespace, cpus_per_task: int = 1, default_jobs: int = 2) -> ExecutorSettings:
        """The settings of ``add_executor_arguments``'s options; ``RAY_ADDRESS`` when --address is not given."""
        kind = getattr(args, "executor", "local")
        address = getattr(args, "address", None)
        if kind == "ray":
            address = address or os.environ.get("RAY_ADDRESS") or None
            if importlib.util.find_spec("ray") is None:
                raise _usage_error(RAY_MISSING)
        return cls(kind=kind, jobs=getattr(args, "jobs", default_jobs), address=address, cpus_per_task=cpus_per_task)

    @property
    def runs_here(self) -> bool:
        """Tasks run in this process, one after another (so they may report progress directly)."""
        return self.kind == "local" and self.jobs == 1

    def describe(self) -> str:
        if self.kind == "ray":
            return f"Ray at {self.address}" if self.address else f"a local Ray with {self.jobs * self.cpus_per_task} CPU(s)"
        return "this process" if self.runs_here else f"{self.jobs} process(es)"

    def command_flags(self) -> str:
        """The options as they would be typed, for a report's command line."""
        flags = f"--jobs {self.jobs}"
        if self.kind == "ray":
            flags += " --executor ray" + (f" --address {self.address}" if self.address else "")
        return flags


def add_executor_arguments(p: argparse.ArgumentParser, jobs: int = 2, jobs_help: str = "") -> None:
    p.add_argument("--jobs", type=int, default=jobs,
                   help=jobs_help or f"tasks at once: local worker processes, or a local Ray's CPUs (default {jobs})")
    p.add_argument("--executor", choices=KINDS, default="local",
                   help="local: a process pool on this machine (default); ray: Ray tasks (pip install 'cfknode[ray]')")
    p.add_argument("--address", default=None,
                   help="with --executor ray: an existing cluster (default: $RAY_ADDRESS, else a local Ray for the run)")


class _Backend(Protocol):
    def submit(self, fn: Callable[[Any], Any], task: Any, key: int) -> None: ...
    def next_done(self) -> tuple[int, Any]: ...
    def close(self, abort: bool) -> None: ...


class _Inline:
    """jobs = 1: in this process, in submission order (a crash here ends the run)."""

    def __init__(self) -> None:
        self._queue: list[tuple[Callable[[Any], Any], Any, int]] = []

    def submit(self, fn: Callable[[Any], Any], task: Any, key: int) -> None:
        self._queue.append((fn, task, key))

    def next_done(self) -> tuple[int, Any]:
        fn, task, key = self._queue.pop(0)
        return key, fn(task)

    def close(self, abort: bool) -> None:
        self._queue.clear()


def _worker_init(env: dict[str, str]) -> None:
    # Runs before the worker unpickles its first task, so before numpy or torch load.
    for name, value in env.items():
        os.environ.setdefault(name, value)


class _LocalPool:
    def __init__(self, jobs: int, max_retries: int) -> None:
        self._jobs, self._max_retries = jobs, max_retries
        self._pool = self._new_pool()
        self._running: dict[cf.Future[Any], tuple[Callable[[Any], Any], Any, int]] = {}
        self._attempts: dict[int, int] = {}

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        ctx = multiprocessing.get_context("spawn")
        return cf.ProcessPoolExecutor(max_workers=self._jobs, mp_context=ctx, initializer=_worker_init,
                                      initargs=(THREAD_ENV,))

    def submit(self, fn: Callable[[Any], Any], task: Any, key: int) -> None:
        try:
            fut = self._pool.submit(fn, task)
        except cf.process.BrokenProcessPool:
            # The pool broke since the last result: keep the task; _recover resubmits it.
            fut = cf.Future()
            fut.set_exception(cf.process.BrokenProcessPool("pool broken before submission"))
        self._running[fut] = (fn, task, key)

    def next_done(self) -> tuple[int, Any]:
        while True:
            done, _ = cf.wait(self._running, return_when=cf.FIRST_COMPLETED)
            for fut in done:
                if not isinstance(fut.exception(), cf.process.BrokenProcessPool):
                    _, _, key = self._running.pop(fut)
                    return key, fut.result()
            self._recover()

    def _recover(self) -> None:
        """A worker died: every task still in the pool is lost; resubmit them to a fresh pool."""
        finished = {f: v for f, v in self._running.items() if f.done() and f.exception() is None}
        lost = [v for f, v in self._running.items() if f not in finished]
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()
        self._running = finished
        for fn, task, key in lost:
            self._attempts[key] = self._attempts.get(key, 0) + 1
            if self._attempts[key] > self._max_retries:
                raise RuntimeError(f"task {key} lost its worker process {self._attempts[key]} time(s); giving up")
            self.submit(fn, task, key)

    def close(self, abort: bool) -> None:
        # After an error or ^C, do not wait for the tasks still running.
        self._pool.shutdown(wait=not abort, cancel_futures=True)


def _call(fn: Callable[[Any], Any], task: Any) -> Any:
    return fn(task)


def connect_ray(address: str | None, num_cpus: int, resources: dict[str, float] | None = None) -> bool:
    """Join the cluster at ``address``, or start a local Ray with ``num_cpus`` CPUs (and custom
    ``resources``) for this run only; a Ray this process already joined is used as it is.
    True when this call joined or started it, so the caller shuts it down."""
    import ray  # optional: only the Ray paths need it

    if ray.is_initialized():
        return False
    if address:
        from cfknode.app.bench.ray_probe import probe_ray

        probe_ray(address)  # bounded: Ray itself retries an address where nothing answers for minutes
        ray.init(address=address, logging_level="warning", log_to_driver=True)
    else:
        # ExecutorSettings.from_args already folded RAY_ADDRESS into the address.
        ray.init(address="local", num_cpus=num_cpus, resources=resources or None, include_dashboard=False,
                 logging_level="warning", runtime_env={"env_vars": THREAD_ENV})
    return True


class _Ray:
    def __init__(self, settings: ExecutorSettings) -> None:
        import ray  # optional: only this path needs it

        self._ray = ray
        self._owned = connect_ray(settings.address, settings.jobs * settings.cpus_per_task)
        self._remote = ray.remote(num_cpus=settings.cpus_per_task, max_retries=settings.max_retries)(_call)
        self._running: dict[Any, int] = {}

    def submit(self, fn: Callable[[Any], Any], task: Any, key: int) -> None:
        self._running[self._remote.remote(fn, task)] = key

    def next_done(self) -> tuple[int, Any]:
        (ref,), _ = self._ray.wait(list(self._running), num_returns=1)
        key = self._running.pop(ref)
        return key, self._ray.get(ref)

    def close(self, abort: bool) -> None:
        for ref in self._running:
            self._ray.cancel(ref, force=True)
        self._running.clear()
        if self._owned:
            self._ray.shutdown()


def _backend(settings: ExecutorSettings) -> _Backend:
    if settings.kind == "ray":
        if importlib.util.find_spec("ray") is None:
            raise _usage_error(RAY_MISSING)
        from cfknode.app.bench.ray_probe import RayAddressError

        try:
            return _Ray(settings)
        except RayAddressError as exc:  # a bad or unreachable --address: one line, exit status 2
            raise _usage_error(str(exc)) from None
    if settings.jobs == 1:
        return _Inline()
    return _LocalPool(settings.jobs, settings.max_retries)


class Runner:
    """Submit tasks, also while results arrive; ``as_completed`` yields ``(key, result)`` until none is pending."""

    def __init__(self, settings: ExecutorSettings, label: str, total: int | None,
                 describe: Callable[[int, Any], str] | None, console: Any, progress: bool) -> None:
        self.settings = settings
        self._label, self._total, self._describe = label, total, describe
        self._console, self._show = console, progress
        self._pending = 0
        self._next_key = 0
        self._backend: _Backend | None = None
        self._bar: Any = None
        self._bar_task: Any = None

    def __enter__(self) -> Runner:
        self._backend = _backend(self.settings)
        if self._show:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(TextColumn(f"[bold]{self._label}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TextColumn("{task.fields[last]}"), console=self._console)
            self._bar.start()
            self._bar_task = self._bar.add_task(self._label, total=self._total, last="")
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._bar is not None:
            self._bar.stop()
        if self._backend is not None:
            self._backend.close(abort=exc is not None)

    def submit(self, fn: Callable[[Any], Any], task: Any, key: int | None = None) -> int:
        """Queue ``fn(task)``; returns its key (``key``, or the next number)."""
        assert self._backend is not None, "submit inside 'with open_runner(...)'"
        key = self._next_key if key is None else key
        self._next_key = max(self._next_key, key + 1)
        self._backend.submit(fn, task, key)
        self._pending += 1
        return key

    def as_completed(self) -> Iterator[tuple[int, Any]]:
        assert self._backend is not None, "iterate inside 'with open_runner(...)'"
        while self._pending:
            key, result = self._backend.next_done()
            self._pending -= 1
            if self._bar is not None:
                text = self._describe(key, result) if self._describe is not None else ""
                self._bar.update(self._bar_task, advance=1, last=text)
            yield key, result


def open_runner(settings: ExecutorSettings, label: str = "tasks", total: int | None = None,
                describe: Callable[[int, Any], str] | None = None, console: Any = None,
                progress: bool = True) -> Runner:
    return Runner(settings, label, total, describe, console, progress)


def run_tasks(fn: Callable[[Any], Any], tasks: Iterable[Any], settings: ExecutorSettings, label: str = "tasks",
              describe: Callable[[int, Any], str] | None = None, console: Any = None,
              progress: bool = True) -> Iterator[tuple[int, Any]]:
    """Run ``fn(task)`` for every task; yields ``(index, result)`` as each completes."""
    tasks = list(tasks)
    with open_runner(settings, label, len(tasks), describe, console, progress) as runner:
        for i, task in enumerate(tasks):
            runner.submit(fn, task, i)
        yield from runner.as_completed()


def run_ordered(fn: Callable[[Any], Any], tasks: Iterable[Any], settings: ExecutorSettings, label: str = "tasks",
                describe: Callable[[int, Any], str] | None = None, console: Any = None,
                progress: bool = True) -> list[Any]:
    """``run_tasks``' results in task order, whatever order they completed in."""
    done = dict(run_tasks(fn, tasks, settings, label, describe, console, progress))
    return [done[i] for i in range(len(done))]


__all__ = ["ExecutorSettings", "KINDS", "RAY_MISSING", "Runner", "add_executor_arguments", "connect_ray", "open_runner",
           "run_ordered", "run_tasks"]
