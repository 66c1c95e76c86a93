"""Operator controls: the e-stop mailbox, ``cfknode estop``, and the SIGINT handler."""

import asyncio
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from cfknode.cli import main
from cfknode.safety.operator import EstopMailbox, estop_watch, mailbox_dir, sigint_handler


def test_mailbox_round_trip(tmp_path):
    flight = EstopMailbox(tmp_path, "cf 2/a")  # odd names become safe file names
    assert flight.request_path.parent == tmp_path and "/" not in flight.request_path.name[6:]
    assert flight.poll() is None
    EstopMailbox(tmp_path, "cf 2/a").post("land")
    assert flight.open()  # a request left from before the flight is stale: dropped
    assert flight.poll() is None
    assert EstopMailbox(tmp_path, "cf 2/a").flight_pid() == os.getpid()
    EstopMailbox(tmp_path, "cf 2/a").post("land")
    assert flight.poll() == "land" and flight.poll() is None
    flight.request_path.write_text("garbage")
    assert flight.poll() == "stop"  # unreadable is read as the stronger request
    flight.close()
    assert EstopMailbox(tmp_path, "cf 2/a").flight_pid() is None
    with pytest.raises(ValueError, match="must be one of"):
        flight.post("hover")


def test_request_times_out_and_withdraws(tmp_path):
    box = EstopMailbox(tmp_path, "cf1")
    start = time.monotonic()
    assert not box.request("stop", timeout=0.05)
    assert time.monotonic() - start < 1.0 and not box.request_path.exists()


def test_presence_of_a_dead_process_is_no_flight(tmp_path):
    box = EstopMailbox(tmp_path, "cf1")
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    box.presence_path.write_text(json.dumps({"pid": int(proc.stdout)}))
    assert box.flight_pid() is None


def test_mailbox_dir_defaults(monkeypatch, tmp_path):
    assert mailbox_dir(str(tmp_path)) == tmp_path
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    assert mailbox_dir() == tmp_path / "run" / "cfknode"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert mailbox_dir() == tmp_path / "cache" / "cfknode" / "estop"


def test_estop_command_without_a_flight_says_so(tmp_path, capsys):
    assert main(["estop", "--robot", "cf9", "--dir", str(tmp_path)]) == 1
    assert "no flight of 'cf9' is running" in capsys.readouterr().err


def test_estop_command_reaches_a_flight(tmp_path, capsys):
    flight = EstopMailbox(tmp_path, "cf9")
    flight.open()
    taken: list[str] = []
    stop = threading.Event()

    def poll() -> None:  # the flight's side, as the supervisor polls it
        while not stop.is_set() and not taken:
            action = flight.poll()
            if action:
                taken.append(action)
            time.sleep(0.005)

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        assert main(["estop", "--robot", "cf9", "--dir", str(tmp_path), "--land"]) == 0
    finally:
        stop.set()
        poller.join()
        flight.close()
    assert taken == ["land"]
    assert "land taken by the flight of 'cf9'" in capsys.readouterr().out


class Target:
    def __init__(self) -> None:
        self.calls = 0

    def interrupt(self) -> None:
        self.calls += 1


def test_sigint_goes_to_the_target_and_the_old_handler_comes_back():
    target = Target()
    before = signal.getsignal(signal.SIGINT)

    async def flight() -> bool:
        with sigint_handler(target) as installed:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10):
                await asyncio.sleep(0.001)
            return installed

    assert asyncio.run(flight())
    assert target.calls == 2
    assert signal.getsignal(signal.SIGINT) is before


def test_sigint_handler_off_the_main_thread_is_not_installed():
    out: list[bool] = []

    async def flight() -> None:
        with sigint_handler(Target()) as installed:
            out.append(installed)

    worker = threading.Thread(target=lambda: asyncio.run(flight()))
    worker.start()
    worker.join()
    assert out == [False]


class Requests:
    def __init__(self) -> None:
        self.got: list[tuple[str, str, str]] = []

    def request_land(self, reason: str, cause: str) -> None:
        self.got.append(("land", reason, cause))

    def request_stop(self, reason: str, cause: str) -> None:
        self.got.append(("stop", reason, cause))


def test_estop_watch_hands_requests_to_the_flight_between_ticks(tmp_path):
    target = Requests()
    box = EstopMailbox(tmp_path, "cf3")

    async def flight() -> None:
        with estop_watch(target, box, period=0.005):
            assert box.flight_pid() == os.getpid()
            EstopMailbox(tmp_path, "cf3").post("land")
            while not target.got:
                await asyncio.sleep(0.001)
            EstopMailbox(tmp_path, "cf3").post("stop")
            while len(target.got) < 2:
                await asyncio.sleep(0.001)

    asyncio.run(asyncio.wait_for(flight(), 10))
    assert target.got == [("land", "cfknode estop --robot cf3 --land", "estop_land"),
                          ("stop", "cfknode estop --robot cf3", "estop_stop")]
    assert box.flight_pid() is None and not box.request_path.exists()
