"""Pre-flight checks: every check passes on a good snapshot and fails (or warns) on its own fault."""

from __future__ import annotations

import dataclasses
import logging
import math

import pytest

from cfknode.safety.preflight import (
    CHECKS,
    PreflightError,
    PreflightSnapshot,
    check_battery,
    check_level,
    check_link,
    check_mocap_rate,
    check_protocol,
    check_rigid_body,
    check_supervisor,
    enforce,
    render_table,
    run_checks,
)

CAN_FLY_IDLE = 0b1111  # can be armed, armed, auto-arm, can fly
GOOD = PreflightSnapshot(
    robot="cf231",
    link_up=True,
    link_error=None,
    latency_ms=2.0,
    protocol_version=12,
    vbat=4.05,
    pm_state=0,
    voltage_warning=3.8,
    voltage_critical=3.7,
    supervisor_info=CAN_FLY_IDLE,
    mocap_label="vicon at 10.0.0.5",
    mocap_rate_hz=100.0,
    expected_rate_hz=100.0,
    mocap_error=None,
    body_seen_age=0.01,
    body_position=(0.02, -0.01, 0.015),
    body_quaternion=(1.0, 0.0, 0.0, 0.0),
    initial_position=(0.0, 0.0, 0.0),
    position_tolerance=0.1,
    max_tilt_deg=15.0,
)


def with_(**changes: object) -> PreflightSnapshot:
    return dataclasses.replace(GOOD, **changes)


def tilted(deg: float) -> tuple[float, float, float, float]:
    half = math.radians(deg) / 2
    return (math.cos(half), math.sin(half), 0.0, 0.0)  # about body x


def test_a_good_snapshot_passes_every_check() -> None:
    report = run_checks(GOOD)
    assert [r.name for r in report.results] == [
        "link", "protocol", "battery", "mocap rate", "rigid body", "level", "supervisor"]
    assert len(report.results) == len(CHECKS)
    assert all(r.status == "pass" for r in report.results), report.results
    assert report.ok and report.reason == "" and report.events() == []
    assert enforce(report, force=False) is report


@pytest.mark.parametrize(
    "check, changes, status, words",
    [
        (check_link, {"link_up": False}, "fail", "no link to cf231"),
        (check_link, {"link_error": "Too many packets lost"}, "fail", "Too many packets lost"),
        (check_link, {"latency_ms": 25.0}, "warn", "latency 25.0 ms > 10 ms"),
        (check_link, {"latency_ms": None}, "warn", "not measured"),
        (check_protocol, {"protocol_version": None}, "fail", "did not report"),
        (check_protocol, {"protocol_version": 3}, "fail", "too old"),
        (check_protocol, {"protocol_version": 10}, "warn", "no emergency-stop-watchdog heartbeat"),
        (check_battery, {"vbat": None}, "fail", "no pm.vbat"),
        (check_battery, {"vbat": 3.65}, "fail", "3.65 V at idle is below 3.70 V"),
        (check_battery, {"vbat": 3.75}, "warn", "below 3.80 V"),
        (check_battery, {"pm_state": 3}, "fail", "low power (pm.state 3)"),
        (check_mocap_rate, {"mocap_rate_hz": 0.0}, "fail", "no frames with cf231 from vicon at 10.0.0.5"),
        (check_mocap_rate, {"mocap_rate_hz": 30.0}, "fail", "30 Hz, expected about 100 Hz"),
        (check_mocap_rate, {"mocap_rate_hz": 70.0}, "warn", "outside 80-120 Hz"),
        (check_mocap_rate, {"mocap_error": "the mocap stream ended"}, "fail", "stream ended"),
        (check_rigid_body, {"body_position": None, "body_seen_age": None}, "fail", "not seen: is the mocap object named 'cf231'"),
        (check_rigid_body, {"body_seen_age": 2.0}, "fail", "not seen for 2.0 s"),
        (check_rigid_body, {"body_position": (0.3, 0.0, 0.0)}, "fail", "0.30 m from its initial_position"),
        (check_level, {"body_quaternion": tilted(25.0)}, "fail", "tilted 25 deg"),
        (check_level, {"body_quaternion": (0.0, 1.0, 0.0, 0.0)}, "fail", "tilted 180 deg"),  # object z down
        (check_level, {"body_quaternion": None}, "fail", "no attitude"),
        (check_supervisor, {"supervisor_info": None}, "fail", "no supervisor.info"),
        (check_supervisor, {"supervisor_info": 0b0100_0100}, "fail", "locked: reboot"),
        (check_supervisor, {"supervisor_info": CAN_FLY_IDLE | 1 << 5}, "fail", "tumbled"),
        (check_supervisor, {"supervisor_info": CAN_FLY_IDLE | 1 << 7}, "fail", "crashed"),
        (check_supervisor, {"supervisor_info": CAN_FLY_IDLE | 1 << 4}, "fail", "already flying"),
        (check_supervisor, {"supervisor_info": 0b0100}, "fail", "cannot fly"),
    ],
)
def test_each_check_flags_its_own_fault(check, changes: dict, status: str, words: str) -> None:
    assert check(GOOD).status == "pass"
    result = check(with_(**changes))
    assert result.status == status
    assert words in result.reason and "\n" not in result.reason
    # Every other check is unaffected by this fault (each looks only at its own fields).
    others = [c(with_(**changes)) for c in CHECKS if c is not check]
    assert all(r.status == "pass" for r in others), others


