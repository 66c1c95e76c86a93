"""The e-stop mailbox against broken and hostile files: a bad presence file never disables
`cfknode estop`, a bad request is a stop, a directory at a request path is written around,
the directory is private, and files of other users are not flights."""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path

import pytest

from cfknode.app.cli import main
from cfknode.safety import estop_files
from cfknode.safety.estop_mailbox import EstopMailbox, check_dir, find_flight, request, scan_flights

BAD_PRESENCE = {
    "started_list": lambda good: {**good, "started": [0]},
    "started_nan": lambda good: {**good, "started": "nan"},
    "pid_string": lambda good: {**good, "pid": str(good["pid"])},
    "pid_huge": lambda good: {**good, "pid": 10**30},
    "proc_start_object": lambda good: {**good, "proc_start": {"a": 1}},
    "robot_list": lambda good: {**good, "robot": ["cf1"]},
    "not_an_object": lambda good: [good],
    "nested": lambda good: "[" * 1000 + "]" * 1000,
}


class Poller:
    """A flight's watcher in a thread: takes each request it finds, as the flight loop's task does."""

    def __init__(self, box: EstopMailbox) -> None:
        self.box, self.got, self.errors = box, [], []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Poller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    def _run(self) -> None:
        while not self._stop.wait(0.005):
            try:
                got = self.box.poll()
            except Exception as exc:  # noqa: BLE001 - the watcher notes errors and goes on
                self.errors.append(str(exc))
                continue
            if got is not None:
                self.got.append(got)


def _plant(directory: Path, name: str, payload: object) -> Path:
    path = directory / name
    path.write_text(payload if isinstance(payload, str) else json.dumps(payload))
    return path


@pytest.mark.parametrize("case", sorted(BAD_PRESENCE))
def test_a_presence_file_that_cannot_be_parsed_is_skipped_and_reported(tmp_path, capsys, case):
    d = tmp_path / "box"
    box = EstopMailbox(d, "sim-cf1")
    box.open()
    good = json.loads(box.presence_path.read_text())
    _plant(d, f"flight-sim-cf2-{os.getpid()}-0badf00d.json", BAD_PRESENCE[case](good))
    scan = scan_flights(d)
    assert [f.id for f in scan.flights] == [box.id] and len(scan.skipped) == 1
    assert scan.skipped[0].startswith("flight-sim-cf2-") and "\n" not in scan.skipped[0]
    for argv in (["estop", "--dir", str(d), "--timeout", "10"], ["estop", "--all", "--dir", str(d), "--timeout", "10"]):
        with Poller(box) as poller:
            code = main(argv)
        out, err = capsys.readouterr()
        assert code == 0, err
        assert [r.action for r in poller.got] == ["stop"] and "stop taken by the flight of 'sim-cf1'" in out
        skipped = [line for line in err.splitlines() if line.startswith("cfknode estop: skipped flight-sim-cf2-")]
        assert len(skipped) == 1 and "Traceback" not in err
    box.close()


def test_garbage_and_oversized_presence_files_are_skipped(tmp_path):
    d = tmp_path / "box"
    check_dir(d)
    _plant(d, "flight-a-1-00000000.json", "{not json")
    _plant(d, "flight-b-1-00000000.json", "x" * 10_000)
    (d / "flight-c-1-00000000.json").mkdir()
    os.mkfifo(d / "flight-d-1-00000000.json")
    (d / "flight-e-1-00000000.json").symlink_to("/dev/zero")
    scan = scan_flights(d)
    assert scan.flights == () and len(scan.skipped) == 5
    assert any("not a regular file" in s for s in scan.skipped) and any("larger than" in s for s in scan.skipped)


def test_a_presence_file_of_another_user_is_not_a_flight(tmp_path, monkeypatch):
    d = tmp_path / "box"
    box = EstopMailbox(d, "sim-cf1")
    box.open()
    assert [f.id for f in scan_flights(d).flights] == [box.id]
    monkeypatch.setattr(estop_files.os, "geteuid", lambda: os.getuid() + 4242)  # as if another user wrote it
    scan = scan_flights(d)
    assert scan.flights == () and "belongs to uid" in scan.skipped[0]
    monkeypatch.undo()
    box.close()


