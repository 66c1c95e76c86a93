"""The e-stop mailbox: the directory through which ``cfknode estop`` reaches a running flight.

The directory (``$XDG_RUNTIME_DIR/cfknode``, else the cache directory) must belong to the user
and be writable by nobody else; it is created with mode 0700, and a flight makes an existing
one that others can read private. It holds, per flight:

- ``flight-<robot>-<id>.json``: the flight's presence, written when it opens the mailbox and
  removed only by that flight. ``id`` is ``<pid>-<random hex>``; the file also holds the
  process's kernel start time, so a pid later reused by another process is not the flight.
  Listing all live flights is a scan of these files (``scan_flights``); one that cannot be
  parsed, or that another user owns, is skipped and reported, never taken as a flight.
- ``estop-<robot>-<id>.json``: a request ``{"action": "stop" | "land"}`` for that one flight,
  left by ``cfknode estop`` and deleted by the flight when taken, which is the acknowledgement.
  Where something that cannot be replaced (a directory) blocks that path, the command writes
  ``estop-<robot>-<id>.<8 hex>.json`` instead, and the flight looks for those while blocked.
  A request that cannot be read or parsed is taken as a stop.
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
import math
import os
import re
import secrets
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cfknode.kernel.bounded_input import quote
from cfknode.safety.estop_files import MailboxError, parse_json, read_small, write_atomic
from cfknode.safety.estop_files import kind as _kind
from cfknode.safety.estop_files import pid_alive as _pid_alive
from cfknode.safety.estop_files import proc_start as _proc_start

ACTIONS = ("stop", "land")
_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")
_ID = re.compile(r"^[0-9]+-[0-9a-f]{8}$")
_ALT = re.compile(r"^[0-9a-f]{8}$")
# Without an obstacle at the request path, the flight looks for written-around requests this
# seldom (in polls): a listing costs more than the one lstat of an ordinary poll.
_ALT_SCAN_EVERY = 20


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
    a directory owned by this user that neither group nor others can write to. One that others
    can only read or enter is made private (chmod 700) when ``create`` (the flight's side)."""
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
    if create and st.st_mode & 0o077:  # readable only: nothing planted, so tightening is safe
        try:
            os.chmod(directory, 0o700)
        except OSError as exc:
            raise MailboxError(f"the e-stop mailbox {directory} has mode {stat.S_IMODE(st.st_mode):o} and cannot "
                               f"be made private ({_strerror(exc)}): chmod 700 {directory}") from None
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
        if not isinstance(robot, str) or not robot or len(robot) > 200:
            raise ValueError("no valid robot name")
        if not isinstance(flight_id, str) or not _ID.match(flight_id):
            raise ValueError("no valid flight id")
        if isinstance(pid, bool) or not isinstance(pid, int) or not 0 < pid < 1 << 31 or flight_id.split("-")[0] != str(pid):
            raise ValueError("no valid pid")
        started, proc_start = d.get("started", 0.0), d.get("proc_start", "")
        if isinstance(started, bool) or not isinstance(started, (int, float)) or not math.isfinite(started):
            raise ValueError(f"'started' is {quote(started)}, not a time")
        if not isinstance(proc_start, str) or not (proc_start == "" or proc_start.isdigit()):
            raise ValueError(f"'proc_start' is {quote(proc_start)}, not a start time")
        return cls(Path(directory), robot, flight_id, pid, float(started), proc_start)


@dataclass(frozen=True)
class FlightScan:
    """The live flights in a mailbox, and one line for each presence file that was skipped."""

    flights: tuple[FlightInfo, ...]
    skipped: tuple[str, ...]  # "<file>: <why>", for files that are not a usable presence


def scan_flights(directory: Path) -> FlightScan:
    """Every live flight announced in ``directory``, oldest first. A presence file that cannot
    be read or parsed for any reason, or that another user owns, is skipped and reported;
    dead flights' files are passed over. Nothing is removed: only a flight removes its own."""
    try:
        names = sorted(os.listdir(directory))
    except FileNotFoundError:
        return FlightScan((), ())
    except OSError as exc:
        raise MailboxError(f"cannot list the e-stop mailbox {directory}: {_strerror(exc)}") from None
    flights, skipped = [], []
    for name in names:
        if not (name.startswith("flight-") and name.endswith(".json")):
            continue
        try:
            data = parse_json(read_small(Path(directory) / name, owner_only=True), Path(name))
            info = FlightInfo.from_json(Path(directory), data)
            if info.presence_path.name != name:
                raise ValueError(f"it names {info.presence_path.name}")
            alive = info.alive()
        except FileNotFoundError:
            continue  # removed by its flight while listed
        except Exception as exc:  # noqa: BLE001 - no file may keep an e-stop from the other flights
            skipped.append(f"{quote(name)[1:-1]}: {describe_error(exc)[:160]}")
            continue
        if alive:
            flights.append(info)
    return FlightScan(tuple(sorted(flights, key=lambda f: f.started)), tuple(skipped))


def live_flights(directory: Path) -> list[FlightInfo]:
    """Every live flight announced in ``directory``, oldest first (``scan_flights`` without the report)."""
    return list(scan_flights(directory).flights)


