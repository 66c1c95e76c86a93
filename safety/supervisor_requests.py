"""The supervisor's inbox: operator requests, stop signals and internal errors.

Requests arrive from other threads or signal callbacks as atomic deque appends and take
effect at the supervisor's next tick; internal errors come from the loop's own thread.
``Supervisor`` owns the state these methods use (``_requests``, ``_interrupts``, ``_errors``).
"""

from __future__ import annotations

from collections import deque
from typing import Any

from cfknode.safety.part_errors import PartError, describe_error, signal_stop_text
from cfknode.safety.supervisor_types import _LAND, _NOTE, _STOP, ERROR_LAND, State

# A loop gone this long (the firmware's own level-out time, docs/hardware.md#commander-watchdog)
# has flown blind too long to carry on: the flight lands once it is back.
STALL_LAND_S = 0.5


class OperatorRequests:
    """Mixed into ``Supervisor``: the methods other threads and the loop's guards call."""

    _requests: deque[tuple[str, str, str, str]]
    _interrupts: list[str]
    _errors: dict[Any, PartError]
    _now: float
    _log: Any
    _radio: Any
    _state: State
    _landing_mode: str
    _landing: Any
    events: list[str]
    error_repeats: int
    # ``_event`` and ``_escalate`` are Supervisor's own.

    def request_land(self, reason: str = "operator e-stop key", cause: str = "operator_land") -> None:
        """Land as soon as possible (the dashboard's e-stop key)."""
        self._requests.append((_LAND, cause, reason, ""))

    def request_stop(self, reason: str = "operator stop", cause: str = "operator_stop") -> None:
        """Stop the motors at the next tick, wherever the drone is; a radio that guards its setpoint's
        age hears of it at once, and stops the motors itself if the loop has stalled."""
        self._requests.append((_STOP, cause, reason, ""))
        notify = getattr(self._radio, "operator_stop", None)
        if notify is not None:
            notify()

    def note(self, level: str, text: str, source: str = "supervisor") -> None:
        """An event from a part outside the loop (the e-stop mailbox), at the latest tick's time."""
        self._event(self._now, level, text, source=source)

    def interrupt(self, signal_name: str = "SIGINT") -> None:
        """A stop signal (SIGINT, SIGTERM, SIGHUP): the first lands, the second of any of them
        stops the motors. The cause is the signal's name in lower case (``sigterm``, then
        ``sigterm_stop``)."""
        self._interrupts.append(signal_name)
        text = signal_stop_text(signal_name)
        code = signal_name.lower()
        if len(self._interrupts) == 1:
            again = "Ctrl-C again" if signal_name == "SIGINT" else f"another {signal_name} (or Ctrl-C)"
            self._requests.append((_LAND, code, text, f"{again} stops the motors"))
        else:
            first = self._interrupts[0]
            said = f"second {text}" if first == signal_name else f"{text} after {signal_stop_text(first)}"
            self._requests.append((_STOP, f"{code}_stop", said, ""))
        # A stalled loop would take neither at its next tick: the radio hears of it at once.
        notify = getattr(self._radio, "stop_signal", None)
        if notify is not None:
            notify(len(self._interrupts))

    def loop_stalled(self, phase: str, age_s: float) -> None:
        """From the radio's TX thread, about a loop that stopped sending setpoints in flight:
        "hold" (the radio flies a level, descending hold: logged), "resumed" (the loop came back
        after ``age_s``: the flight lands if that was ``STALL_LAND_S`` or more), "stop" (the radio
        stopped the motors). All take effect at the loop's next tick, if it comes."""
        if phase == "hold":
            self._requests.append((_NOTE, "radio", f"the flight loop stalled (no setpoint for {age_s * 1e3:.0f} ms): "
                                   "the radio flies a level, descending hold until it is back", ""))
        elif phase == "resumed" and age_s >= STALL_LAND_S:
            self._requests.append((_LAND, "loop_stall", f"the flight loop stalled for {age_s:.2f} s", ""))
        elif phase == "stop":
            self._requests.append((_STOP, "loop_stall_stop",
                                   f"the flight loop stalled: the radio stopped the motors ({age_s:.2f} s without a "
                                   "setpoint, or a second stop signal during the stall)", ""))

    def internal_error(self, part: str, exc: BaseException, action: str = ERROR_LAND) -> PartError | None:
        """An exception from ``part`` of the flight, at the latest tick's time.

        The first of each distinct error goes on ``/events`` with its traceback; repeats are
        only counted. ``action``: ``ERROR_LAND`` lands (a supervised landing, even when the
        trajectory's own landing is under way, so a broken reference or controller does not
        decide where the drone sets down), ``ERROR_STOP`` stops the motors, ``ERROR_RECORD``
        only records it (a detached observer, a log write). Returns the new error, or None for
        a repeat. Called on the loop's thread only.
        """
        error = describe_error(part, exc)
        if error.key in self._errors:
            self.error_repeats += 1
            return None
        self._errors[error.key] = error
        now = self._now
        what = {_LAND: "landing", _STOP: "stopping the motors"}.get(action, "the flight goes on")
        self.events.append(f"{now:.3f} s error: {error.line}")
        self._log.write("/events", now, {"level": "error", "text": f"{error.line}: {what}", "source": "internal_error",
                                         "part": part, "traceback": error.traceback})
        if action == _STOP:
            self._escalate(now, _STOP, "internal_error", f"internal error in {part}", error.line)
        elif action == _LAND:
            if self._state is State.LAND and self._landing_mode == "nominal":
                self._landing_mode, self._landing = "supervised", None
            self._escalate(now, _LAND, "internal_error", f"internal error in {part}", error.line)
        return error

    @property
    def errors(self) -> tuple[PartError, ...]:
        """The distinct internal errors so far, oldest first."""
        return tuple(self._errors.values())