@pytest.mark.parametrize("body", ["[" * 100_000 + "]" * 100_000, '{"action": ' * 3000, '{"action": 1e999999}',
                                  '{"action": ' + "9" * 5000 + "}", "\xff\xfe", '{"action": ["stop"]}'])
def test_a_request_that_cannot_be_parsed_is_a_stop(tmp_path, body):
    box = EstopMailbox(tmp_path, "sim-cf1")
    box.open()
    box.request_path.write_text(body, errors="surrogateescape")
    got = box.poll()
    assert got is not None and got.action == "stop" and "taken as stop" in got.note
    assert not box.request_path.exists() and not list(tmp_path.glob(".taken-*"))
    box.close()


@pytest.mark.parametrize("obstacle", ["directory", "full_directory"])
def test_a_directory_at_the_request_path_is_written_around(tmp_path, obstacle):
    box = EstopMailbox(tmp_path, "sim-cf1")
    box.open()
    box.request_path.mkdir()
    if obstacle == "full_directory":
        (box.request_path / "x").write_text("")
    with Poller(box) as poller:
        assert request(find_flight(tmp_path), "land", timeout=10)
    assert [r.action for r in poller.got] == ["land"]
    assert "is a directory" in poller.got[0].note and "taken from estop-sim-cf1-" in poller.got[0].note
    assert box.request_path.is_dir()  # left alone: only written around
    box.close()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("estop-")] == [box.request_path.name]


def test_a_written_around_request_is_found_after_the_obstacle_went(tmp_path):
    box = EstopMailbox(tmp_path, "sim-cf1")
    box.open()
    box.request_path.mkdir()
    flight = find_flight(tmp_path)
    from cfknode.safety.estop_mailbox import post

    posted = post(flight, "stop")
    assert posted.path != box.request_path
    box.request_path.rmdir()
    got = None
    for _ in range(50):  # found on a periodic scan, not only while blocked
        got = got or box.poll()
    assert got is not None and got.action == "stop" and not posted.path.exists()
    box.close()


def test_the_directory_is_created_private_and_a_readable_one_is_tightened(tmp_path):
    old = os.umask(0o022)
    try:
        made = tmp_path / "new" / "estop"
        EstopMailbox(made, "sim-cf1").open()
        assert stat.S_IMODE(made.stat().st_mode) == 0o700
        wide = tmp_path / "wide"
        wide.mkdir(mode=0o755)
        os.chmod(wide, 0o755)
        box = EstopMailbox(wide, "sim-cf1")
        box.open()
        assert stat.S_IMODE(wide.stat().st_mode) == 0o700
        box.close()
    finally:
        os.umask(old)


def test_estop_reaches_a_real_flight_whose_request_path_stays_blocked(tmp_path):
    """`cfknode fly` (lockstep) in a subprocess, a directory left at its request path and a broken
    presence file beside it: `cfknode estop` still stops the flight, by writing around the directory."""
    import subprocess
    import sys
    import time

    d = tmp_path / "estop"
    cmd = [sys.executable, "-m", "cfknode", "fly", "--traj", "hover", "--duration", "600", "--controller",
           "geometric", "--headless", "--json", "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={d}"]
    fly = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not scan_flights(d).flights and fly.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        (flight,) = scan_flights(d).flights
        flight.request_path.mkdir()
        _plant(d, f"flight-sim-cf9-{fly.pid}-0badf00d.json", {"robot": "sim-cf9", "id": f"{fly.pid}-0badf00d", "pid": fly.pid, "started": [0],
                                                                  "proc_start": flight.proc_start})
        estop = subprocess.run([sys.executable, "-m", "cfknode", "estop", "--dir", str(d), "--timeout", "30"],
                               capture_output=True, text=True, timeout=120)
        fly.communicate(timeout=120)
    finally:
        if fly.poll() is None:
            fly.kill()
            fly.wait()
    assert estop.returncode == 0, estop.stderr
    assert f"stop taken by the flight of 'sim-cf231' (pid {fly.pid}" in estop.stdout
    assert "cfknode estop: skipped flight-sim-cf9-" in estop.stderr and "'started' is [0]" in estop.stderr
    assert "Traceback" not in estop.stderr
    assert fly.returncode == 1 and flight.request_path.is_dir()
