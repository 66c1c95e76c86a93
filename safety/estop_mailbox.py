"""The e-stop mailbox: the directory through which ``cfknode estop`` reaches a running flight.

The directory (``$XDG_RUNTIME_DIR/cfknode``, else the cache directory) must belong to the user
and be writable by nobody else; it is created with mode 0700. It holds, per flight:

- ``flight-<robot>-<id>.json``: the flight's presence, written when it opens the mailbox and
  removed only by that flight. ``id`` is ``<pid>-<random hex>``; the file also holds the
  process's kernel start time, so a pid later reused by another process is not the flight.
  Listing all live flights is a scan of these files (``live_flights``).
- ``estop-<robot>-<id>.json``: a request ``{"action": "stop" | "land"}`` for that one flight,
  left by ``cfknode estop`` and deleted by the flight when taken, which is the acknowledgement.
- ``robot-<robot>.lock``: locked (``flock``) for the whole flight by a flight of a real robot,
  so a second flight of the same robot is refused. The kernel drops the lock when the process
  ends, however it ends; the empty file stays.

Files are written under a ``mkstemp`` name in the same directory and renamed into place, are
never opened through a symbolic link, and are opened non-blocking (a FIFO cannot hang a flight).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import secrets
import stat
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ACTIONS = ("stop", "land")
_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")
_ID = re.compile(r"^[0-9]+-[0-9a-f]{8}$")
_MAX_BYTES = 4096  # presence and request files are a few hundred bytes
_O_READ = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC


class MailboxError(Exception):
    """The mailbox cannot be used as asked; the message is one line for the user."""


class FlightRunning(MailboxError):
    """A live flight already flies this robot."""


class NoFlight(MailboxError):
    """No live flight matches the request."""


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


def safe_name(robot: str) -> str:
    """``robot`` as a file-name part (odd characters become ``_``)."""
    return _SAFE.sub("_", robot).strip("._") or "robot"


def check_dir(directory: Path, create: bool = True) -> Path:
    """``directory``, made with mode 0700 if missing (and ``create``); MailboxError unless it is
    a directory owned by this user that neither group nor others can write to."""
    directory = Path(directory)
    if create:
        try:
            directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            raise MailboxError(f"cannot create the e-stop mailbox {directory}: {_strerror(exc)}") from None
    try:
        st = os.stat(directory)
    except OSError as exc:
        raise MailboxError(f"cannot use the e-stop mailbox {directory}: {_strerror(exc)}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise MailboxError(f"the e-stop mailbox {directory} is not a directory")
    if st.st_uid != os.geteuid():
        raise MailboxError(f"the e-stop mailbox {directory} belongs to uid {st.st_uid}, not to you (uid "
                           f"{os.geteuid()}): anyone who owns it can fake or swallow an e-stop")
    # Sticky or not: whoever can create files here can plant a request, a fake flight or a lock.
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise MailboxError(f"the e-stop mailbox {directory} is writable by group or others "
                           f"(mode {stat.S_IMODE(st.st_mode):o}); make it private: chmod 700 {directory}")
    return directory


@dataclass(frozen=True)
class FlightInfo:
    """One flight as its presence file describes it."""

    directory: Path
    robot: str
    id: str  # "<pid>-<8 hex digits>", unique per flight
    pid: int
    started: float  # wall clock, seconds since the epoch
    proc_start: str  # the process's start time in clock ticks since boot ("" where unknown)

    @property
    def presence_path(self) -> Path:
        return self.directory / f"flight-{safe_name(self.robot)}-{self.id}.json"

    @property
    def request_path(self) -> Path:
        return self.directory / f"estop-{safe_name(self.robot)}-{self.id}.json"

    def alive(self) -> bool:
        """The process that wrote the presence file still runs (and is not a reused pid)."""
        if not _pid_alive(self.pid):
            return False
        now = _proc_start(self.pid)
        return not (self.proc_start and now) or now == self.proc_start

    def describe(self) -> str:
        started = time.strftime("%H:%M:%S", time.localtime(self.started))
        return f"{self.robot!r} (pid {self.pid}, flight id {self.id}, started {started})"

    def to_json(self) -> dict[str, Any]:
        return {"robot": self.robot, "id": self.id, "pid": self.pid, "started": self.started,
                "proc_start": self.proc_start, "request": self.request_path.name}

    @classmethod
    def from_json(cls, directory: Path, d: Any) -> FlightInfo:
        """Raises ValueError for anything but a well-formed presence record."""
        if not isinstance(d, dict):
            raise ValueError("not a JSON object")
        robot, flight_id, pid = d.get("robot"), d.get("id"), d.get("pid")
        if not isinstance(robot, str) or not isinstance(flight_id, str) or not _ID.match(flight_id):
            raise ValueError("no valid robot or id")
        if not isinstance(pid, int) or pid <= 0 or flight_id.split("-")[0] != str(pid):
            raise ValueError("no valid pid")
        return cls(Path(directory), robot, flight_id, pid, float(d.get("started", 0.0)), str(d.get("proc_start", "")))


def live_flights(directory: Path) -> list[FlightInfo]:
    """Every live flight announced in ``directory``, oldest first. Unreadable, foreign-looking
    and dead flights' files are skipped (and left where they are: only a flight removes its own)."""
    try:
        names = sorted(os.listdir(directory))
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise MailboxError(f"cannot list the e-stop mailbox {directory}: {_strerror(exc)}") from None
    flights = []
    for name in names:
        if not (name.startswith("flight-") and name.endswith(".json")):
            continue
        try:
            info = FlightInfo.from_json(Path(directory), json.loads(_read_small(Path(directory) / name)))
        except (OSError, ValueError, MailboxError):
            continue
        if info.presence_path.name == name and info.alive():
            flights.append(info)
    return sorted(flights, key=lambda f: f.started)


