"""The flight side of the trainer process: start it, send requests, receive results, detect crashes and hangs.

No torch here: the child runs ``cfknode.models.trainer_process.trainer_main``, and only numpy
windows and ``ModelFile``s cross the pipe.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import sys
import time
from dataclasses import dataclass
from multiprocessing import resource_tracker
from typing import Any, Callable

from cfknode.models.trainer_process import (
    CHILD_IMPORTS,
    IGNORED_SIGNALS,
    Job,
    JobOutcome,
    TrainerReady,
    TrainerSettings,
    TrainOutcome,
    TrainRequest,
    trainer_main,
)

# An idle trainer sends nothing until it is asked, but its death (an EOF): a poll that may not wait reads the pipe
# only every this many calls while idle (0.1 s of a 400 Hz loop). Each read is a system call that cost a real-time
# flight's thread 25-35 us a tick (docs/results.md); a dead trainer is still found then, or at the next send.
IDLE_READ_EVERY = 40


@dataclass(frozen=True)
class TrainerFault:
    kind: str  # "crash" | "hang"
    reason: str


class TrainerClient:
    """The trainer child process: start, requests, results, crash and hang detection, restarts.

    States: ``starting`` (started, warming up), ``idle``, ``busy`` (one request out),
    ``stopped``. Nothing here blocks unless asked to (``wait_ready``, ``poll(timeout)``).
    Between rounds it also runs the flight side's numpy ``Job``s (``submit_job``).
    """

    runs_jobs = True  # a learner may hand it the gate (a shared trainer's ports do not: their queue is rounds)

    def __init__(
        self,
        settings: TrainerSettings,
        timeout: float,
        start_timeout: float = 120.0,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.settings = settings
        self.timeout = timeout
        self.start_timeout = start_timeout
        self._wall = wall
        self._ctx = trainer_context(settings.preload)
        self._proc: Any = None
        self._conn: Any = None
        self._dead: list[Any] = []  # killed processes not yet reaped
        self.state = "stopped"
        self.sent_wall = math.nan  # wall time the outstanding request was sent
        self.start_wall = math.nan  # wall time of the last start
        self.starts = 0
        self.pid: int | None = None
        self.warmup_s = math.nan
        self.ready: TrainerReady | None = None  # the running trainer's report: its niceness and threads
        self.start_problem = ""  # why the last wait_ready failed, one line
        self.tagged = False  # a shared trainer's protocol (trainer_main's ``tagged``)
        self._idle_polls = 0  # polls since the pipe was last read while idle (IDLE_READ_EVERY)

    def start(self) -> None:
        """Start a trainer (non-blocking: it reports ``TrainerReady`` when torch is up)."""
        self._reap()
        parent, child = self._ctx.Pipe(duplex=True)
        # The child inherits this thread's signal mask: with the stop signals blocked it cannot
        # die of a Ctrl-C meant for the flight before ``trainer_main`` ignores them. The parent
        # loses none: blocked here, they wait (or reach another thread) and are handled as usual.
        # The resource tracker first: starting it unblocks SIGINT and SIGTERM on this thread. A fork
        # server started here keeps the mask too, and so does every trainer forked from it.
        resource_tracker.ensure_running()
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, IGNORED_SIGNALS)
        try:
            try:
                proc = self._launch(child)
            except OSError:
                if self._ctx.get_start_method() != "forkserver":
                    raise
                # No fork server here (its socket or process could not be made): spawn, as elsewhere.
                self._ctx = multiprocessing.get_context("spawn")
                proc = self._launch(child)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        child.close()  # only the child holds it now, so its death reads as EOF here
        self._proc, self._conn = proc, parent
        self.pid = proc.pid
        self.state = "starting"
        self.start_wall = self._wall()
        self.starts += 1

    def _launch(self, child: Any) -> Any:
        proc = self._ctx.Process(target=trainer_main, args=(child, self.settings, self.tagged), name="cfknode-trainer",
                                 daemon=True)
        proc.start()
        return proc

    def wait_ready(self, timeout: float) -> bool:
        """Block until the trainer is up (pre-flight); False on timeout or failure, with
        ``start_problem`` saying which in one line."""
        deadline = self._wall() + timeout
        self.start_problem = ""
        while self.state == "starting":
            left = deadline - self._wall()
            if left <= 0:
                self.start_problem = f"the online trainer did not start within {timeout:g} s"
                return False
            event = self.poll(min(left, 0.5))
            if isinstance(event, TrainerFault):
                self.start_problem = _start_failure(event)
                return False
        return self.state == "idle"

    @property
    def busy(self) -> bool:
        return self.state == "busy"

    def submit(self, request: TrainRequest) -> None:
        if self.state != "idle":
            raise RuntimeError(f"trainer is {self.state}, not idle")
        # Clock first: the child may start training before send() returns on a busy machine.
        self.sent_wall = self._wall()
        self._send(request)
        self.state = "busy"

    def submit_job(self, job: Job) -> None:
        """Hand the idle trainer numpy work (``Job``); its ``JobOutcome`` comes through ``poll`` like a
        round's result, with the same hang deadline."""
        self.submit(job)  # type: ignore[arg-type]

    def _send(self, message: Any) -> None:
        """Send to the child. A child killed while idle breaks the pipe: the request is lost, and
        the next ``poll`` reads the EOF and reports the crash, as for a child killed mid-round."""
        try:
            self._conn.send(message)
        except OSError:
            pass

    def poll(self, timeout: float = 0.0) -> TrainOutcome | JobOutcome | TrainerReady | TrainerFault | None:
        """The trainer's next message, or a fault; waits up to ``timeout`` s (0: never blocks; while idle it reads
        the pipe only every ``IDLE_READ_EVERY``-th such call)."""
        if self.state in ("stopped",):
            return None
        if self.state == "idle" and timeout <= 0.0:
            self._idle_polls += 1
            if self._idle_polls < IDLE_READ_EVERY:
                return None
        self._idle_polls = 0
        deadline = self._deadline()
        if deadline is not None:
            timeout = min(timeout, max(0.0, deadline - self._wall()))  # never wait past the hang deadline
        try:
            ready = self._conn.poll(timeout) if timeout > 0 else self._conn.poll()
            message = self._conn.recv() if ready else None
        except (EOFError, OSError):
            code = self._proc.exitcode if self._proc is not None else None
            if code is None:
                self._proc.join(0.05)
                code = self._proc.exitcode
            self._discard_process(kill=True)
            return TrainerFault("crash", f"trainer process exited (code {code})")
        if message is None:
            if deadline is not None and self._wall() >= deadline:
                what = (f"no result within online.trainer_timeout = {self.timeout:g} s" if self.state == "busy"
                        else f"not up within {self.start_timeout:g} s of starting")
                self._discard_process(kill=True)
                return TrainerFault("hang", f"{what}; killed")
            return None
        if isinstance(message, TrainerReady):
            self.state = "idle"
            self.warmup_s = message.warmup_s
            self.ready = message
        elif isinstance(message, (TrainOutcome, JobOutcome)):
            self.state = "idle"
        return message

    def _deadline(self) -> float | None:
        if self.state == "busy":
            return self.sent_wall + self.timeout
        if self.state == "starting":
            return self.start_wall + self.start_timeout
        return None

    def kill(self) -> None:
        """Kill the trainer at once (fault injection): the next ``poll`` reports the crash, or while idle the next
        that reads the pipe (``IDLE_READ_EVERY``), or the next send."""
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()

    def close(self, timeout: float = 2.0) -> None:
        """Ask the trainer to stop; kill it if it does not within ``timeout``."""
        if self._proc is not None:
            try:
                if self.state in ("idle", "starting"):
                    self._conn.send(None)
            except (OSError, ValueError):
                pass
            if self.state == "idle":
                self._proc.join(timeout)
            self._discard_process(kill=True)
        self._reap(timeout)
        self.state = "stopped"

    def _discard_process(self, kill: bool) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self.state = "stopped"
        if conn is not None:
            conn.close()
        if proc is not None:
            if kill and proc.is_alive():
                proc.kill()
            self._dead.append(proc)
        self._reap()

    def _reap(self, timeout: float = 0.0) -> None:
        alive = []
        for proc in self._dead:
            proc.join(timeout)
            if proc.exitcode is None:
                alive.append(proc)
            else:
                proc.close()
        self._dead = alive


