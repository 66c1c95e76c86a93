"""The e-stop mailbox: flight identity, exclusive robots, a private directory, safe files, a
watcher that outlives any error, and one real flight that is stopped after a planted directory."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cfknode.app.cli import main
from cfknode.app.logs.writer import read_log
from cfknode.safety import estop_files
from cfknode.safety import estop_mailbox as em
from cfknode.safety.estop_mailbox import (
    EstopMailbox,
    FlightInfo,
    FlightRunning,
    MailboxError,
    NoFlight,
    check_dir,
    find_flight,
    live_flights,
    post,
    request,
)
from cfknode.safety.operator import MAX_REPORTED_ERRORS, estop_watch


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(proc.stdout)


# --- identity --------------------------------------------------------------------------------


def test_two_flights_of_one_name_have_their_own_identity_and_requests(tmp_path):
    a, b = EstopMailbox(tmp_path, "sim-cf231"), EstopMailbox(tmp_path, "sim-cf231")
    a.open()
    b.open()
    assert a.id != b.id and a.presence_path != b.presence_path and a.request_path != b.request_path
    assert [f.id for f in live_flights(tmp_path)] == [a.id, b.id]
    with pytest.raises(MailboxError, match="2 flights of 'sim-cf231' are running.*--id ID"):
        find_flight(tmp_path, "sim-cf231")
    post(find_flight(tmp_path, flight_id=b.id), "land")
    assert a.poll() is None  # a request for b is never taken by a
    taken = b.poll()
    assert taken is not None and taken.action == "land" and taken.note == ""
    assert b.poll() is None
    # Only the owner removes a presence file: b's close leaves a announced.
    b.close()
    assert find_flight(tmp_path).id == a.id and a.presence_path.exists()
    a.close()
    assert live_flights(tmp_path) == []
    with pytest.raises(NoFlight, match="no flight of 'sim-cf231' is running"):
        find_flight(tmp_path, "sim-cf231")


def test_presence_file_names_the_flight_and_its_request(tmp_path):
    box = EstopMailbox(tmp_path, "cf 2/a")  # odd names become safe file names
    box.open()
    record = json.loads(box.presence_path.read_text())
    assert record["robot"] == "cf 2/a" and record["pid"] == os.getpid() and record["id"] == box.id
    assert record["request"] == box.request_path.name and "/" not in box.request_path.name
    assert box.request_path.parent == tmp_path
    assert stat.S_IMODE(box.presence_path.stat().st_mode) == 0o600
    box.close()
    assert not box.presence_path.exists()


def test_a_dead_or_reused_pid_is_no_flight(tmp_path):
    pid = _dead_pid()
    dead = FlightInfo(tmp_path, "cf1", f"{pid}-0123abcd", pid, time.time(), "")
    dead.presence_path.write_text(json.dumps(dead.to_json()))
    # This pid is alive, but started at another time: a reused pid, not the flight.
    reused = FlightInfo(tmp_path, "cf2", f"{os.getpid()}-89abcdef", os.getpid(), time.time(), "1")
    reused.presence_path.write_text(json.dumps(reused.to_json()))
    (tmp_path / "flight-cf3-x.json").write_text("garbage")
    assert live_flights(tmp_path) == []
    with pytest.raises(NoFlight):
        find_flight(tmp_path)


def test_a_second_flight_of_a_real_robot_is_refused(tmp_path):
    first = EstopMailbox(tmp_path, "cf231", exclusive=True)
    first.open()
    second = EstopMailbox(tmp_path, "cf231", exclusive=True)
    with pytest.raises(FlightRunning, match=rf"'cf231' \(pid {os.getpid()}, flight id {first.id}.*already flying"):
        second.open()
    assert not second.is_open and not second.presence_path.exists()
    EstopMailbox(tmp_path, "cf5", exclusive=True).open()  # another robot flies
    first.close()
    second.open()  # the robot is free again
    second.close()


def test_a_stale_presence_of_a_dead_process_does_not_refuse(tmp_path):
    pid = _dead_pid()
    stale = FlightInfo(tmp_path, "cf231", f"{pid}-0123abcd", pid, time.time(), "")
    stale.presence_path.write_text(json.dumps(stale.to_json()))
    box = EstopMailbox(tmp_path, "cf231", exclusive=True)
    box.open()
    assert [f.id for f in live_flights(tmp_path)] == [box.id]
    box.close()
    assert stale.presence_path.exists()  # not ours to remove


def test_the_robot_lock_is_held_by_another_process(tmp_path):
    """The lock lives in the kernel: a flight in another process refuses this one, and its end frees it."""
    code = ("import sys, time; from cfknode.safety.estop_mailbox import EstopMailbox as M\n"
            f"m = M({str(tmp_path)!r}, 'cf231', exclusive=True); m.open(); print(m.id, flush=True); sys.stdin.read()")
    other = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        other_id = other.stdout.readline().strip()
        with pytest.raises(FlightRunning, match=f"flight id {other_id}"):
            EstopMailbox(tmp_path, "cf231", exclusive=True).open()
    finally:
        other.kill()  # no clean-up: the kernel drops the lock, the presence file stays behind
        other.wait()
    box = EstopMailbox(tmp_path, "cf231", exclusive=True)
    box.open()
    assert [f.id for f in live_flights(tmp_path)] == [box.id]
    box.close()


# --- the directory ---------------------------------------------------------------------------


def test_the_directory_is_made_private(tmp_path):
    d = check_dir(tmp_path / "a" / "estop")
    assert stat.S_IMODE(d.stat().st_mode) == 0o700


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o770])
def test_a_directory_others_can_write_is_refused(tmp_path, mode):
    d = tmp_path / "shared"
    d.mkdir()
    d.chmod(mode)
    with pytest.raises(MailboxError, match=r"writable by group or others .*chmod 700") as err:
        EstopMailbox(d, "cf1").open()
    assert "\n" not in str(err.value)
    with pytest.raises(MailboxError, match="writable by group or others"):
        find_flight(d)  # the command does not trust it either


def test_a_directory_of_another_user_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(em.os, "geteuid", lambda: os.getuid() + 4242)
    with pytest.raises(MailboxError, match=r"belongs to uid \d+, not to you"):
        check_dir(tmp_path)


def test_a_directory_that_cannot_be_made_is_one_line(tmp_path):
    (tmp_path / "file").write_text("")
    for bad in ("/proc/nope", str(tmp_path / "file" / "estop")):
        with pytest.raises(MailboxError, match="cannot create the e-stop mailbox") as err:
            EstopMailbox(Path(bad), "cf1").open()
        assert "\n" not in str(err.value)


def test_fly_with_an_unusable_mailbox_is_a_one_line_error(tmp_path, capsys):
    code = main(["fly", "--controller", "geometric", "--headless", "--json", "--log-dir", str(tmp_path),
                 "--set", "safety.estop_dir=/proc/nope"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("cfknode: error: ") and "safety.estop_dir" in err[-1] and "cannot create" in err[-1]
    assert "Traceback" not in "\n".join(err)


# --- the files -------------------------------------------------------------------------------


def test_a_symlink_at_the_request_path_is_not_followed(tmp_path):
    box = EstopMailbox(tmp_path / "box", "cf1")
    box.open()
    outside = tmp_path / "outside.json"
    outside.write_text(json.dumps({"action": "land"}))
    box.request_path.symlink_to(outside)
    with pytest.raises(MailboxError, match="is a symbolic link, not a request file"):
        box.poll()
    assert outside.read_text() == json.dumps({"action": "land"}) and box.request_path.is_symlink()
    # The command replaces the link itself; the file it pointed at is untouched.
    post(find_flight(tmp_path / "box"), "stop")
    assert not box.request_path.is_symlink() and outside.read_text() == json.dumps({"action": "land"})
    assert box.poll().action == "stop"
    box.close()


def test_a_fifo_at_the_request_path_does_not_block_the_flight(tmp_path):
    box = EstopMailbox(tmp_path, "cf1")
    box.open()
    os.mkfifo(box.request_path)
    with pytest.raises(MailboxError, match="is a FIFO"):
        box.poll()
    box.close()


def test_requests_are_written_under_unpredictable_names(tmp_path, monkeypatch):
    box = EstopMailbox(tmp_path, "cf1")
    box.open()
    made: list[str] = []
    real = estop_files.tempfile.mkstemp

    def spy(*args, **kwargs):
        fd, name = real(*args, **kwargs)
        made.append(name)
        return fd, name

    monkeypatch.setattr(estop_files.tempfile, "mkstemp", spy)
    post(find_flight(tmp_path), "land")
    assert len(made) == 1 and Path(made[0]).parent == tmp_path and not Path(made[0]).exists()
    assert box.poll().action == "land"
    box.close()


def test_request_times_out_and_withdraws(tmp_path):
    box = EstopMailbox(tmp_path, "cf1")
    box.open()
    start = time.monotonic()
    assert not request(find_flight(tmp_path), "stop", timeout=0.05)
    assert time.monotonic() - start < 1.0 and not box.request_path.exists()
    with pytest.raises(ValueError, match="must be one of"):
        post(find_flight(tmp_path), "hover")
    box.close()


# --- the watcher -----------------------------------------------------------------------------


class Target:
    """The supervisor's side of the watcher: requests and events."""

    def __init__(self) -> None:
        self.got: list[tuple[str, str, str]] = []
        self.notes: list[tuple[str, str, str]] = []

    def request_land(self, reason: str, cause: str) -> None:
        self.got.append(("land", reason, cause))

    def request_stop(self, reason: str, cause: str) -> None:
        self.got.append(("stop", reason, cause))

    def note(self, level: str, text: str, source: str) -> None:
        self.notes.append((level, text, source))