def find_flight(directory: Path, robot: str | None = None, flight_id: str | None = None) -> FlightInfo:
    """The one live flight with that robot name and/or id (both None: the only live flight).
    NoFlight when there is none; MailboxError, listing them, when several match."""
    if Path(directory).exists():
        check_dir(directory, create=False)  # a planted or shared directory could fake a flight
    flights = [f for f in live_flights(directory)
               if (robot is None or f.robot == robot) and (flight_id is None or f.id == flight_id)]
    what = " ".join(filter(None, [f"of {robot!r}" if robot else "", f"with id {flight_id}" if flight_id else ""]))
    if not flights:
        raise NoFlight(f"no flight {what + ' ' if what else ''}is running (mailbox {directory})")
    if len(flights) > 1:
        listed = "; ".join(f.describe() for f in flights)
        raise MailboxError(f"{len(flights)} flights {what + ' ' if what else ''}are running: {listed}; "
                           "choose one with --robot NAME or --id ID")
    return flights[0]


@dataclass(frozen=True)
class Request:
    action: str  # "stop" or "land"
    note: str = ""  # why a request was read as something it did not say ("" when it was clear)


class EstopMailbox:
    """The flight's side of the mailbox: its presence, its request file, its robot lock.

    ``exclusive``: a flight of a real robot, which takes the robot's lock (a second flight of
    the same robot is refused). Simulated flights are not exclusive: benches fly many at once.
    """

    def __init__(self, directory: Path, robot: str, exclusive: bool = False) -> None:
        self.directory = Path(directory)
        self.robot = robot
        self.exclusive = exclusive
        pid = os.getpid()
        self.info = FlightInfo(self.directory, robot, f"{pid}-{secrets.token_hex(4)}", pid, time.time(),
                               _proc_start(pid))
        self._lock_fd: int | None = None
        self._open = False

    @property
    def id(self) -> str:
        return self.info.id

    @property
    def request_path(self) -> Path:
        return self.info.request_path

    @property
    def presence_path(self) -> Path:
        return self.info.presence_path

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        """Announce the flight (once). MailboxError for an unusable directory, FlightRunning when
        an exclusive flight's robot already flies."""
        if self._open:
            return
        check_dir(self.directory)
        if self.exclusive:
            self._lock()
        try:
            same = [f for f in live_flights(self.directory) if f.robot == self.robot] if self.exclusive else []
            if same:  # the lock file was removed under a live flight
                raise FlightRunning(f"{same[0].describe()} is already flying; a second flight of the same "
                                    "robot is refused")
            _write_atomic(self.presence_path, self.info.to_json())
        except BaseException:
            self._unlock()
            raise
        self._open = True

    def poll(self) -> Request | None:
        """The request waiting for this flight, consumed (deleted), or None.

        Raises OSError or MailboxError when the request path holds something that is not a
        request file (a directory, a symbolic link, a FIFO; left alone) or cannot be taken. A
        request file that is taken but cannot be read or parsed is a stop, with a ``note``.
        """
        path = self.request_path
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            return None
        if not stat.S_ISREG(st.st_mode):
            raise MailboxError(f"{path} is {_kind(st.st_mode)}, not a request file: ignored")
        # Renamed first, so a request posted while this one is read lands beside it, not lost.
        taken = self.directory / f".taken-{path.name}"
        try:
            os.rename(path, taken)
        except FileNotFoundError:
            return None  # withdrawn by the command that posted it
        # A file at this flight's request path was meant as an e-stop: whatever cannot be read
        # from it is taken as the stronger action.
        try:
            raw = _read_small(taken)
        except (OSError, MailboxError) as exc:
            return Request("stop", f"unreadable e-stop request ({describe_error(exc)}) taken as stop")
        finally:
            with contextlib.suppress(OSError):
                os.unlink(taken)
        try:
            action = json.loads(raw).get("action")
        except (ValueError, AttributeError):
            action = None
        if action in ACTIONS:
            return Request(action)
        return Request("stop", f"unreadable e-stop request {raw[:60]!r} taken as stop")

    def close(self) -> None:
        """Withdraw the presence (only this flight's own file) and release the robot."""
        if not self._open:
            return
        self._open = False
        with contextlib.suppress(OSError, ValueError, MailboxError):
            mine = FlightInfo.from_json(self.directory, json.loads(_read_small(self.presence_path)))
            if mine.id == self.id:
                os.unlink(self.presence_path)
        with contextlib.suppress(OSError):
            if stat.S_ISREG(os.lstat(self.request_path).st_mode):
                os.unlink(self.request_path)  # addressed to this flight only: nobody else will take it
        self._unlock()

    def _lock(self) -> None:
        lock_path = self.directory / f"robot-{safe_name(self.robot)}.lock"
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise MailboxError(f"cannot open the robot lock {lock_path}: {_strerror(exc)}") from None
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise MailboxError(f"the robot lock {lock_path} is not a regular file")
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            holders = [f for f in live_flights(self.directory) if f.robot == self.robot]
            who = holders[0].describe() if holders else f"{self.robot!r} (another process holds {lock_path})"
            raise FlightRunning(f"{who} is already flying; a second flight of the same robot is refused") from None
        except BaseException:
            os.close(fd)
            raise
        self._lock_fd = fd

    def _unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock; the file stays for the next flight
            self._lock_fd = None


