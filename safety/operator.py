"""Operator controls that reach a flight from outside the loop: Ctrl-C and ``cfknode estop``.

- SIGINT: installed with ``loop.add_signal_handler`` on the flight's own event loop, so the
  handler runs between ticks as an ordinary callback (never inside a tick), and the previous
  handler is put back when the flight ends. First Ctrl-C lands, the second stops the motors.
- The e-stop mailbox: a directory (``$XDG_RUNTIME_DIR/cfknode``, else the cache directory)
  where a flight announces itself with ``flight-<robot>.json`` and ``cfknode estop --robot NAME``
  drops ``estop-<robot>.json``. A small task on the flight's event loop looks for that file
  20 times a second, between ticks (a file-system call releases the GIL, and getting it back
  can cost a tick tens of microseconds), hands it to the supervisor and deletes it, which
  is the acknowledgement the command waits for. Files, not a socket: nothing to serve,
  nothing to clean up after a crash but two small files, which the next flight replaces.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

ACTIONS = ("stop", "land")
_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


class Interruptible(Protocol):
    def interrupt(self) -> None: ...


class Stoppable(Protocol):
    def request_land(self, reason: str, cause: str) -> None: ...

    def request_stop(self, reason: str, cause: str) -> None: ...


def mailbox_dir(configured: str = "") -> Path:
    """The e-stop mailbox directory: ``configured``, else ``$XDG_RUNTIME_DIR/cfknode``, else
    ``$XDG_CACHE_HOME/cfknode/estop`` (``~/.cache/cfknode/estop``)."""
    if configured:
        return Path(configured).expanduser()
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        return Path(runtime) / "cfknode"
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(cache) / "cfknode" / "estop"


class EstopMailbox:
    """The flight's side and the command's side of the e-stop files for one robot."""

    def __init__(self, directory: Path, robot: str) -> None:
        name = _SAFE.sub("_", robot).strip("._") or "robot"
        self.directory = Path(directory)
        self.robot = robot
        self.request_path = self.directory / f"estop-{name}.json"
        self.presence_path = self.directory / f"flight-{name}.json"

    # --- the flight's side -------------------------------------------------------------------

    def open(self) -> bool:
        """Announce the flight and drop a stale request; True if there was one."""
        self.directory.mkdir(parents=True, exist_ok=True)
        stale = self.request_path.exists()
        self.request_path.unlink(missing_ok=True)
        _write_atomic(self.presence_path, {"pid": os.getpid(), "robot": self.robot, "started": time.time()})
        return stale

    def poll(self) -> str | None:
        """The pending action ("stop" or "land"), consumed (the file is deleted), or None."""
        try:
            with open(self.request_path, "rb") as f:
                raw = f.read()
        except FileNotFoundError:
            return None
        self.request_path.unlink(missing_ok=True)
        try:
            action = json.loads(raw).get("action")
        except (ValueError, AttributeError):
            action = None
        # Anything unreadable is treated as the stronger action: it was meant as an e-stop.
        return action if action in ACTIONS else "stop"

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.presence_path.unlink(missing_ok=True)

    # --- the command's side ------------------------------------------------------------------

    def flight_pid(self) -> int | None:
        """The pid of the running flight of this robot, or None (no file, or its process is gone)."""
        try:
            pid = int(json.loads(self.presence_path.read_text())["pid"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return pid if _alive(pid) else None

    def post(self, action: str) -> None:
        """Leave ``action`` ("stop" or "land") for the flight, without waiting."""
        if action not in ACTIONS:
            raise ValueError(f"e-stop action must be one of {ACTIONS}, got {action!r}")
        self.directory.mkdir(parents=True, exist_ok=True)
        _write_atomic(self.request_path, {"action": action, "pid": os.getpid(), "time": time.time()})

    def request(self, action: str, timeout: float = 2.0, poll_s: float = 0.01) -> bool:
        """``post`` and wait until the flight takes it; False (and the request withdrawn) if
        nobody took it within ``timeout`` seconds."""
        self.post(action)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self.request_path.exists():
                return True
            time.sleep(poll_s)
        self.request_path.unlink(missing_ok=True)
        return False


@contextlib.contextmanager
def sigint_handler(target: Interruptible) -> Iterator[bool]:
    """Route SIGINT to ``target.interrupt()`` on the running event loop while the block runs.

    Yields whether the handler is installed (only the main thread may set signal handlers;
    elsewhere Ctrl-C keeps its previous meaning). The previous handler is restored on exit.
    """
    loop = asyncio.get_running_loop()
    previous: Callable[..., Any] | int | None = signal.getsignal(signal.SIGINT)
    try:
        loop.add_signal_handler(signal.SIGINT, target.interrupt)
    except (RuntimeError, ValueError, NotImplementedError):
        yield False
        return
    try:
        yield True
    finally:
        loop.remove_signal_handler(signal.SIGINT)
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def estop_watch(target: Stoppable, mailbox: EstopMailbox | None, period: float = 0.05) -> Iterator[None]:
    """While the block runs: the flight is announced in ``mailbox`` and a task on the running
    event loop hands each ``cfknode estop`` request to ``target``. Nothing without a mailbox."""
    if mailbox is None:
        yield
        return
    mailbox.open()
    task = asyncio.get_running_loop().create_task(_watch(target, mailbox, period))
    try:
        yield
    finally:
        task.cancel()
        mailbox.close()


async def _watch(target: Stoppable, mailbox: EstopMailbox, period: float) -> None:
    while True:
        await asyncio.sleep(period)
        action = mailbox.poll()
        if action is None:
            continue
        reason = f"cfknode estop --robot {mailbox.robot}" + (" --land" if action == "land" else "")
        if action == "land":
            target.request_land(reason, "estop_land")
        else:
            target.request_stop(reason, "estop_stop")


def _write_atomic(path: Path, payload: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(payload))
    os.replace(tmp, path)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True
