"""SIGTERM and SIGHUP end a flight as Ctrl-C does: a real `cfknode fly` process, a real signal.

The first signal lands, a second stops the motors; either way the firmware is handed back,
the summary is printed and the log is complete, and the exit status is 1. Handlers are put
back after the flight.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cfknode.safety.process_signals import ProcessSignals, StopSignal
from fakes import finish_json, wait_for_log_events

from cfknode.app.logs.writer import read_log

WAIT_S = 240.0  # generous: the machine is shared; the flights themselves take seconds


def _start(tmp_path: Path, *sets: str) -> subprocess.Popen[str]:
    """A long lockstep hover (it would run a minute of flight time), headless, summary as JSON."""
    cmd = [sys.executable, "-m", "cfknode", "fly", "--headless", "--json", "--log-dir", str(tmp_path / "logs"),
           "--set", f"safety.estop_dir={tmp_path / 'estop'}", "--set", "trajectory.kind=hover",
           "--set", "trajectory.duration=60", *(a for s in sets for a in ("--set", s))]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_stop_signal_in_flight_lands_and_hands_back(tmp_path, sig):
    proc = _start(tmp_path)
    wait_for_log_events(proc, tmp_path / "logs", ["/events"], "TAKEOFF -> TRACK", WAIT_S)
    proc.send_signal(sig)
    code, summary, err = finish_json(proc, WAIT_S)
    extra = summary["extra"]
    text = "SIGTERM" if sig is signal.SIGTERM else "SIGHUP (terminal closed)"
    assert code == 1, err  # landed safely, but the mission was cut short, as with Ctrl-C
    assert extra["outcome"].startswith(f"landed: {text} at "), extra["outcome"]
    assert extra["safety_cause"] == sig.name.lower()
    assert err.strip().splitlines()[-1] == f"cfknode: {extra['outcome']}"
    assert "Traceback" not in err
    assert extra["firmware_after_shutdown"] == "landed"
    assert extra["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    assert extra["vehicle_after_shutdown"]["on_ground"]
    log = read_log(summary["log_path"])
    assert not log.truncated
    assert log.topic("/summary")[0]["extra"]["outcome"] == extra["outcome"]


def test_a_second_sigterm_stops_the_motors(tmp_path):
    # A slow landing from 1 m, so the second signal arrives while it is under way.
    proc = _start(tmp_path, "trajectory.height=1.0", "safety.land_speed=0.1")
    wait_for_log_events(proc, tmp_path / "logs", ["/events"], "TAKEOFF -> TRACK", WAIT_S)
    proc.send_signal(signal.SIGTERM)
    wait_for_log_events(proc, tmp_path / "logs", ["/events"], "TRACK -> LAND: SIGTERM", WAIT_S)
    proc.send_signal(signal.SIGTERM)
    code, summary, err = finish_json(proc, WAIT_S)
    extra = summary["extra"]
    assert code == 1, err
    assert extra["safety_state"] == "EMERGENCY" and extra["safety_cause"] == "sigterm_stop"
    assert extra["outcome"].startswith("motors stopped: second SIGTERM at ")
    assert extra["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    assert "Traceback" not in err
    assert not read_log(summary["log_path"]).truncated


def test_sigterm_before_take_off_unwinds_like_ctrl_c(tmp_path):
    # Before the flight has a supervisor (here: while the process starts) nothing flies: the
    # signal unwinds like Ctrl-C's KeyboardInterrupt, with the conventional 128 + 15.
    proc = _start(tmp_path)
    deadline = time.monotonic() + WAIT_S
    while not (tmp_path / "estop").exists() and time.monotonic() < deadline:  # the command is past imports
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=WAIT_S)
    assert "Traceback" not in err
    if proc.returncode == 1:  # the signal came after the supervisor existed: take-off refused, or a landing
        outcome = json.loads(out)["extra"]["outcome"]
        assert outcome.startswith(("take-off refused: SIGTERM", "landed: SIGTERM")), outcome
    else:
        assert proc.returncode == 128 + signal.SIGTERM and "cfknode: interrupted (SIGTERM)" in err


class Target:
    def __init__(self) -> None:
        self.got: list[str] = []

    def interrupt(self, signal_name: str) -> None:
        self.got.append(signal_name)


def test_a_stop_signal_swallowed_where_python_cannot_raise_is_not_printed_and_still_reaches_the_supervisor():
    import weakref

    seen = []
    before = sys.unraisablehook
    sys.unraisablehook = seen.append  # stands for Python's printing hook
    try:
        target = Target()
        with ProcessSignals() as signals:

            class Owner:
                pass

            owner = Owner()

            def lock_callback(_ref: object) -> None:  # as an import lock's weakref callback, where the signal landed
                signals._handle(signal.SIGTERM, None)

            ref = weakref.ref(owner, lock_callback)
            del owner  # the callback raises StopSignal: Python can only swallow it
            assert ref() is None and seen == []  # not printed as a traceback
            ref2 = weakref.ref(Owner(), lambda _r: 1 / 0)  # anything else is still reported
            assert ref2() is None and len(seen) == 1 and seen[0].exc_type is ZeroDivisionError
            signals.route(target)
        assert target.got == ["SIGTERM"]  # the swallowed stop: take-off refused
        assert sys.unraisablehook == seen.append  # restored
    finally:
        sys.unraisablehook = before


def test_process_signals_route_then_restore():
    mine = signal.getsignal(signal.SIGTERM)
    # Not always Python's default: a shell starting the run in the background ignores SIGINT.
    mine_int = signal.getsignal(signal.SIGINT)
    target = Target()
    with ProcessSignals() as signals:
        with pytest.raises(StopSignal) as raised:  # no supervisor yet: unwind as Ctrl-C does
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.01)
        assert raised.value.signum == signal.SIGTERM
        # The process went on after it (here the test caught it; CasADi's callbacks can swallow
        # it while the MPC is built): the supervisor gets it, so the take-off is refused.
        signals.route(target)
        assert target.got == ["SIGTERM"]
        os.kill(os.getpid(), signal.SIGHUP)
        with pytest.raises(StopSignal):  # a third routed signal: a way out of a hung hand-back
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
    assert target.got == ["SIGTERM", "SIGHUP"]
    assert signals.received == ["SIGTERM", "SIGHUP", "SIGINT"]
    assert signal.getsignal(signal.SIGTERM) is mine
    assert signal.getsignal(signal.SIGINT) is mine_int