def trainer_context(preload: tuple[str, ...] = ()) -> Any:
    """How trainers start: on Linux forked from one server process that imported torch and the trainer's
    modules once (``CHILD_IMPORTS`` and ``preload``), so every trainer after the process's first is ready
    in a fraction of a second instead of about 3 s of imports (a restart after a fault, a script's next
    flight, a bench's next task); elsewhere spawned. The server holds imports only, no state of any
    flight, and ends with this process. It has one thread, so forking from it is safe; it is Python's
    default start method on Linux from 3.14 on."""
    if not sys.platform.startswith("linux"):
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    # Read when the server starts (the process's first trainer, or the next after a server that died).
    ctx.set_forkserver_preload([*CHILD_IMPORTS, *preload])
    return ctx


def refuse_in_spawned_import() -> None:
    """Fail fast inside a spawned child that is re-importing an unguarded calling script.

    Spawning re-runs the calling script's top level in the child; without an
    ``if __name__ == "__main__":`` guard that would start a flight there. Raising at once
    ends the child within a second, and the parent reports why.
    """
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise RuntimeError("cfknode flight started while a child process imports its parent's script "
                           "(guard the script's entry point with `if __name__ == \"__main__\":`)")


def _start_failure(fault: TrainerFault) -> str:
    """One line for a trainer that died while starting: usually an unguarded calling script."""
    if fault.kind != "crash":
        return f"the online trainer could not start: {fault.reason}"
    if script := _unreadable_main():
        return (f"the online trainer could not start ({fault.reason}): the trainer process re-imports the calling "
                f"script, and {script} is not a file; run it from a file")
    return (f"the online trainer could not start ({fault.reason}): a script that learns online must run "
            "its flight under `if __name__ == \"__main__\":`, because the trainer process re-imports it")


def _unreadable_main() -> str:
    """The calling script's name when a child process cannot re-import it (``python -`` reads it from
    stdin: multiprocessing looks for a file ``<stdin>``); "" otherwise."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if path is None or getattr(main, "__spec__", None) is not None or os.path.isfile(path):
        return ""
    return path


__all__ = ["TrainerClient", "TrainerFault", "refuse_in_spawned_import", "trainer_context"]