def find_flight(directory: Path, robot: str | None = None, flight_id: str | None = None,
                scan: FlightScan | None = None) -> FlightInfo:
    """The one live flight with that robot name and/or id (both None: the only live flight).
    NoFlight when there is none; MailboxError, listing them, when several match. ``scan``:
    one already made (the command reports what it skipped)."""
    if Path(directory).exists():
        check_dir(directory, create=False)  # a planted or shared directory could fake a flight
    found = scan.flights if scan is not None else live_flights(directory)
    flights = [f for f in found if (robot is None or f.robot == robot) and (flight_id is None or f.id == flight_id)]
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
        self._polls = 0

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
            _write(self.presence_path, self.info.to_json())
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
        self._polls += 1
        path = self.request_path
        try:
            st: os.stat_result | None = os.lstat(path)
        except FileNotFoundError:
            st = None
        if st is not None and stat.S_ISREG(st.st_mode):
            return self._take(path)
        blocked = None if st is None else f"{path} is {_kind(st.st_mode)}, not a request file: ignored"
        # A command that found the request path blocked wrote around it (``post``): look for
        # that at once when it is blocked, and now and then in case the obstacle went away since.
        if blocked is not None or self._polls % _ALT_SCAN_EVERY == 0:
            for alternate in self._alternates():
                got = self._take(alternate)
                if got is not None:
                    return got if got.note or blocked is None else Request(got.action, f"{blocked}; {got.action} "
                                                                                       f"taken from {alternate.name}")
        if blocked is not None:
            raise MailboxError(blocked)
        return None

    def _alternates(self) -> list[Path]:
        """This flight's written-around requests, ``estop-<robot>-<id>.<8 hex>.json``, oldest name first."""
        stem = self.request_path.name[: -len(".json")] + "."
        try:
            names = os.listdir(self.directory)
        except FileNotFoundError:
            return []
        picked = [n for n in names if n.startswith(stem) and n.endswith(".json") and _ALT.match(n[len(stem):-5])]
        return [self.directory / n for n in sorted(picked)]

    def _take(self, path: Path) -> Request | None:
        """The request at ``path`` (a regular file when listed), consumed; None if it is gone."""
        # Renamed first, so a request posted while this one is read lands beside it, not lost;
        # under a unique name, so nothing planted at a fixed name can block the taking.
        taken = self.directory / f".taken-{path.name}.{secrets.token_hex(4)}"
        try:
            os.rename(path, taken)
        except FileNotFoundError:
            return None  # withdrawn by the command that posted it
        # A file at this flight's request path was meant as an e-stop: whatever cannot be read
        # from it is taken as the stronger action.
        try:
            raw = _read_small(taken)
        except Exception as exc:  # noqa: BLE001 - see above
            return Request("stop", f"unreadable e-stop request ({describe_error(exc)[:160]}) taken as stop")
        finally:
            with contextlib.suppress(OSError):
                os.unlink(taken)
        try:
            data = parse_json(raw, path)
            action = data.get("action") if isinstance(data, dict) else None
        except MailboxError:
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
            mine = FlightInfo.from_json(self.directory, parse_json(_read_small(self.presence_path), self.presence_path))
            if mine.id == self.id:
                os.unlink(self.presence_path)
        for request_path in (self.request_path, *self._alternates()):
            with contextlib.suppress(OSError):
                if stat.S_ISREG(os.lstat(request_path).st_mode):
                    os.unlink(request_path)  # addressed to this flight only: nobody else will take it
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


@dataclass(frozen=True)
class Posted:
    """Where a request was left, and its inode (to withdraw only our own)."""

    path: Path
    inode: int


def post(flight: FlightInfo, action: str) -> Posted:
    """Leave ``action`` for ``flight`` without waiting. When something that cannot be replaced
    (a directory) sits at the request path, the request is written around it under
    ``estop-<robot>-<id>.<8 hex>.json``, which the flight looks for as soon as its path is blocked."""
    if action not in ACTIONS:
        raise ValueError(f"e-stop action must be one of {ACTIONS}, got {action!r}")
    payload = {"action": action, "id": flight.id, "pid": os.getpid(), "time": time.time()}
    path = flight.request_path
    try:
        return Posted(path, write_atomic(path, payload))
    except OSError as exc:
        blocked = exc
    around = path.with_name(f"{path.name[: -len('.json')]}.{secrets.token_hex(4)}.json")
    try:
        return Posted(around, write_atomic(around, payload))
    except OSError as exc:
        raise MailboxError(f"cannot write {path} ({_strerror(blocked)}) nor {around.name} ({_strerror(exc)})") from None


def request(flight: FlightInfo, action: str, timeout: float = 2.0, poll_s: float = 0.01) -> bool:
    """``post`` and wait until the flight takes it; False (and the request withdrawn) if it
    did not within ``timeout`` seconds or its process ended."""
    posted = post(flight, action)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            st = os.lstat(posted.path)
        except FileNotFoundError:
            return True
        if st.st_ino != posted.inode or not flight.alive():
            break
        time.sleep(poll_s)
    with contextlib.suppress(OSError):
        if os.lstat(posted.path).st_ino == posted.inode:  # withdraw our own request only
            os.unlink(posted.path)
    return False


# --- files ----------------------------------------------------------------------------------


def _read_small(path: Path) -> bytes:
    return read_small(path)


def _write(path: Path, payload: dict[str, Any]) -> int:
    try:
        return write_atomic(path, payload)
    except OSError as exc:
        raise MailboxError(f"cannot write {path}: {_strerror(exc)}") from None


def _strerror(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


def describe_error(exc: BaseException) -> str:
    """A short stable description of ``exc`` (for logging each distinct error once)."""
    if isinstance(exc, OSError):
        code = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{_strerror(exc)} [{code}]{where}"
    return f"{exc}" if isinstance(exc, MailboxError) else f"{type(exc).__name__}: {exc}"
