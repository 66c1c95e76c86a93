"""What keeps one failing part from ending a flight: a log whose writes never raise, observers
that detach themselves when they raise, and the geometric fallback computed without the MPC.

The flight loop (``loop.fly``) reports each failure to the supervisor
(``Supervisor.internal_error``), which logs it once with its traceback and lands or stops.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from cfknode.flight.controller import Command, Controller, TickInfo
from cfknode.flight.geometric import geometric_acc
from cfknode.flight.mellinger import acc_to_setpoint
from cfknode.kernel.reference import RefSamples

__all__ = ["GuardedLog", "GuardedObserver", "fallback_command", "hold_reference"]

ErrorSink = Callable[[str, BaseException], None]  # (part, exception)


class GuardedLog:
    """A flight log whose ``write`` never raises: a failing write is dropped and reported.

    ``report_to(sink)`` names where failures go (the supervisor, once the flight has one);
    before that they are only counted. A report that itself writes to this log (the error's
    own ``/events`` message) cannot recurse: writes during a report that fail are only counted.
    Other attributes (``path``, ``flush``) are the wrapped log's.
    """

    def __init__(self, log: Any) -> None:
        self._log = log
        self._sink: ErrorSink | None = None
        self._reporting = False
        self.failed_writes = 0

    def report_to(self, sink: ErrorSink | None) -> None:
        self._sink = sink

    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None:
        try:
            self._log.write(topic, t, msg)
        except Exception as exc:  # noqa: BLE001 - a log must never end a flight
            self.failed_writes += 1
            if self._sink is None or self._reporting:
                return
            self._reporting = True
            try:
                self._sink(f"the flight log ({topic})", exc)
            except Exception:  # noqa: BLE001 - the report is best effort
                pass
            finally:
                self._reporting = False

    def __getattr__(self, name: str) -> Any:
        return getattr(self._log, name)


class GuardedObserver:
    """A tick observer that detaches itself (and reports why) the first time it raises."""

    def __init__(self, observer: Any, sink: ErrorSink) -> None:
        self.observer = observer
        self.name = f"the tick observer {type(observer).__name__}"
        self._sink = sink
        self.detached = False

    def on_tick(self, tick: TickInfo) -> None:
        if self.detached:
            return
        try:
            self.observer.on_tick(tick)
        except Exception as exc:  # noqa: BLE001 - see the class docstring
            self.detached = True
            self._sink(f"{self.name} (detached)", exc)


def fallback_command(controller: Controller, state: Any, ref: RefSamples, status: str) -> Command:
    """The geometric fallback's command for ``ref``, without the MPC or the model (a part of
    those raised): the same law and Mellinger layer ``Controller`` falls back to."""
    acc = geometric_acc(state.p, state.v, ref.p[0], ref.v[0], ref.a[0], controller.gains)
    setpoint = acc_to_setpoint(acc, float(ref.yaw[0]), state.q, controller.vehicle, controller.settings)
    return Command(acc, setpoint, "fallback", status, 0.0, False)


def hold_reference(times: np.ndarray, position: np.ndarray) -> RefSamples:
    """Hold ``position`` at ``times`` (the trajectory raised; the supervisor's landing replaces it)."""
    n = len(times)
    zeros = np.zeros((n, 3))
    return RefSamples(np.asarray(times, dtype=float), np.tile(np.asarray(position, dtype=float), (n, 1)),
                      zeros, zeros.copy(), np.zeros(n))


def hand_back(shutdown: Callable[[], None], after: Callable[[], dict[str, Any]], sink: ErrorSink) -> dict[str, Any]:
    """Hand the drone back (``shutdown``) and read what the backend reports once it is
    (``after``, summary fields). An error in either goes to ``sink`` and is never raised, so
    the flight's summary is still written."""
    try:
        shutdown()
    except Exception as exc:  # noqa: BLE001 - see the docstring
        sink("the radio's hand-back", exc)
    try:
        return dict(after())
    except Exception as exc:  # noqa: BLE001
        sink("the backend's report after the hand-back", exc)
        return {}