async def _until(cond, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.002)


def _watch(box: EstopMailbox, body) -> Target:
    target = Target()

    async def flight() -> None:
        with estop_watch(target, box, period=0.002):
            await body(target)

    asyncio.run(asyncio.wait_for(flight(), 30))
    return target


def test_watcher_survives_a_directory_at_the_request_path(tmp_path):
    box = EstopMailbox(tmp_path, "cf3")

    async def body(target: Target) -> None:
        box.request_path.mkdir()
        await asyncio.sleep(0.1)  # tens of polls
        box.request_path.rmdir()
        post(find_flight(tmp_path), "land")
        await _until(lambda: target.got)

    target = _watch(box, body)
    assert target.got == [("land", "cfknode estop --robot cf3 --land", "estop_land")]
    assert len(target.notes) == 1  # once, not once per poll
    level, text, source = target.notes[0]
    assert (level, source) == ("error", "estop") and "is a directory, not a request file" in text


def test_watcher_takes_garbage_as_stop_and_says_so(tmp_path):
    box = EstopMailbox(tmp_path, "cf3")

    async def body(target: Target) -> None:
        box.request_path.write_text("garbage")
        await _until(lambda: target.got)

    target = _watch(box, body)
    assert target.got == [("stop", "cfknode estop --robot cf3", "estop_stop")]
    assert target.notes == [("warning", "e-stop mailbox: unreadable e-stop request b'garbage' taken as stop", "estop")]


