"""A part that raises in flight degrades the flight instead of ending it.

Short lockstep flights with one part made to raise (monkeypatched): the controller (in the tick or
after the send), an observer, the flight log, the estimator, the simulated plant. Each asserts how the flight
ended, that the error went to the log once with its traceback, that the drone was handed
back with its motors off, and that the log is complete.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


from cfknode.app.cli import main
from cfknode.app.config import load_config
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import VelocityEstimator
from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.flight.mpc import TranslationalMpc
from cfknode.app.mission import FlightResult, run_flight
from cfknode.sim_backend.vehicle import Vehicle

# A 2 s hover: take-off 1.5 s, then the pattern, then the landing; about 6 s of flight time.
SHORT = {"trajectory.kind": "hover", "trajectory.duration": 2.0, "trajectory.takeoff_duration": 1.5,
         "trajectory.settle_duration": 0.5, "trajectory.land_duration": 1.5}
RAISE_AT_S = 2.5  # flight time from which the part raises: airborne, on the pattern


def _cfg(tmp_path: Path, **overrides: Any):
    return load_config(None, overrides={"log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "estop"),
                                        **SHORT, **overrides})


def _raise_after(calls: int, original: Any, exc: type[BaseException] = ZeroDivisionError) -> Any:
    """``original`` until it has run ``calls`` times, then ``exc`` on every call."""
    count = [0]

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        count[0] += 1
        if count[0] > calls:
            raise exc("injected failure")
        return original(*args, **kwargs)

    return wrapped


def _error_events(res: FlightResult) -> list[dict]:
    return [m for m in read_log(res.summary.log_path).topic("/events") if m.get("source") == "internal_error"]


def _assert_handed_back(res: FlightResult) -> None:
    extra = res.summary.extra
    assert extra["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    log = read_log(res.summary.log_path)
    assert not log.truncated
    assert log.topic("/summary")[0]["extra"]["outcome"] == res.outcome.message


def _assert_the_fallback_landed_on_a_controller_fault(res: FlightResult) -> None:
    out = res.outcome
    assert out.state.value == "LANDED" and out.cause == "internal_error"
    assert out.message.startswith("landed: internal error in the controller at ")
    assert len(out.errors) == 1 and "ZeroDivisionError: injected failure" in out.errors[0]
    assert res.summary.extra["fallback_reasons"].get("error", 0) > 100  # the fallback flew the landing
    assert res.summary.extra["vehicle_after_shutdown"]["on_ground"]
    assert res.summary.extra["firmware_after_shutdown"] == "landed"
    events = _error_events(res)
    assert len(events) == 1  # one traceback, not one per tick
    assert events[0]["part"] == "the controller" and "ZeroDivisionError: injected failure" in events[0]["traceback"]
    assert res.summary.extra["internal_errors"] == list(out.errors)
    _assert_handed_back(res)


def test_a_raising_mpc_flies_the_fallback_and_lands(tmp_path, monkeypatch):
    # 400 Hz: the MPC's solve raises from RAISE_AT_S on (it is not called before take-off).
    monkeypatch.setattr(TranslationalMpc, "solve", _raise_after(int(RAISE_AT_S * 400), TranslationalMpc.solve))
    _assert_the_fallback_landed_on_a_controller_fault(run_flight(_cfg(tmp_path)))


def test_a_raising_preparation_after_the_send_flies_the_fallback_and_lands(tmp_path, monkeypatch):
    # The controller's work after the send (the next tick's linearisation) raising is the controller's fault.
    monkeypatch.setattr(Controller, "prepare", _raise_after(int(RAISE_AT_S * 400), Controller.prepare))
    _assert_the_fallback_landed_on_a_controller_fault(run_flight(_cfg(tmp_path)))


class Brittle:
    """A tick observer that raises at its n-th tick."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.calls = 0

    def on_tick(self, tick: Any) -> None:
        self.calls += 1
        if self.calls == self.n:
            raise RuntimeError("observer broke")


