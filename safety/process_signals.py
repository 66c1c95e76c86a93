"""Stop signals for a whole ``cfknode fly`` process, around the flight loop's own handlers.

While the loop runs, ``operator.stop_signal_handler`` owns SIGINT, SIGTERM and SIGHUP (the
first lands, the second stops the motors). Around it this context covers the rest of the
process's life, so no stop signal kills it with the radio open, the firmware not handed
back or the log without its summary:

- before the flight has a supervisor (compiling the MPC, starting the trainer, connecting):
  SIGTERM and SIGHUP raise ``StopSignal`` (a ``KeyboardInterrupt``) as Ctrl-C does, so
  nothing takes off and everything opened so far is closed on the way out. Native code that
  calls back into Python (CasADi building the MPC) can swallow that exception: a signal the
  process went on after is handed to the target when ``route`` is called, so it still refuses
  the take-off;
- once ``route(target)`` has been called (with the supervisor, just before take-off): every
  stop signal goes to ``target.interrupt(name)``. Before the loop's first tick that refuses
  the take-off; after its last tick (the hand-back, the summary) the flight is already ending
  and the signal only counts. A third routed signal raises ``StopSignal``: a way out
  of a hand-back that hangs.

The previous handlers are restored on exit. Outside the main thread nothing is installed.
"""

from __future__ import annotations

import signal
import sys
import threading
from types import FrameType, TracebackType
from typing import Any, Protocol

from cfknode.safety.operator import STOP_SIGNALS

__all__ = ["ProcessSignals", "StopSignal"]

# Routed signals after which another one leaves at once.
ROUTED_BEFORE_EXIT = 2


class StopSignal(KeyboardInterrupt):
    """A stop signal that ends the process before (or, the third, after) the flight: it
    unwinds like Ctrl-C's ``KeyboardInterrupt``; ``signum`` says which signal it was."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class Interruptible(Protocol):
    def interrupt(self, signal_name: str) -> None: ...


class ProcessSignals:
    """A context manager; see the module docstring."""

    def __init__(self, signals: tuple[signal.Signals, ...] = STOP_SIGNALS) -> None:
        self._signals = signals
        self._previous: dict[signal.Signals, Any] = {}
        self._target: Interruptible | None = None
        self._routed = 0
        self._unwound: list[str] = []  # raised as StopSignal before there was a target
        self.received: list[str] = []  # every stop signal this context handled, by name
        self._unraisable: Any = None  # the hook to restore (``_quiet_swallowed``)

    def route(self, target: Interruptible) -> None:
        """From now on stop signals go to ``target`` (a ``Supervisor``); one raised before that
        which did not end the process (swallowed on the way) goes to it now."""
        self._target = target
        for name in self._unwound[:ROUTED_BEFORE_EXIT]:
            self._routed += 1
            target.interrupt(name)
        self._unwound.clear()

    def __enter__(self) -> "ProcessSignals":
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig in self._signals:
            self._previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self._handle)
        self._unraisable, sys.unraisablehook = sys.unraisablehook, self._quiet_swallowed
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()
        if self._unraisable is not None:
            sys.unraisablehook, self._unraisable = self._unraisable, None

    def _quiet_swallowed(self, unraisable: Any) -> None:
        """A StopSignal raised where Python cannot propagate it (a weakref callback inside an import, say) is
        swallowed there, printing a traceback; ``route`` hands it to the supervisor, so only others are printed."""
        if isinstance(unraisable.exc_value, StopSignal):
            return
        (self._unraisable or sys.__unraisablehook__)(unraisable)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        # A Python-level handler: it runs on the main thread between bytecodes, so it only
        # appends to the target's request queue and never writes the log (whose lock the
        # interrupted code may hold).
        name = signal.Signals(signum).name
        self.received.append(name)
        target = self._target
        if target is None:
            self._unwound.append(name)
            raise StopSignal(signum)
        self._routed += 1
        if self._routed > ROUTED_BEFORE_EXIT:
            raise StopSignal(signum)
        target.interrupt(name)