ERRORS = [PermissionError(13, "Permission denied"), OSError(5, "Input/output error"), RuntimeError("anything else")]


@pytest.mark.parametrize("exc", ERRORS, ids=["permission", "io", "other"])
def test_watcher_survives_an_error_taking_a_request(tmp_path, monkeypatch, exc):
    """The request cannot be taken (root ignores file permissions, so the failure is simulated):
    logged once, the request stays, and it is taken once the fault clears."""
    box = EstopMailbox(tmp_path, "cf3")
    real = os.rename
    failing = {"on": True, "tries": 0}

    def rename(src, dst):
        if failing["on"] and Path(src) == box.request_path:
            failing["tries"] += 1
            raise exc
        return real(src, dst)

    async def body(target: Target) -> None:
        monkeypatch.setattr(em.os, "rename", rename)
        post(find_flight(tmp_path), "land")
        await _until(lambda: failing["tries"] >= 5)
        assert not target.got and box.request_path.exists()
        failing["on"] = False
        await _until(lambda: target.got)

    target = _watch(box, body)
    assert target.got == [("land", "cfknode estop --robot cf3 --land", "estop_land")]
    assert len(target.notes) == 1 and target.notes[0][0] == "error" and target.notes[0][2] == "estop"
    assert str(exc.strerror if isinstance(exc, OSError) else exc) in target.notes[0][1]