def test_a_raising_observer_is_detached_and_the_flight_goes_on(tmp_path):
    brittle = Brittle(1000)
    res = run_flight(_cfg(tmp_path), observers=[brittle])
    out = res.outcome
    assert out.state.value == "LANDED" and out.cause == "complete"  # flown to the end
    assert brittle.calls == 1000  # not called again once it raised
    assert len(out.errors) == 1 and "the tick observer Brittle (detached)" in out.errors[0]
    assert out.message.endswith("; 1 internal error (see the log)")
    assert len(_error_events(res)) == 1
    _assert_handed_back(res)


def test_a_raising_log_write_does_not_end_the_flight(tmp_path, monkeypatch):
    original = FlightLog.write

    def write(self: FlightLog, topic: str, t: float, msg: Any) -> None:
        if topic == "/reference" and t >= RAISE_AT_S:
            raise TypeError("cannot encode this")
        original(self, topic, t, msg)

    monkeypatch.setattr(FlightLog, "write", write)
    res = run_flight(_cfg(tmp_path))
    out = res.outcome
    assert out.state.value == "LANDED" and out.cause == "complete"
    assert len(out.errors) == 1 and "the flight log (/reference)" in out.errors[0]
    assert len(_error_events(res)) == 1
    log = read_log(res.summary.log_path)
    assert log.times("/reference").max() < RAISE_AT_S <= log.times("/state").max()  # only that topic lost
    _assert_handed_back(res)


def test_a_raising_fast_layer_log_message_is_recorded_and_the_controller_flies_on(tmp_path, monkeypatch):
    # The loop builds /adaptation after the tick's setpoint is sent, outside the control law: its failure is
    # a record's, not the controller's, and no tick falls back to the geometric controller for it.
    from cfknode.flight.adaptation import LoopAdaptation

    monkeypatch.setattr(LoopAdaptation, "log", _raise_after(int(RAISE_AT_S * 400), LoopAdaptation.log))
    res = run_flight(_cfg(tmp_path))
    out = res.outcome
    assert out.state.value == "LANDED" and out.cause == "complete"
    assert len(out.errors) == 1 and "the fast layer's log message" in out.errors[0]
    assert "error" not in res.summary.extra["fallback_reasons"]
    log = read_log(res.summary.log_path)
    assert log.times("/adaptation").max() < RAISE_AT_S + 0.1 < log.times("/state").max()  # the others go on
    _assert_handed_back(res)


def test_a_raising_estimator_stops_the_motors(tmp_path, monkeypatch):
    monkeypatch.setattr(VelocityEstimator, "predict",
                        _raise_after(int(RAISE_AT_S * 400), VelocityEstimator.predict, ValueError))
    res = run_flight(_cfg(tmp_path))
    out = res.outcome
    assert out.state.value == "EMERGENCY" and out.cause == "internal_error"
    assert out.message.startswith("motors stopped: internal error in the estimator at ")
    assert [e["part"] for e in _error_events(res)] == ["the estimator"]
    _assert_handed_back(res)


def test_a_raising_simulator_stops_and_still_hands_back(tmp_path, monkeypatch):
    # The plant steps at 500 Hz; from RAISE_AT_S on it raises (as a zero mass would).
    monkeypatch.setattr(Vehicle, "step", _raise_after(int(RAISE_AT_S * 500), Vehicle.step))
    res = run_flight(_cfg(tmp_path))
    out = res.outcome
    assert out.state.value == "EMERGENCY" and out.cause == "internal_error"
    assert out.message.startswith("motors stopped: internal error in the clock (the simulator in lockstep) at ")
    assert len(out.errors) == 1 and "ZeroDivisionError" in out.errors[0]
    assert len(_error_events(res)) == 1
    _assert_handed_back(res)  # the frozen plant's firmware took the stop and the hand-back


def test_the_terminal_gets_one_line_per_error_and_no_traceback(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(TranslationalMpc, "solve", _raise_after(int(RAISE_AT_S * 400), TranslationalMpc.solve))
    sets = [a for k, v in SHORT.items() for a in ("--set", f"{k}={v}")]
    code = main(["fly", "--headless", "--json", "--log-dir", str(tmp_path), "--set",
                 f"safety.estop_dir={tmp_path / 'estop'}", *sets])
    err = capsys.readouterr().err
    assert code == 1
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "internal error in the controller: ZeroDivisionError" in line]
    assert len(lines) == 1 and "traceback in " in lines[0] and ".mcap (/events)" in lines[0]
