"""Exceptions from parts of a flight, described for the log and the user.

A part that raises in flight (the MPC, a model, an observer, the flight log, the simulator)
must not end the flight: the loop degrades and the supervisor lands or stops. What the user
and the log get is one ``PartError`` per distinct error (same part, type and raising line),
however many ticks it repeats on: one line for the terminal, the traceback for the log.
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass
from pathlib import Path

__all__ = ["PartError", "describe_error", "signal_stop_text"]

# How much of an exception's message a one-line description keeps.
_MAX_MESSAGE = 200


@dataclass(frozen=True)
class PartError:
    """One distinct error of one part of the flight."""

    part: str  # which part raised, as the user reads it ("the controller")
    kind: str  # the exception's type name
    message: str  # its message, on one line
    where: str  # "package/file.py:line" of the raising line ("" when unknown)
    traceback: str  # the full traceback text, for the log

    @property
    def key(self) -> tuple[str, str, str]:
        """What makes two errors the same: a repeat on every tick is one error."""
        return (self.part, self.kind, self.where)

    @property
    def line(self) -> str:
        """``internal error in <part>: <Type>: <message> (<where>)``."""
        text = f"internal error in {self.part}: {self.kind}"
        if self.message:
            text += f": {self.message}"
        return text + (f" ({self.where})" if self.where else "")


def describe_error(part: str, exc: BaseException) -> PartError:
    """``exc`` (raised by ``part``) as a ``PartError``; never raises itself."""
    try:
        message = " ".join(str(exc).split())
    except Exception:  # noqa: BLE001 - a broken __str__ must not hide the error
        message = "(unprintable message)"
    if len(message) > _MAX_MESSAGE:
        message = message[: _MAX_MESSAGE - 3] + "..."
    frames = traceback.extract_tb(exc.__traceback__)
    where = ""
    if frames:
        last = frames[-1]
        path = Path(last.filename)
        where = f"{path.parent.name}/{path.name}:{last.lineno}" if path.parent.name else f"{path.name}:{last.lineno}"
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    return PartError(part, type(exc).__name__, message, where, text)


def signal_stop_text(name: str) -> str:
    """How a stop signal reads in the outcome: Ctrl-C for SIGINT, the signal's name otherwise."""
    return {"SIGINT": "Ctrl-C (SIGINT)", "SIGHUP": "SIGHUP (terminal closed)"}.get(name, name)