def test_boundaries_are_inclusive_where_the_thresholds_say_so() -> None:
    assert check_battery(with_(vbat=3.7)).status == "warn"  # at critical: not below it
    assert check_battery(with_(vbat=3.8)).status == "pass"
    assert check_mocap_rate(with_(mocap_rate_hz=80.0)).status == "pass"
    assert check_mocap_rate(with_(mocap_rate_hz=150.0)).status == "warn"
    assert check_mocap_rate(with_(mocap_rate_hz=151.0)).status == "fail"
    assert check_rigid_body(with_(body_position=(0.1, 0.0, 0.0))).status == "pass"
    assert check_level(with_(body_quaternion=tilted(14.9))).status == "pass"
    # The expected rate is the configured one, not always 100 Hz.
    assert check_mocap_rate(with_(mocap_rate_hz=240.0, expected_rate_hz=250.0)).status == "pass"
    assert check_protocol(with_(protocol_version=10, heartbeat_requested=False)).reason.startswith(
        "protocol 10 < 12: the thrust mapping")


def test_a_failure_refuses_take_off_with_one_line_naming_every_failed_check(caplog: pytest.LogCaptureFixture) -> None:
    report = run_checks(with_(vbat=3.5, supervisor_info=0b0100_0100, latency_ms=30.0))
    assert not report.ok
    assert [r.name for r in report.failures] == ["battery", "supervisor"]
    assert [r.name for r in report.warnings] == ["link"]
    with pytest.raises(PreflightError) as info:
        enforce(report, force=False)
    message = str(info.value)
    assert "\n" not in message
    assert "battery: 3.50 V at idle is below 3.70 V" in message
    assert "supervisor: the supervisor reports locked" in message and "--force" in message
    assert info.value.report is report
    levels = [e["level"] for e in report.events()]
    assert levels == ["critical", "critical", "warning"]

    with caplog.at_level(logging.WARNING, logger="cfknode.preflight"):
        forced = enforce(report, force=True)
    assert forced.forced and not forced.ok
    assert "FORCED" in caplog.text and "battery" in caplog.text
    events = forced.events()
    assert events[-1]["level"] == "warning" and events[-1]["text"].startswith("take-off FORCED despite: battery")
    assert forced.to_dict()["forced"] is True and forced.to_dict()["checks"][2]["status"] == "fail"


def test_table_renders_every_row() -> None:
    from rich.console import Console

    console = Console(width=200, record=True)
    console.print(render_table(enforce(run_checks(with_(vbat=3.5)), force=True)))
    text = console.export_text()
    for name in ("link", "protocol", "battery", "mocap rate", "rigid body", "level", "supervisor"):
        assert name in text
    assert "FAIL" in text and "PASS" in text and "FORCED" in text