@pytest.mark.parametrize("exc", ERRORS[:2], ids=["permission", "io"])
def test_a_request_that_cannot_be_read_is_a_stop(tmp_path, monkeypatch, exc):
    box = EstopMailbox(tmp_path, "cf3")

    def read(path):
        raise exc

    async def body(target: Target) -> None:
        monkeypatch.setattr(em, "_read_small", read)
        post(box.info, "land")
        await _until(lambda: target.got)

    target = _watch(box, body)
    assert target.got == [("stop", "cfknode estop --robot cf3", "estop_stop")]
    assert len(target.notes) == 1 and target.notes[0][0] == "warning"
    assert f"unreadable e-stop request ({exc.strerror}" in target.notes[0][1]
    assert not box.request_path.exists() and not list(tmp_path.glob(".taken-*"))


def test_watcher_errors_are_not_logged_without_bound(tmp_path, monkeypatch):
    box = EstopMailbox(tmp_path, "cf3")
    count = {"n": 0}

    def poll():
        count["n"] += 1
        raise OSError(5, f"error number {count['n']}")

    monkeypatch.setattr(box, "poll", poll)

    async def body(target: Target) -> None:
        await _until(lambda: count["n"] > 3 * MAX_REPORTED_ERRORS)

    target = _watch(box, body)
    assert len(target.notes) == MAX_REPORTED_ERRORS + 1
    assert "no more are logged" in target.notes[-1][1]


# --- a real flight ---------------------------------------------------------------------------


def test_estop_stops_a_real_flight_after_a_directory_was_planted(tmp_path):
    """`cfknode fly` (lockstep) in a subprocess; a directory sits at its request path for 0.5 s;
    then `cfknode estop --dir D` still stops it, and the flight log has the error once."""
    d = tmp_path / "estop"
    cmd = [sys.executable, "-m", "cfknode", "fly", "--traj", "hover", "--duration", "600", "--controller",
           "geometric", "--headless", "--json", "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={d}"]
    fly = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not live_flights(d) and fly.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        (flight,) = live_flights(d)
        assert flight.robot == "sim-cf231" and flight.pid == fly.pid
        flight.request_path.mkdir()
        time.sleep(0.5)
        flight.request_path.rmdir()
        estop = subprocess.run([sys.executable, "-m", "cfknode", "estop", "--dir", str(d), "--timeout", "30"],
                               capture_output=True, text=True, timeout=120)
        out, err = fly.communicate(timeout=120)
    finally:
        if fly.poll() is None:
            fly.kill()
            fly.wait()
    assert estop.returncode == 0, estop.stderr
    assert f"stop taken by the flight of 'sim-cf231' (pid {fly.pid}" in estop.stdout
    assert fly.returncode == 1, err
    assert err.strip().splitlines()[-1].startswith("cfknode: motors stopped: cfknode estop --robot sim-cf231 at")
    events = read_log(json.loads(out)["log_path"]).topic("/events")
    mailbox_errors = [e["text"] for e in events if e.get("source") == "estop"]
    assert len(mailbox_errors) == 1 and "is a directory, not a request file" in mailbox_errors[0]
    assert live_flights(d) == [] and not flight.presence_path.exists()


# --- wiring ----------------------------------------------------------------------------------


def test_simulated_flights_are_not_named_like_a_robot():
    from cfknode.app.config import load_config
    from cfknode.app.mission import estop_name

    assert estop_name(load_config(None, {})) == "sim-cf231"
    assert estop_name(load_config(None, {"backend": "cf", "hardware.robot": "cf5"})) == "cf5"


def test_a_second_flight_of_a_flying_robot_is_refused_before_take_off(tmp_path, capsys):
    d = tmp_path / "estop"
    flying = EstopMailbox(d, "cf231", exclusive=True)  # stands for a flight of cf231 in another terminal
    flying.open()
    try:
        code = main(["fly", "--backend", "cf", "--robot", "cf231", "--controller", "geometric", "--headless",
                     "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={d}"])
    finally:
        flying.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1
    assert err[0] == (f"cfknode: error: take-off refused: 'cf231' (pid {os.getpid()}, flight id {flying.id}, "
                      f"started {time.strftime('%H:%M:%S', time.localtime(flying.info.started))}) is already "
                      "flying; a second flight of the same robot is refused")
    assert not list(tmp_path.glob("*.mcap"))  # refused before anything started: no flight log