# --- the command's side ---------------------------------------------------------------------


def post(flight: FlightInfo, action: str) -> int:
    """Leave ``action`` for ``flight`` without waiting; returns the request file's inode."""
    if action not in ACTIONS:
        raise ValueError(f"e-stop action must be one of {ACTIONS}, got {action!r}")
    return _write_atomic(flight.request_path, {"action": action, "id": flight.id, "pid": os.getpid(),
                                               "time": time.time()})


def request(flight: FlightInfo, action: str, timeout: float = 2.0, poll_s: float = 0.01) -> bool:
    """``post`` and wait until the flight takes it; False (and the request withdrawn) if it
    did not within ``timeout`` seconds or its process ended."""
    inode = post(flight, action)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            st = os.lstat(flight.request_path)
        except FileNotFoundError:
            return True
        if st.st_ino != inode or not flight.alive():
            break
        time.sleep(poll_s)
    with contextlib.suppress(OSError):
        if os.lstat(flight.request_path).st_ino == inode:  # withdraw our own request only
            os.unlink(flight.request_path)
    return False


# --- files ----------------------------------------------------------------------------------


def _write_atomic(path: Path, payload: dict[str, Any]) -> int:
    """Write ``payload`` under an unpredictable name beside ``path`` (mode 0600) and rename it
    over ``path``: a symbolic link there is replaced, never followed. Returns the inode."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise MailboxError(f"cannot write in the e-stop mailbox {path.parent}: {_strerror(exc)}") from None
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(payload, f)
            inode = os.fstat(f.fileno()).st_ino
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise MailboxError(f"cannot write {path}: {_strerror(exc)}") from None
        raise
    return inode


def _read_small(path: Path) -> bytes:
    """A small regular file's bytes, not through a symbolic link and without blocking."""
    fd = os.open(path, _O_READ)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise MailboxError(f"{path} is {_kind(mode)}, not a regular file")
        data = os.read(fd, _MAX_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > _MAX_BYTES:
        raise MailboxError(f"{path} is larger than {_MAX_BYTES} bytes")
    return data


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _strerror(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True


def _proc_start(pid: int) -> str:
    """The process's start time in clock ticks since boot (Linux ``/proc``), "" elsewhere."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return fields[19].decode()  # field 22 of the line; fields[0] here is field 3
    except (OSError, IndexError):
        return ""


def describe_error(exc: BaseException) -> str:
    """A short stable description of ``exc`` (for logging each distinct error once)."""
    if isinstance(exc, OSError):
        code = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{_strerror(exc)} [{code}]{where}"
    return f"{exc}" if isinstance(exc, MailboxError) else f"{type(exc).__name__}: {exc}"
