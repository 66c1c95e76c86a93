"""Pre-flight checks before a hardware take-off: each a pure function of one snapshot.

The hardware backend gathers a ``PreflightSnapshot`` (link, firmware, telemetry, mocap) after
a short settle, ``run_checks`` turns it into a ``PreflightReport`` (a row per check, shown as
a rich table), and ``enforce`` refuses take-off on any failure with one line naming it,
unless forced, in which case the override is logged.

Thresholds and their sources: battery from the robot type (Crazyswarm2: warn below 3.8 V,
refuse below 3.7 V at idle; firmware ``pm.state`` 3 = lowPower; docs/hardware.md#battery), mocap rate within
20 % of the expected rate (Crazyswarm2's 80-120 Hz around 100 Hz; docs/hardware.md#mocap), link latency
10 ms (Crazyswarm2 server.yaml; docs/hardware.md#crazyswarm2), supervisor bits
(docs/hardware.md#supervisor), protocol 12 for the
supervisor port and the emergency-stop watchdog (docs/hardware.md#emergency-stop).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Literal, Sequence

import numpy as np

Status = Literal["pass", "warn", "fail"]
_log = logging.getLogger("cfknode.preflight")

# supervisor.info bits (docs/hardware.md#supervisor)
SUP_CAN_FLY = 1 << 3
SUP_FLYING = 1 << 4
SUP_TUMBLED = 1 << 5
SUP_LOCKED = 1 << 6
SUP_CRASHED = 1 << 7

PM_LOW_POWER = 3
PM_SHUTDOWN = 4
SUPERVISOR_PROTOCOL = 12  # supervisor port, emergency-stop watchdog (docs/hardware.md#emergency-stop)
MIN_PROTOCOL = 4  # log/param TOC v2 with 16-bit ids, which every current cflib speaks
RATE_WARN_FRACTION = 0.2  # +-20 %: Crazyswarm2's 80-120 Hz around 100 Hz
RATE_FAIL_FRACTION = 0.5  # +-50 %: too far from what the estimator and the extpose stream expect
MAX_LATENCY_MS = 10.0  # Crazyswarm2's unicast latency warning
BODY_STALE_S = 0.5  # s: a body not seen for this long is not visible


@dataclass(frozen=True)
class PreflightSnapshot:
    """Everything the checks look at, gathered once; ``None`` = never received."""

    robot: str
    link_up: bool
    link_error: str | None
    latency_ms: float | None
    protocol_version: int | None
    vbat: float | None  # V at idle
    pm_state: int | None
    voltage_warning: float
    voltage_critical: float
    supervisor_info: int | None
    mocap_label: str
    mocap_rate_hz: float  # rate of frames holding the rigid body
    expected_rate_hz: float
    mocap_error: str | None
    body_seen_age: float | None  # s since the body was last seen
    body_position: tuple[float, float, float] | None
    body_quaternion: tuple[float, float, float, float] | None  # w, x, y, z
    initial_position: tuple[float, float, float]
    position_tolerance: float
    max_tilt_deg: float
    heartbeat_requested: bool = True


@dataclass(frozen=True)
class CheckResult:
    name: str
    status: Status
    value: str  # what was measured
    expected: str  # what passes
    reason: str = ""  # one line when the status is not "pass"


@dataclass(frozen=True)
class PreflightReport:
    results: tuple[CheckResult, ...]
    forced: bool = False

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def failures(self) -> tuple[CheckResult, ...]:
        return tuple(r for r in self.results if r.status == "fail")

    @property
    def warnings(self) -> tuple[CheckResult, ...]:
        return tuple(r for r in self.results if r.status == "warn")

    @property
    def reason(self) -> str:
        """One line: why take-off is refused ("" when every check passed)."""
        return "; ".join(f"{r.name}: {r.reason}" for r in self.failures)

    def events(self) -> list[dict[str, str]]:
        """Flight-log ``/events`` messages: failures, warnings, and the override if forced."""
        out = [{"level": "error" if self.forced else "critical", "text": f"pre-flight {r.name}: {r.reason}",
                "source": "preflight"} for r in self.failures]
        out += [{"level": "warning", "text": f"pre-flight {r.name}: {r.reason}", "source": "preflight"}
                for r in self.warnings]
        if self.forced and self.failures:
            out.append({"level": "warning", "text": f"take-off FORCED despite: {self.reason}", "source": "preflight"})
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "forced": self.forced,
            "checks": [{"name": r.name, "status": r.status, "value": r.value, "expected": r.expected,
                        "reason": r.reason} for r in self.results],
        }


class PreflightError(RuntimeError):
    """Take-off refused; ``str()`` is one line naming the failed checks, ``report`` has the rows."""

    def __init__(self, report: PreflightReport) -> None:
        super().__init__(f"take-off refused by the pre-flight checks: {report.reason} (--force overrides)")
        self.report = report


# --- the checks ------------------------------------------------------------------------------


def check_link(s: PreflightSnapshot) -> CheckResult:
    expected = f"connected, latency <= {MAX_LATENCY_MS:g} ms"
    if not s.link_up or s.link_error:
        return CheckResult("link", "fail", s.link_error or "down", expected,
                           f"no link to {s.robot}" + (f" ({s.link_error})" if s.link_error else ""))
    if s.latency_ms is None:
        return CheckResult("link", "warn", "up, latency not measured yet", expected, "latency not measured yet")
    value = f"up, {s.latency_ms:.1f} ms"
    if s.latency_ms > MAX_LATENCY_MS:
        return CheckResult("link", "warn", value, expected, f"latency {s.latency_ms:.1f} ms > {MAX_LATENCY_MS:g} ms")
    return CheckResult("link", "pass", value, expected)


def check_protocol(s: PreflightSnapshot) -> CheckResult:
    expected = f">= {SUPERVISOR_PROTOCOL} (>= {MIN_PROTOCOL} to fly)"
    v = s.protocol_version
    if v is None or v < 0:
        return CheckResult("protocol", "fail", "unknown", expected, "the firmware did not report its protocol version")
    if v < MIN_PROTOCOL:
        return CheckResult("protocol", "fail", str(v), expected, f"firmware protocol {v} is too old (update the firmware)")
    if v < SUPERVISOR_PROTOCOL:
        why = f"protocol {v} < {SUPERVISOR_PROTOCOL}: "
        why += "no emergency-stop-watchdog heartbeat; " if s.heartbeat_requested else ""
        return CheckResult("protocol", "warn", str(v), expected,
                           why + "the thrust mapping may differ (run cfknode calibrate)")
    return CheckResult("protocol", "pass", str(v), expected)


def check_battery(s: PreflightSnapshot) -> CheckResult:
    expected = f">= {s.voltage_warning:.2f} V (refused < {s.voltage_critical:.2f} V)"
    if s.vbat is None:
        return CheckResult("battery", "fail", "no reading", expected, "no pm.vbat telemetry from the Crazyflie")
    value = f"{s.vbat:.2f} V" + (f", pm.state {s.pm_state}" if s.pm_state is not None else "")
    if s.pm_state in (PM_LOW_POWER, PM_SHUTDOWN):
        return CheckResult("battery", "fail", value, expected, f"the firmware reports low power (pm.state {s.pm_state})")
    if s.vbat < s.voltage_critical:
        return CheckResult("battery", "fail", value, expected,
                           f"{s.vbat:.2f} V at idle is below {s.voltage_critical:.2f} V: charge or swap the battery")
    if s.vbat < s.voltage_warning:
        return CheckResult("battery", "warn", value, expected, f"{s.vbat:.2f} V at idle is below {s.voltage_warning:.2f} V")
    return CheckResult("battery", "pass", value, expected)


def check_mocap_rate(s: PreflightSnapshot) -> CheckResult:
    exp = s.expected_rate_hz
    lo_w, hi_w = exp * (1 - RATE_WARN_FRACTION), exp * (1 + RATE_WARN_FRACTION)
    expected = f"{lo_w:.0f}-{hi_w:.0f} Hz"
    rate = s.mocap_rate_hz
    if s.mocap_error:
        return CheckResult("mocap rate", "fail", "stream ended", expected, f"{s.mocap_label}: {s.mocap_error}")
    value = f"{rate:.0f} Hz"
    if rate <= 0:
        return CheckResult("mocap rate", "fail", value, expected,
                           f"no frames with {s.robot} from {s.mocap_label}")
    if not exp * (1 - RATE_FAIL_FRACTION) <= rate <= exp * (1 + RATE_FAIL_FRACTION):
        return CheckResult("mocap rate", "fail", value, expected,
                           f"{s.mocap_label} streams {s.robot} at {rate:.0f} Hz, expected about {exp:.0f} Hz")
    if not lo_w <= rate <= hi_w:
        return CheckResult("mocap rate", "warn", value, expected, f"{rate:.0f} Hz is outside {expected}")
    return CheckResult("mocap rate", "pass", value, expected)


def check_rigid_body(s: PreflightSnapshot) -> CheckResult:
    x0 = np.asarray(s.initial_position, dtype=float)
    expected = f"visible, within {s.position_tolerance:g} m of ({x0[0]:g}, {x0[1]:g}, {x0[2]:g})"
    if s.body_position is None or s.body_seen_age is None:
        return CheckResult("rigid body", "fail", "never seen", expected,
                           f"rigid body {s.robot!r} not seen: is the mocap object named {s.robot!r} and tracked?")
    if s.body_seen_age > BODY_STALE_S:
        return CheckResult("rigid body", "fail", f"lost {s.body_seen_age:.1f} s ago", expected,
                           f"rigid body {s.robot!r} not seen for {s.body_seen_age:.1f} s (occluded?)")
    p = np.asarray(s.body_position, dtype=float)
    d = float(np.linalg.norm(p - x0))
    value = f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}), {d:.3f} m off"
    if d > s.position_tolerance:
        return CheckResult("rigid body", "fail", value, expected,
                           f"{s.robot} is {d:.2f} m from its initial_position (tolerance {s.position_tolerance:g} m)")
    return CheckResult("rigid body", "pass", value, expected)


def check_level(s: PreflightSnapshot) -> CheckResult:
    """A robot tilted on the ground, or a mocap object whose axes are not the Crazyflie's
    (z must be up: docs/hardware.md#mocap), would be flown upside down by the attitude layer."""
    expected = f"tilt <= {s.max_tilt_deg:g} deg"
    if s.body_quaternion is None:
        return CheckResult("level", "fail", "no attitude", expected, f"no attitude for {s.robot!r} from the mocap")
    w, x, y, z = s.body_quaternion
    up_z = 1.0 - 2.0 * (x * x + y * y)  # body z axis, world z component
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, up_z))))
    value = f"{tilt:.1f} deg"
    if tilt > s.max_tilt_deg:
        return CheckResult("level", "fail", value, expected,
                           f"{s.robot} is tilted {tilt:.0f} deg: put it flat, or fix the mocap object's axes (z up)")
    return CheckResult("level", "pass", value, expected)


