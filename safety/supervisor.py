"""The flight supervisor: a state machine between the controller and the radio.

States: IDLE -> PREFLIGHT -> TAKEOFF -> TRACK -> LAND -> LANDED, and EMERGENCY (motors
stopped) from anywhere in flight. A refused take-off goes from PREFLIGHT back to IDLE.

It is the radio's only owner in the loop (``FlightParts`` has no radio): every setpoint goes
through ``send`` and every mocap pose through ``accept_pose``, so nothing reaches the drone
without passing it. Each tick the loop asks ``plan`` what to fly:

- ``("fly", ref, "")``: run the controller on ``ref`` (the trajectory, clamped into the
  geofence, or the supervisor's own landing);
- ``("blind", ref, "blind")``: no fresh pose for ``mocap_hold_s``: send ``blind_setpoint``
  (level, thrust a little below hover, so it sinks gently);
- ``("off", ref, source)``: motors off (waiting for the first pose, landed, stopped, refused).

Watchdogs (the firmware has none of these: docs/hardware.md#host-safety): mocap loss (sink blind, then stop),
geofence (land, or stop far outside), radio link (lost: stop; silent or slow: land), loop
overruns and MPC deadlines (wall clock only: in lockstep no time passes while computing),
battery (refuse take-off, land), tumble (stop), tracking error (land), sustained MPC failure
(land). Operator requests (Ctrl-C, e-stop key, ``cfknode estop``) arrive from other threads
or signal callbacks through a deque (atomic appends) and take effect at the next tick.

Every transition is logged on ``/events`` (source "supervisor", with the new ``state``) and
``/safety``; ``/safety`` also gets the watchdog readings at 10 Hz. ``outcome()`` is the one
line the user sees.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from cfknode.kernel.errors import ConfigError
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.safety.settings import SafetyConfig
from cfknode.kernel.setpoint import AttitudeSetpoint, thrust_command
from cfknode.kernel.reference import Reference as Trajectory
from cfknode.kernel.reference import RefSamples
from cfknode.mocap.source import Pose
from cfknode.safety.geofence import Geofence, axis_name, clamp_reference
from cfknode.safety.landing import Landing, LandingPlanner
from cfknode.safety.part_errors import PartError
from cfknode.safety.watchdogs import LowPass, Persistence, tilt_cos, tilt_deg

from cfknode.safety.supervisor_inputs import SlowInputs
from cfknode.safety.supervisor_requests import OperatorRequests
from cfknode.safety.supervisor_types import (  # noqa: F401 (re-exported: the loop and the mission use them)
    MOTORS_OFF,
    FLY,
    BLIND,
    OFF,
    CUTOFF_HOLD_S,
    STOP_HOLD_S,
    MAX_OVERTIME_S,
    _CYCLE,
    _SCHEDULE,
    MAX_START_TILT_DEG,
    TOUCHDOWN_S,
    _TIME_EPS,
    State,
    _FLYING,
    _STOP,
    _LAND,
    _NOTE,
    ERROR_LAND,
    ERROR_STOP,
    ERROR_RECORD,
    Radio,
    Log,
    SupervisorInputs,
    SupervisedFlight,
    Outcome,
    SafetySnapshot,
)


class Supervisor(OperatorRequests, SlowInputs):
    """The flight's state machine and the radio's gate (see the module docstring)."""

    def __init__(
        self,
        config: SafetyConfig,
        radio: Radio,
        flight: SupervisedFlight,
        *,
        log: Log,
        inputs: SupervisorInputs = SupervisorInputs(),
    ) -> None:
        """``flight``: the trajectory, vehicle and tick rate it watches over (``SupervisedFlight``)."""
        if config.mocap_stop_s <= config.mocap_hold_s:
            raise ConfigError("config key 'safety.mocap_stop_s' must be greater than 'safety.mocap_hold_s'")
        self.config = config
        self.robot = flight.robot
        self._radio = radio
        self._log = log
        self._enabled = config.enabled
        self._period = 1.0 / flight.rate_hz
        self._deadlines = flight.deadlines_apply
        self._battery_source = inputs.battery_voltage
        self._link_source = inputs.link_status
        self.fence = Geofence.from_config(config)
        self._soft_lo, self._soft_hi = self.fence.soft_lo, self.fence.soft_hi
        self._watch_trajectory(flight.trajectory)
        self._blind_hold(config, flight.vehicle, radio)
        self._cos_tilt_max = math.cos(math.radians(config.max_tilt_deg))
        self._landing_planner: LandingPlanner | None = None
        self._start_state(config, flight.rate_hz)
        if self._clamp:
            self._event(0.0, "warning", "the reference leaves the geofence's soft box; it is clamped into it")

    def _watch_trajectory(self, trajectory: Trajectory) -> None:
        segments = trajectory.segments
        self._t_takeoff_end = segments["takeoff"][1]
        self._t_land_start = segments["land"][0]
        self._t_traj_end = trajectory.duration
        self._t_max = trajectory.duration + MAX_OVERTIME_S
        self._start = trajectory.sample(np.zeros(1)).p[0]
        self._ground_z = float(trajectory.final_position[2])
        grid = np.arange(0.0, trajectory.duration + 0.05, 0.05)
        self._clamp = self._enabled and not self.fence.contains_soft(trajectory.sample(grid).p)

    def _blind_hold(self, config: SafetyConfig, vehicle: VehicleConfig, radio: Radio) -> None:
        hover = vehicle.mass * vehicle.gravity
        self.blind_setpoint = AttitudeSetpoint(0.0, 0.0, 0.0, thrust_command(config.hold_thrust_factor * hover, vehicle))
        blind_az = self.blind_setpoint.thrust * vehicle.newton_per_cmd / vehicle.mass - vehicle.gravity
        self.blind_acc = np.array([0.0, 0.0, blind_az])
        self.blind_acc.flags.writeable = False  # shared with the estimator and observers every blind tick
        # A radio that checks its setpoint's age holds on this same blind setpoint if the loop stalls.
        guard = getattr(radio, "set_stale_hold", None)
        if guard is not None:
            guard(self.blind_setpoint, self.loop_stalled)

    def _start_state(self, config: SafetyConfig, rate_hz: float) -> None:
        self._state = State.IDLE
        self._refused = False
        self._cause = ""
        self._cause_text = ""
        self._cause_t = math.nan
        self._raised: set[str] = set()
        self._t_end: float | None = None
        self._hold = 0.0
        self._now = 0.0
        self._tick = 0
        self._requests: deque[tuple[str, str, str, str]] = deque()  # (kind, cause, text, note)
        self._interrupts: list[str] = []  # stop signals received, oldest first
        self._errors: dict[tuple[str, str, str], PartError] = {}
        self.error_repeats = 0  # internal errors seen again after their first report
        # Watchdog readings and timers.
        self._pose_t = -math.inf
        self._fresh = False  # a frame arrived since the last tracking check
        self._fence_margin = math.nan
        self._track_err = math.nan
        self._battery = LowPass(config.battery_filter_s)
        self._link_silence = 0.0
        self._tumble = Persistence(config.tumble_s)
        self._tracking = Persistence(config.tracking_error_s)
        self._touchdown = Persistence(TOUCHDOWN_S)
        self._fallback_run = 0
        self._fallback_limit = max(1, math.ceil(config.max_fallback_s * rate_hz - 1e-9))
        self._overrun_run = 0
        self.fallback_ticks = 0
        self.rejected_poses = 0
        # Landing: "nominal" follows the trajectory's own land segment; "supervised" flies
        # ``_landing``, planned at the first tick that can fly it (from the estimate then).
        self._landing_mode = ""
        self._landing: Landing | None = None
        self._blind = False
        self._blind_since = math.nan
        self.events: list[str] = []

    def set_landing_planner(self, planner: LandingPlanner | None) -> None:
        """How a supervised landing is planned: ``planner(start, ground_z, t0, land_speed)``; a fleet's
        orders it among the drones (ordered_landing.py). None: straight down from where it is."""
        self._landing_planner = planner

    # --- what other parts read ------------------------------------------------------------------

    @property
    def state(self) -> State:
        return self._state

    @property
    def brake_tilt_deg(self) -> float | None:
        """The fence brake's tilt for the controller while a landing for a fence crossing is outside the soft box
        (docs/design.md#safety; the margin is to the hard box, whose floor is not inset), else None."""
        braking = self._state is State.LAND and self._cause == "fence" and self._fence_margin < self.fence.margin
        return self.config.fence_brake_tilt_deg if braking else None

    @property
    def deadlines_apply(self) -> bool:
        return self._deadlines

    @property
    def finished(self) -> bool:
        """The flight is over: motors cut (or take-off refused) and the hold time streamed."""
        return self._t_end is not None and self._now >= self._t_end + self._hold - 1e-9

    def snapshot(self) -> SafetySnapshot:
        return SafetySnapshot(self._state, self._cause, self._now - self._pose_t, self._fence_margin,
                              self._track_err, self._battery.value, self._link_silence, self._fallback_run)

    def outcome(self) -> Outcome:
        state, text, t = self._state, self._cause_text, self._cause_t
        if state is State.IDLE and self._refused:
            message = f"take-off refused: {text}"
        elif state is State.LANDED and not self._cause:
            message = "flight complete: landed"
        elif state is State.LANDED:
            message = f"landed: {text} at {t:.2f} s"
        elif state is State.EMERGENCY:
            message = f"motors stopped: {text} at {t:.2f} s"
        else:
            message = f"flight ended in {state.value}" + (f": {text}" if text else "")
        if self.fallback_ticks:
            message += f"; the geometric fallback flew {self.fallback_ticks} ticks"
        errors = tuple(e.line for e in self._errors.values())
        if errors and self._cause != "internal_error":
            message += f"; {len(errors)} internal error{'s' if len(errors) > 1 else ''} (see the log)"
        return Outcome(state, message, self._cause or "complete", t, errors)

    # --- the gate -------------------------------------------------------------------------------

    def accept_pose(self, now: float, pose: Pose) -> bool:
        """A new mocap frame: checked (finite, geofence, tilt), forwarded to the drone's
        estimator, and accepted for the loop's; False for a frame that must be ignored."""
        x, y, z = pose.position.tolist()
        qw, qx, qy, qz = pose.quaternion.tolist()
        if not math.isfinite(x + y + z + qw + qx + qy + qz):
            self.rejected_poses += 1
            if self.rejected_poses == 1:
                self._event(now, "warning", "mocap frame with non-finite numbers ignored")
            return False
        self._pose_t = pose.t
        self._fresh = True
        self._radio.set_extpose(pose.position, pose.quaternion)
        if not self._enabled:
            return True
        margin, axis = self.fence.margin_of(x, y, z)
        self._fence_margin = margin
        if self._state in _FLYING:
            if margin < -self.config.fence_stop_distance:
                self._escalate(now, _STOP, "fence_stop",
                               f"{-margin:.2f} m outside the geofence on {axis_name(axis)} "
                               f"(stop beyond {self.config.fence_stop_distance:g} m)")
            elif margin < 0.0:
                self._escalate(now, _LAND, "fence", f"crossed the geofence on {axis_name(axis)}",
                               "landing inside its soft margin")
            if self._tumble.update(now, tilt_cos(qw, qx, qy, qz) < self._cos_tilt_max):
                self._escalate(now, _STOP, "tumble",
                               f"tilted {tilt_deg(pose.quaternion):.0f} deg (limit {self.config.max_tilt_deg:g} deg)")
        return True

    def send(self, now: float, sp: AttitudeSetpoint) -> AttitudeSetpoint:
        """The only way to the radio: motors off unless flying, never a non-finite number."""
        if self._state not in _FLYING:
            sp = MOTORS_OFF
        elif not math.isfinite(sp.roll_deg + sp.pitch_deg + sp.yawrate_deg):
            self._escalate(now, _STOP, "nonfinite_setpoint", f"non-finite setpoint {sp}")
            sp = MOTORS_OFF
        self._radio.set_setpoint(sp)
        self._radio.pump(now)
        return sp

    # --- once per tick --------------------------------------------------------------------------

    def plan(self, now: float, est: Any, ref: RefSamples) -> tuple[str, RefSamples, str]:
        """What to fly this tick: (action, reference, source for an "off" or "blind" tick)."""
        self._now = now
        slot = _SCHEDULE.get(self._tick % _CYCLE)
        self._tick += 1
        if slot is not None:
            self._poll(now, slot)
        while self._requests:  # appended by other threads; deque ends are atomic
            kind, cause, text, note = self._requests.popleft()
            if kind == _NOTE:
                self._event(now, "warning", text, source=cause)
            else:
                self._escalate(now, kind, cause, text, note)
        state = self._state
        if state in _FLYING:
            return self._fly(now, est, ref)
        if state is State.PREFLIGHT or (state is State.IDLE and not self._refused):
            return self._preflight(now, est, ref)
        if state is State.LANDED:
            return OFF, ref, "cutoff"
        if state is State.EMERGENCY:
            return OFF, ref, "stop"
        return OFF, ref, "refused"

    def after_tick(self, now: float, fallback: bool, status: str, missed: bool) -> None:
        """The tick's result: an MPC failure the fallback flew, a missed deadline."""
        if fallback:
            self.fallback_ticks += 1
            self._fallback_run += 1
            if self._enabled and self._fallback_run >= self._fallback_limit:
                self._escalate(now, _LAND, "mpc_failure",
                               f"the MPC failed for {self._fallback_run * self._period:.2f} s ({status})",
                               "the geometric controller flies the landing")
        else:
            self._fallback_run = 0
        if self._deadlines and self._enabled:
            self._overrun_run = self._overrun_run + 1 if missed else 0
            if self._overrun_run >= self.config.overrun_ticks:
                self._escalate(now, _LAND, "overrun", f"{self._overrun_run} missed deadlines in a row")

    # --- internals ------------------------------------------------------------------------------

    def _preflight(self, now: float, est: Any, ref: RefSamples) -> tuple[str, RefSamples, str]:
        if self._state is State.IDLE:
            self._transition(now, State.PREFLIGHT, "pre-flight checks")
        if est is None:
            if now >= self.config.preflight_timeout_s:
                body = f" '{self.robot}'" if self.robot else ""
                self._refuse(now, "no_mocap", f"no mocap frame within {self.config.preflight_timeout_s:g} s "
                             f"(is the rigid body{body} visible?)")
                return OFF, ref, "refused"
            return OFF, ref, "no_state"
        problem = self._preflight_problem(now, est) if self._enabled else None
        if problem is not None:
            self._refuse(now, *problem)
            return OFF, ref, "refused"
        volts = self._battery_now()
        self._transition(now, State.TAKEOFF, "pre-flight checks passed" + (
            f" (battery {volts:.2f} V)" if volts is not None else ""))
        return self._fly(now, est, ref)

    def _preflight_problem(self, now: float, est: Any) -> tuple[str, str] | None:
        cfg = self.config
        volts = self._battery_now()
        if volts is not None and volts < cfg.battery_takeoff_min_v:
            return "battery_low", f"battery {volts:.2f} V is below {cfg.battery_takeoff_min_v:g} V"
        if self._link_source is not None:
            link = self._link_source(now)
            if link.lost:
                return "link_lost", f"radio link lost ({link.lost})"
        margin, axis = self.fence.margin_of(*est.p.tolist())
        if margin < 0.0:
            return "fence", f"the drone is {-margin:.2f} m outside the geofence on {axis_name(axis)}"
        offset = float(np.linalg.norm(est.p - self._start))
        if offset > cfg.start_tolerance:
            return "start_pose", (f"the drone is {offset:.2f} m from the trajectory's start "
                                  f"(tolerance {cfg.start_tolerance:g} m)")
        tilt = tilt_deg(est.q)
        if tilt > MAX_START_TILT_DEG:
            return "start_tilt", f"the drone is tilted {tilt:.0f} deg (it must be level to take off)"
        return None

    def _fly(self, now: float, est: Any, ref: RefSamples) -> tuple[str, RefSamples, str]:
        cfg = self.config
        if self._enabled:
            age = now - self._pose_t - _TIME_EPS  # tick times are k * period: no rounding slips
            if age > cfg.mocap_stop_s:
                self._escalate(now, _STOP, "mocap_lost", f"mocap lost (no frame for {age:.2f} s)")
            elif age > cfg.mocap_hold_s:
                if not self._blind:
                    self._blind, self._blind_since = True, self._pose_t
                    self._escalate(now, _LAND, "mocap_lost", f"mocap lost (no frame for {age:.2f} s)",
                                   "level, sinking slowly until frames return")
                    self._landing_mode, self._landing = "supervised", None
                if self._state in _FLYING:
                    return BLIND, ref, "blind"
            elif self._blind:
                self._blind = False
                self._event(now, "warning", f"mocap back after {now - self._blind_since:.2f} s: landing from here")
                self._landing_mode, self._landing = "supervised", None
        if now > self._t_max:
            self._escalate(now, _STOP, "overtime", f"still flying {MAX_OVERTIME_S:g} s after the trajectory's end")
        state = self._state
        if state not in _FLYING:
            return OFF, ref, "stop"
        if est is None:  # cannot happen after PREFLIGHT (the estimator never forgets); never fly blind on it
            return BLIND, ref, "blind"
        if state is State.TAKEOFF and now >= self._t_takeoff_end:
            state = self._transition(now, State.TRACK, "take-off done")
        if state is State.TRACK and now >= self._t_land_start:
            self._landing_mode = "nominal"
            state = self._transition(now, State.LAND, "trajectory: landing")
        if state is State.LAND:
            return self._land(now, est, ref)

        if self._clamp:
            ref = clamp_reference(ref, self._soft_lo, self._soft_hi)
        if self._enabled and self._fresh:
            # Checked at the mocap rate: between frames the estimate is only a prediction.
            self._fresh = False
            d = est.p - ref.p[0]
            if state is State.TAKEOFF:
                # A heavier vehicle legitimately lags a climb (the fence bounds altitude);
                # during take-off only drifting sideways means the controller is lost.
                d = d[:2]
            err = math.sqrt(float(d @ d))
            self._track_err = err
            if self._tracking.update(now, err > cfg.max_tracking_error):
                self._escalate(now, _LAND, "tracking",
                               f"tracking error {err:.2f} m above {cfg.max_tracking_error:g} m")
                if self._state is State.LAND:
                    return self._land(now, est, ref)
        return FLY, ref, ""

    def _land(self, now: float, est: Any, ref: RefSamples) -> tuple[str, RefSamples, str]:
        if self._landing_mode == "nominal":
            if now >= self._t_traj_end:
                self._cut(now)
                return OFF, ref, "cutoff"
            if self._clamp:
                ref = clamp_reference(ref, self._soft_lo, self._soft_hi)
            return FLY, ref, ""
        landing = self._landing
        if landing is None:
            start = self.fence.clamp_point(est.p)
            start[2] = min(float(est.p[2]), float(self._soft_hi[2]))
            landing = self._landing = (self._landing_planner or Landing.plan)(start, self._ground_z, now,
                                                                              self.config.land_speed)
            self._event(now, "info", f"landing from ({start[0]:.2f}, {start[1]:.2f}, {start[2]:.2f}) m "
                        f"{landing.describe()}")
        landing.advance(now)
        low = float(est.p[2]) - self._ground_z < self.config.touchdown_height
        if now >= landing.t_end or self._touchdown.update(now, low):
            self._cut(now)
            return OFF, ref, "cutoff"
        return FLY, landing.sample(ref.t), ""

    def _escalate(self, now: float, kind: str, cause: str, text: str, note: str = "") -> None:
        """Land or stop for ``cause`` (once per cause and kind), as far as the state allows.

        ``text`` is the cause as the user reads it in the outcome; ``note`` only goes in the event.
        """
        key = f"{kind}:{cause}"
        if key in self._raised:
            return
        self._raised.add(key)
        state = self._state
        if state in (State.IDLE, State.PREFLIGHT):
            if not self._refused:
                self._refuse(now, cause, text)
            return
        if state is State.LANDED or state is State.EMERGENCY:
            return
        detail = f"{text}: {note}" if note else text
        if kind == _STOP:
            self._set_cause(now, cause, text, override=True)
            self._transition(now, State.EMERGENCY, detail, level="error")
            self._t_end, self._hold = now, STOP_HOLD_S
            return
        if state is State.LAND:
            # Already on the way down: keep that landing, but say why if it was the nominal one.
            self._set_cause(now, cause, text, override=False)
            self._event(now, "warning", f"{detail} (already landing)")
            return
        self._set_cause(now, cause, text, override=False)
        self._landing_mode, self._landing = "supervised", None
        self._transition(now, State.LAND, detail, level="warning")

    def _set_cause(self, now: float, cause: str, text: str, override: bool) -> None:
        if override or not self._cause:
            self._cause, self._cause_text, self._cause_t = cause, text, now

    def _refuse(self, now: float, cause: str, text: str) -> None:
        self._refused = True
        self._set_cause(now, cause, text, override=True)
        self._transition(now, State.IDLE, f"take-off refused: {text}", level="error")
        self._t_end, self._hold = now, 0.0

    def _cut(self, now: float) -> None:
        self._transition(now, State.LANDED, "touched down: motors off")
        self._t_end, self._hold = now, CUTOFF_HOLD_S

    def _transition(self, now: float, new: State, reason: str, level: str = "info") -> State:
        old = self._state
        self._state = new
        self._event(now, level, f"{old.value} -> {new.value}: {reason}", state=new.value, previous=old.value)
        self._log_status(now)
        return new

    def _event(self, now: float, level: str, text: str, **extra: Any) -> None:
        self.events.append(f"{now:.3f} s {level}: {text}")
        self._log.write("/events", now, {"level": level, "text": text, "source": "supervisor", **extra})
