"""Operator controls: the e-stop mailbox, ``cfknode estop``, and the SIGINT handler."""

import asyncio
import os
import signal
import threading
import time

import pytest

from cfknode.app.cli import main
from cfknode.safety.estop_mailbox import find_flight, live_flights, post
from cfknode.safety.operator import EstopMailbox, estop_watch, mailbox_dir, stop_signal_handler


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
    assert main(["estop", "--dir", str(tmp_path / "missing")]) == 1
    assert "no flight is running" in capsys.readouterr().err


def _serve(flight: EstopMailbox, taken: list[str], stop: threading.Event) -> threading.Thread:
    def poll() -> None:  # the flight's side, as the watcher polls it
        while not stop.is_set() and not taken:
            request = flight.poll()
            if request:
                taken.append(request.action)
            time.sleep(0.005)

    poller = threading.Thread(target=poll)
    poller.start()
    return poller


@pytest.mark.parametrize("select", [[], ["--robot", "cf9"]], ids=["only-flight", "by-robot"])
def test_estop_command_reaches_a_flight(tmp_path, capsys, select):
    flight = EstopMailbox(tmp_path, "cf9")
    flight.open()
    taken: list[str] = []
    stop = threading.Event()
    poller = _serve(flight, taken, stop)
    try:
        assert main(["estop", *select, "--dir", str(tmp_path), "--land"]) == 0
    finally:
        stop.set()
        poller.join()
        flight.close()
    assert taken == ["land"]
    assert f"land taken by the flight of 'cf9' (pid {os.getpid()}, id {flight.id})" in capsys.readouterr().out


def test_estop_command_with_several_flights_asks_which(tmp_path, capsys):
    a, b = EstopMailbox(tmp_path, "sim-cf231"), EstopMailbox(tmp_path, "sim-cf231")
    a.open()
    b.open()
    try:
        assert main(["estop", "--dir", str(tmp_path)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and a.id in err and b.id in err and "--id ID" in err
        taken: list[str] = []
        stop = threading.Event()
        poller = _serve(b, taken, stop)
        try:
            assert main(["estop", "--dir", str(tmp_path), "--id", b.id]) == 0
        finally:
            stop.set()
            poller.join()
        assert taken == ["stop"] and a.poll() is None
    finally:
        a.close()
        b.close()


def test_estop_command_refuses_a_shared_directory(tmp_path, capsys):
    tmp_path.chmod(0o777)
    assert main(["estop", "--dir", str(tmp_path)]) == 2
    assert "writable by group or others" in capsys.readouterr().err


class Target:
    def __init__(self) -> None:
        self.calls: list[str] = []

    def interrupt(self, signal_name: str) -> None:
        self.calls.append(signal_name)


def test_stop_signals_go_to_the_target_and_the_old_handlers_come_back():
    target = Target()
    signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    before = {sig: signal.getsignal(sig) for sig in signals}

    def mine(signum, frame):  # a caller's own handler, to be put back
        raise AssertionError("not while the flight runs")

    signal.signal(signal.SIGTERM, mine)
    try:
        async def flight() -> bool:
            with stop_signal_handler(target) as installed:
                for sig in signals:
                    os.kill(os.getpid(), sig)
                for _ in range(10):
                    await asyncio.sleep(0.001)
                return installed

        assert asyncio.run(flight())
        assert target.calls == ["SIGINT", "SIGTERM", "SIGHUP"]
        assert signal.getsignal(signal.SIGINT) is before[signal.SIGINT]
        assert signal.getsignal(signal.SIGHUP) is before[signal.SIGHUP]
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, before[signal.SIGTERM])


def test_stop_signal_handler_off_the_main_thread_is_not_installed():
    out: list[bool] = []

    async def flight() -> None:
        with stop_signal_handler(Target()) as installed:
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

    def note(self, level: str, text: str, source: str) -> None:
        self.got.append((level, text, source))


def test_estop_watch_hands_requests_to_the_flight_between_ticks(tmp_path):
    target = Requests()
    box = EstopMailbox(tmp_path, "cf3")

    async def flight() -> None:
        with estop_watch(target, box, period=0.005):
            assert find_flight(tmp_path, "cf3").pid == os.getpid()
            post(find_flight(tmp_path, "cf3"), "land")
            while not target.got:
                await asyncio.sleep(0.001)
            post(find_flight(tmp_path, "cf3"), "stop")
            while len(target.got) < 2:
                await asyncio.sleep(0.001)

    asyncio.run(asyncio.wait_for(flight(), 10))
    assert target.got == [("land", "cfknode estop --robot cf3 --land", "estop_land"),
                          ("stop", "cfknode estop --robot cf3", "estop_stop")]
    assert live_flights(tmp_path) == [] and not box.request_path.exists()


def test_estop_watch_leaves_a_mailbox_opened_before_take_off_open(tmp_path):
    box = EstopMailbox(tmp_path, "cf3")
    box.open()

    async def flight() -> None:
        with estop_watch(Requests(), box, period=0.005):
            await asyncio.sleep(0.01)

    asyncio.run(flight())
    assert box.is_open and [f.id for f in live_flights(tmp_path)] == [box.id]
    box.close()