def check_supervisor(s: PreflightSnapshot) -> CheckResult:
    expected = "can fly; not locked, tumbled, crashed or flying"
    info = s.supervisor_info
    if info is None:
        return CheckResult("supervisor", "fail", "no reading", expected, "no supervisor.info telemetry from the Crazyflie")
    value = f"0x{info:04x}"
    for bit, why in ((SUP_LOCKED, "locked: reboot the Crazyflie"), (SUP_TUMBLED, "tumbled: put it upright"),
                     (SUP_CRASHED, "crashed: recover or reboot"), (SUP_FLYING, "already flying")):
        if info & bit:
            return CheckResult("supervisor", "fail", value, expected, f"the supervisor reports {why}")
    if not info & SUP_CAN_FLY:
        return CheckResult("supervisor", "fail", value, expected, "the supervisor says it cannot fly (not armed?)")
    return CheckResult("supervisor", "pass", value, expected)


CHECKS: tuple[Callable[[PreflightSnapshot], CheckResult], ...] = (
    check_link, check_protocol, check_battery, check_mocap_rate, check_rigid_body, check_level, check_supervisor,
)


def run_checks(snapshot: PreflightSnapshot,
               checks: Sequence[Callable[[PreflightSnapshot], CheckResult]] = CHECKS) -> PreflightReport:
    return PreflightReport(tuple(check(snapshot) for check in checks))


def enforce(report: PreflightReport, force: bool) -> PreflightReport:
    """Raise ``PreflightError`` on a failed check unless ``force``; a forced take-off is logged."""
    if report.ok:
        return report
    if not force:
        raise PreflightError(report)
    _log.warning("take-off FORCED despite failed pre-flight checks: %s", report.reason)
    return PreflightReport(report.results, forced=True)


def render_table(report: PreflightReport, title: str = "Pre-flight checks") -> Any:
    """The report as a ``rich.table.Table`` (imported here: rich is for the terminal only)."""
    from rich.table import Table

    style = {"pass": "green", "warn": "yellow", "fail": "bold red"}
    table = Table(title=title + (" [bold red](FORCED)[/]" if report.forced else ""))
    table.add_column("check")
    table.add_column("status")
    table.add_column("measured")
    table.add_column("expected")
    table.add_column("note")
    for r in report.results:
        table.add_row(r.name, f"[{style[r.status]}]{r.status.upper()}[/]", r.value, r.expected, r.reason)
    return table
