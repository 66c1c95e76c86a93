"""A flight loop that never comes back, its motors stopped or off: end the process.

The radio's TX thread stops the motors of a loop that stalls in flight (backends/stale_setpoint.py).
If the loop's thread then never returns (a hung call, a deadlock), nothing else would end the
process: it would sit there, motors off, until SIGKILL, and the log would lack its footer.
``stall_exit`` watches from a thread of its own: once a radio has stopped the motors for a stall
(``RadioStats.stale_stops``) and the loop has not ticked for ``grace_s`` since, it

1. writes an error on ``/events`` saying so (at the last tick's flight time),
2. hands each radio back and closes the flight log (footer written, everything recorded so far
   kept), each bounded in time: the stuck thread may hold the log's lock or the radio,
3. prints one line to stderr and leaves with ``os._exit(EXIT_STATUS)``: the loop's thread cannot
   be joined, and a normal exit would wait for it.

The same when the loop hangs with the motors already off, so no stall stop ever comes: after
landing, before take-off, or in the loop's own teardown (every radio reports ``motors_off``: its
newest setpoint has no thrust, or it is stopped or handed back). Nothing flies, but nothing would
end the process either: once the loop has not ticked for ``idle_grace_s`` it leaves the same way.
This holds in lockstep too (a loop hung there blocks the simulator, and nothing flies).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from typing import Any, Callable, Iterator, Sequence

__all__ = ["EXIT_STATUS", "GRACE_S", "IDLE_GRACE_S", "LoopProgress", "stall_exit"]

# Both graces are read when ``stall_exit`` starts, so a test may lower them.
GRACE_S = 10.0  # wall seconds a loop gets to come back after its motors were stopped for it: far beyond a stall that ends
# Wall seconds a loop with every motor off may go without a tick: a loop ticks at its rate from start to
# end, so this only ever ends a hung one.
IDLE_GRACE_S = 10.0
CLOSE_S = 2.0  # wall seconds each of the hand-back and the log close may take before we leave anyway
EXIT_STATUS = 1  # the flight did not end as planned (as any other cut-short flight)
_POLL_S = 0.1


class LoopProgress:
    """A tick observer: when the loop last ticked (monotonic) and at which flight time."""

    def __init__(self) -> None:
        self.wall = time.monotonic()
        self.t = 0.0
        self.ticked = False  # a first tick may be slow (a cold solver): the motors-off exit waits for it

    def on_tick(self, info: Any) -> None:
        self.wall, self.t, self.ticked = time.monotonic(), float(info.t), True


@contextlib.contextmanager
def stall_exit(radios: Sequence[Any], log: Any, progress: LoopProgress, grace_s: float | None = None,
               leave: Callable[[int], None] = os._exit, idle_grace_s: float | None = None) -> Iterator[None]:
    """While the block runs, a thread watches for a loop gone for good after its radio stopped the
    motors (``grace_s``, default ``GRACE_S``), or with every motor already off (``idle_grace_s``, default
    ``IDLE_GRACE_S``);
    see the module docstring. ``log``: the flight log (``write``, ``close``, ``path``); ``leave``: how
    the process ends (``os._exit``; a test passes its own)."""
    done = threading.Event()
    graces = (GRACE_S if grace_s is None else grace_s, IDLE_GRACE_S if idle_grace_s is None else idle_grace_s)
    watcher = threading.Thread(target=_watch, args=(radios, log, progress, graces, leave, done),
                               name="stall-exit", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join(timeout=1.0)


def _stopped(radios: Sequence[Any]) -> bool:
    for radio in radios:
        with contextlib.suppress(Exception):  # a radio that cannot report has not stopped anything
            if radio.stats().stale_stops > 0:
                return True
    return False


def _all_off(radios: Sequence[Any]) -> bool:
    """Every radio sends zero thrust whatever the loop does (a radio that cannot say: not off)."""
    for radio in radios:
        try:
            if not getattr(radio.stats(), "motors_off", False):
                return False
        except Exception:  # noqa: BLE001
            return False
    return bool(radios)


def _watch(radios: Sequence[Any], log: Any, progress: LoopProgress, graces: tuple[float, float],
           leave: Callable[[int], None], done: threading.Event) -> None:
    grace_s, idle_grace_s = graces
    stopped_at: float | None = None
    while not done.wait(_POLL_S):
        now = time.monotonic()
        if stopped_at is None and _stopped(radios):
            stopped_at = now
        if stopped_at is not None:  # the stall's own stop: its grace counts from then
            if now - max(stopped_at, progress.wall) < grace_s:
                continue
            why = "the radio has stopped the motors"
        elif progress.ticked and now - progress.wall >= idle_grace_s and _all_off(radios):
            why = "the motors are off"
        else:
            continue
        if done.is_set():
            return  # the flight ended after all
        _leave(radios, log, progress, now - progress.wall, leave, why)
        return


def _bounded(action: Callable[[], Any], timeout: float) -> bool:
    """Run ``action`` on a thread of its own; whether it finished within ``timeout``."""
    worker = threading.Thread(target=_quiet, args=(action,), name="stall-exit-close", daemon=True)
    worker.start()
    worker.join(timeout)
    return not worker.is_alive()


def _quiet(action: Callable[[], Any]) -> None:
    try:
        action()
    except Exception:  # noqa: BLE001 - the process is leaving; what could not be closed is said below
        pass


def _leave(radios: Sequence[Any], log: Any, progress: LoopProgress, gone_s: float,
           leave: Callable[[int], None], why: str) -> None:
    text = (f"the flight loop has not come back {gone_s:.1f} s after its last tick, and {why}: the log is "
            "closed and the process exits")
    wrote = _bounded(lambda: log.write("/events", progress.t, {"level": "error", "text": text,
                                                                "source": "supervisor"}), CLOSE_S)
    for radio in radios:
        _bounded(radio.shutdown, CLOSE_S)
    closed = wrote and _bounded(log.close, CLOSE_S)
    where = f"log closed: {log.path}" if closed else f"the log could not be closed (kept as written): {log.path}"
    motors = "motors stopped by the radio" if "stopped" in why else "motors off"
    print(f"cfknode fly: the flight loop hung (no tick for {gone_s:.1f} s; {motors}); "
          f"{where}; exiting with status {EXIT_STATUS}", file=sys.stderr)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    leave(EXIT_STATUS)
