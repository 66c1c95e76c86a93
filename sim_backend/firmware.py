"""What the Crazyflie firmware does with what it receives (default PID controller; docs/hardware.md).

Inputs arrive as decoded CRTP packets (``on_*``); ``control`` runs once per plant step
(500 Hz, the firmware's ATTITUDE_RATE) and returns the four motor commands. Modelled:

- RPYT commander (port 3): angle mode for roll/pitch, rate mode for yaw. The wire pitch is
  stored as it comes (cflib already negated it, so it is the firmware's "legacy" pitch,
  + = nose up); the yaw rate is negated ("legacy rate input is inverted"), so + on the wire
  turns clockwise seen from above. Thrust < 1000 -> 0, clamp ``vehicle.thrust_cmd_clamp``;
  the thrust stays 0 until one packet with thrust == 0 has arrived (unlock).
- Commander priorities: streamed setpoints (2) beat the high-level commander (1); a streamed
  setpoint disables the high-level planner; ``notify_setpoint_stop`` relaxes the priority;
  a stopped (not disabled) planner feeds null setpoints, which keep the watchdog satisfied.
- Supervisor, evaluated at 25 Hz as on the drone: ReadyToFly ("idle") -> Flying when a motor
  runs; Flying -> WarningLevelOut when the setpoint is > 0.5 s old (roll = pitch = 0, yaw
  rate 0, thrust kept); -> ExceptFreeFall -> Locked when > 2 s old (motors off, setpoints
  ignored for good); Flying -> Landed when no motor has run for 2 s. WarningLevelOut has no
  path to Landed, hence the "stop streaming right after cutting thrust locks it" gotcha.
  Simplification: Landed stands for the firmware's Landed/Reset/pre-flight/ReadyToFly
  sequence (a few supervisor ticks on the drone) and goes back to Flying directly.
- Emergency stop (supervisor port 9 ch 1, or the legacy localization channel): from any
  state that can run the motors -> ExceptFreeFall -> Locked. The emergency-stop watchdog
  is off until its first notification; after that a gap of 1 s stops the drone the same
  way, in every state, landed or not, until a reboot (``power_off`` / ``power_on``, what
  cflib's ``PowerSwitch.stm_power_cycle`` does), which is the only thing that clears it.
- Attitude PID (controller_pid + attitude_pid_controller): the yaw-rate setpoint moves a yaw
  angle setpoint; angle PIDs give rate setpoints [deg/s]; rate PIDs give int16 outputs;
  everything reset while the thrust is 0. Derivative on the measurement, integrator
  clamps, yaw error and yaw derivative wrapped to +-180 deg. The estimate is perfect
  (true attitude and body rates).
- Legacy X mixer with r = roll/2, p = pitch/2 and the excess-capping rule.

Units and stability: the rate PID's output is a PWM difference, so its loop gain in SI is
kp * (180/pi) [units per rad/s] * 2 * (arm/sqrt(2)) * thrust_max/65535 [N m per unit] / J:
with the defaults 250 * 57.3 * 1.19e-7 / 1.66e-5 ~ 103 1/s, crossing over near 85 rad/s
with the 15 ms motor lag (phase margin ~75 deg; kd/kp = 10 ms adds lead). The angle loop
(kp 6 1/s) is an order of magnitude slower, so the firmware gains are used unchanged.
"""

from __future__ import annotations

import math
import threading
from typing import Sequence

import numpy as np

from cfknode.kernel.setpoint import ccw_yaw_rate_deg, integrate_yaw_deg, rpyt_thrust
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.vehicle import command_to_force


from cfknode.sim_backend.firmware_parts import (  # noqa: F401 (re-exported: tests and the link driver use them)
    ESTOP_WATCHDOG_TIMEOUT,
    ExtPose,
    INT16_LIMIT,
    IS_FLYING_HYSTERESIS,
    PITCH_ANGLE_GAINS,
    PITCH_RATE_GAINS,
    PRIORITY_CRTP,
    PRIORITY_DISABLE,
    PRIORITY_HIGH_LEVEL,
    PidGains,
    ROLL_ANGLE_GAINS,
    ROLL_RATE_GAINS,
    RPYT_MIN_THRUST,
    SUPERVISOR_PERIOD,
    Setpoint,
    WDT_LEVEL_OUT,
    WDT_SHUTDOWN,
    YAW_ANGLE_GAINS,
    YAW_RATE_GAINS,
    _MOTORS_ALLOWED,
    _PUBLIC_STATE,
    _Pid,
    _TIME_TOL,
    _null_setpoint,
    _saturate_int16,
    cap_angle,
    firmware_attitude,
    legacy_mixer,
)


class Firmware:
    """The onboard firmware of one simulated Crazyflie.

    ``lock`` (shared with the ``SimCrazyflie``) makes the inputs safe to call from the cflib
    driver thread while another thread steps; pass the simulator's lock.
    """

    def __init__(
        self, vehicle: VehicleConfig, dt: float, lock: threading.RLock | None = None, *,
        attitude_gain: float = 1.0, yaw_gain: float = 1.0,
    ) -> None:
        """``attitude_gain`` / ``yaw_gain``: the roll/pitch angle and yaw rate the attitude loop
        tracks per commanded unit (a plant that answers more or less than asked; 1 = as asked)."""
        self.dt = dt
        self._attitude_gain = attitude_gain
        self._yaw_gain = yaw_gain
        self._lock = lock if lock is not None else threading.RLock()
        self._thrust_max = vehicle.thrust_max_per_motor
        self._thrust_clamp = int(vehicle.thrust_cmd_clamp)
        self.powered = True
        self.boots = 1
        self._boot()

    def _boot(self) -> None:
        """Everything a reboot resets: commander, supervisor, emergency stop, controller."""
        dt = self.dt
        # Commander
        self._setpoint = _null_setpoint(0.0, "boot")
        self._priority = PRIORITY_DISABLE
        self._hl_stopped = False  # planner idle (feeds null setpoints) vs disabled (feeds nothing)
        self.thrust_locked = True
        self.setpoints_received = 0
        self.setpoints_blocked = 0
        self.last_setpoint: Setpoint | None = None
        # Localization
        self.extposes_received = 0
        self.last_extpose: ExtPose | None = None
        # Supervisor
        self._state = "ready"
        self._next_supervisor_t = 0.0
        self._latest_thrust_t: float | None = None
        self.lock_reason: str | None = None  # why it went to Locked: commander_watchdog | emergency_stop | ...
        # Emergency stop (crtp_localization_service / supervisor port)
        self._estop_requested = False
        self._estop_watchdog_t: float | None = None  # latest notification; None = watchdog inactive
        self.estop_watchdog_notifications = 0
        # Controller
        self._pid_roll = _Pid(ROLL_ANGLE_GAINS, dt)
        self._pid_pitch = _Pid(PITCH_ANGLE_GAINS, dt)
        self._pid_yaw = _Pid(YAW_ANGLE_GAINS, dt, wrap=True)
        self._pid_roll_rate = _Pid(ROLL_RATE_GAINS, dt)
        self._pid_pitch_rate = _Pid(PITCH_RATE_GAINS, dt)
        self._pid_yaw_rate = _Pid(YAW_RATE_GAINS, dt)
        self._yaw_desired = 0.0
        self._prev_attitude_mode: bool | None = None
        self.active_setpoint = self._setpoint  # what the controller used last (after the supervisor's override)
        self.control_outputs: tuple[int, int, int] = (0, 0, 0)  # roll, pitch, yaw (after the yaw negation)
        self.motor_commands: tuple[int, int, int, int] = (0, 0, 0, 0)

    # ------------------------------------------------------------------------- status
    @property
    def supervisor_state(self) -> str:
        """One of "idle", "flying", "warning_level_out", "locked", "landed" ("off" while powered down)."""
        if not self.powered:
            return "off"
        return _PUBLIC_STATE[self._state]

    @property
    def estop_watchdog_active(self) -> bool:
        """True once a watchdog notification has arrived (until the next reboot)."""
        return self._estop_watchdog_t is not None

    @property
    def can_fly(self) -> bool:
        """Whether the supervisor lets the motors run (and accepts streamed setpoints)."""
        return self._state in _MOTORS_ALLOWED

    @property
    def setpoint(self) -> Setpoint:
        """The setpoint the commander currently holds (before the supervisor's override)."""
        return self._setpoint

    # ------------------------------------------------------------------------- inputs
    def on_rpyt(self, t: float, roll_deg: float, wire_pitch_deg: float, wire_yawrate_deg: float, thrust: int) -> None:
        """A legacy RPYT packet (port 3, ``'<fffH'``) with its decoded wire values."""
        with self._lock:
            if not self._accepts_streamed():
                return
            raw = int(thrust)
            if self._priority == PRIORITY_DISABLE:
                self.thrust_locked = True
            if raw == 0:
                self.thrust_locked = False
            # The commander's reading of the packet is the kernel's (read_setpoint), rule for rule.
            value = 0 if self.thrust_locked else rpyt_thrust(raw, self._thrust_clamp)
            sp = Setpoint(t, float(roll_deg), float(wire_pitch_deg), ccw_yaw_rate_deg(wire_yawrate_deg), value, "rpyt",
                          True)
            self._set_setpoint(sp, PRIORITY_CRTP)
            self.setpoints_received += 1
            self.last_setpoint = sp

    def on_stop(self, t: float) -> None:
        """Generic stop setpoint (type 0): a null setpoint, motors off at once; refreshes the watchdog."""
        with self._lock:
            if not self._accepts_streamed():
                return
            sp = _null_setpoint(t, "stop")
            self._set_setpoint(sp, PRIORITY_CRTP)
            self.setpoints_received += 1
            self.last_setpoint = sp

    def on_notify_setpoint_stop(self, t: float) -> None:
        """Relax the priority: the high-level commander may take over (if its planner is not disabled)."""
        with self._lock:
            if not self._accepts_streamed():
                return
            self._priority = PRIORITY_HIGH_LEVEL

    def on_hl_stop(self, t: float) -> None:
        """High-level STOP: the planner goes idle and from now on feeds null setpoints (when it has priority)."""
        with self._lock:
            if not self.powered:
                return
            self._hl_stopped = True
            self._feed_high_level(t)

    def on_emergency_stop(self, t: float) -> None:
        """Emergency stop request: motors off at the next supervisor tick, then Locked."""
        with self._lock:
            if self.powered:
                self._estop_requested = True

    def on_emergency_stop_watchdog(self, t: float) -> None:
        """Watchdog notification: from now on a 1 s gap is an emergency stop."""
        with self._lock:
            if self.powered:
                self._estop_watchdog_t = t
                self.estop_watchdog_notifications += 1

    def power_off(self, t: float) -> None:
        """STM32 powered down (cflib ``PowerSwitch.stm_power_down``): motors off, deaf."""
        with self._lock:
            self.powered = False
            self.motor_commands = (0, 0, 0, 0)

    def power_on(self, t: float) -> None:
        """STM32 powered up: a fresh boot, which is what clears Locked and the watchdog latch."""
        with self._lock:
            if self.powered:
                return
            self.powered = True
            self.boots += 1
            self._boot()
            self._next_supervisor_t = t

    def on_extpose(self, t: float, pos: Sequence[float], quat_xyzw: Sequence[float]) -> None:
        """External pose for the (here unused) Kalman estimator: stored and counted."""
        with self._lock:
            if not self.powered:
                return
            px, py, pz = (float(v) for v in pos)
            qx, qy, qz, qw = (float(v) for v in quat_xyzw)
            self.last_extpose = ExtPose(float(t), (px, py, pz), (qx, qy, qz, qw))
            self.extposes_received += 1

    # ------------------------------------------------------------------------- control
    def control(self, t: float, state13: Sequence[float]) -> np.ndarray:
        """One 500 Hz stabilizer iteration on the true state; returns the 4 motor commands (0..65535)."""
        x = state13.tolist() if isinstance(state13, np.ndarray) else list(state13)
        with self._lock:
            return np.array(self.step(t, x), dtype=float)

    def step(self, t: float, x: Sequence[float]) -> tuple[int, int, int, int]:
        """``control`` without the lock and numpy (the simulator's hot path; it holds the lock)."""
        if not self.powered:
            return (0, 0, 0, 0)
        if self._hl_stopped:
            self._feed_high_level(t)
        if t >= self._next_supervisor_t - _TIME_TOL:
            self._supervisor_tick(t)
            self._next_supervisor_t = (math.floor((t + _TIME_TOL) / SUPERVISOR_PERIOD) + 1) * SUPERVISOR_PERIOD
        self.active_setpoint = sp = self._override(self._setpoint)
        roll, pitch, yaw = firmware_attitude(x[6], x[7], x[8], x[9])
        thrust = self._attitude_pid(sp, roll, pitch, yaw, math.degrees(x[10]), math.degrees(x[11]), math.degrees(x[12]))
        if self._state in _MOTORS_ALLOWED and thrust > 0:
            r, p, y = self.control_outputs
            motors = legacy_mixer(thrust, r, p, y)
        else:
            motors = (0, 0, 0, 0)
        fmax = self._thrust_max
        # isFlyingCheck looks at the motors every step here (the drone samples them at 25 Hz).
        if any(command_to_force(m, fmax) > 0.0 for m in motors):
            self._latest_thrust_t = t
        self.motor_commands = motors
        return motors

    # ------------------------------------------------------------------------- internals
    def _accepts_streamed(self) -> bool:
        # stabilizer.c: crtpCommanderBlock(!canFly) drops streamed packets when the supervisor forbids flight.
        if self.powered and self._state in _MOTORS_ALLOWED:
            return True
        self.setpoints_blocked += 1
        return False

    def _set_setpoint(self, sp: Setpoint, priority: int) -> bool:
        """commanderSetSetpoint: accepted at equal or higher priority; a streamed one disables the planner."""
        if priority < self._priority:
            return False
        self._setpoint = sp
        self._priority = priority
        if priority > PRIORITY_HIGH_LEVEL:
            self._hl_stopped = False
        return True

    def _feed_high_level(self, t: float) -> None:
        self._set_setpoint(_null_setpoint(t, "high_level"), PRIORITY_HIGH_LEVEL)

    def _is_flying(self, t: float) -> bool:
        return self._latest_thrust_t is not None and t - self._latest_thrust_t < IS_FLYING_HYSTERESIS

    def _emergency_stop_reason(self, t: float) -> str | None:
        if self._estop_requested:
            return "emergency_stop"
        # checkEmergencyStopWatchdog: ok while tick < latest + timeout.
        if self._estop_watchdog_t is not None and t >= self._estop_watchdog_t + ESTOP_WATCHDOG_TIMEOUT - _TIME_TOL:
            return "emergency_stop_watchdog"
        return None

    def _supervisor_tick(self, t: float) -> None:
        age = t - self._setpoint.timestamp
        warning = age > WDT_LEVEL_OUT
        timeout = age > WDT_SHUTDOWN
        flying = self._is_flying(t)
        state = self._state
        estop = self._emergency_stop_reason(t) if state in _MOTORS_ALLOWED else None
        if estop is not None:
            # Every state that may run the motors goes to ExceptFreeFall on an emergency stop
            # (supervisor_state_machine.c); Landed gets there through Reset and pre-flight.
            self._state = "except_free_fall"
            self.lock_reason = estop
            return
        if state in ("ready", "landed"):
            if flying:
                state = "flying"
        elif state == "flying":
            if timeout:
                state = "except_free_fall"
                self.lock_reason = "commander_watchdog"
            elif warning:
                state = "warning_level_out"
            elif not flying:
                state = "landed"
        elif state == "warning_level_out":
            if timeout:
                state = "except_free_fall"
                self.lock_reason = "commander_watchdog"
            elif not warning:
                state = "flying"
        elif state == "except_free_fall":
            state = "locked"
        self._state = state

    def _override(self, sp: Setpoint) -> Setpoint:
        """supervisorOverrideSetpoint: level out keeping the thrust, or a null setpoint."""
        state = self._state
        if state == "warning_level_out":
            return Setpoint(sp.timestamp, 0.0, 0.0, 0.0, sp.thrust, sp.source, True)
        if state in ("except_free_fall", "locked"):
            return _null_setpoint(sp.timestamp, sp.source)
        return sp

    def _reset_pids(self, roll: float, pitch: float, yaw: float) -> None:
        self._pid_roll.reset(roll)
        self._pid_pitch.reset(pitch)
        self._pid_yaw.reset(yaw)
        self._pid_roll_rate.reset(0.0)
        self._pid_pitch_rate.reset(0.0)
        self._pid_yaw_rate.reset(0.0)

    def _attitude_pid(
        self, sp: Setpoint, roll: float, pitch: float, yaw: float, gyro_x: float, gyro_y: float, gyro_z: float
    ) -> int:
        """controller_pid at ATTITUDE_RATE; sets ``control_outputs`` and returns the thrust command."""
        if sp.attitude_mode != self._prev_attitude_mode:
            # setpointModeChanged(): a new mode starts from fresh PIDs.
            self._reset_pids(roll, pitch, yaw)
            self._prev_attitude_mode = sp.attitude_mode
        if sp.attitude_mode:
            self._yaw_desired = integrate_yaw_deg(self._yaw_desired, sp.yaw_rate * self._yaw_gain, self.dt)
        thrust = sp.thrust
        if thrust == 0:
            self.control_outputs = (0, 0, 0)
            self._reset_pids(roll, pitch, yaw)
            self._yaw_desired = yaw
            return 0
        gain = self._attitude_gain  # x * 1.0 == x exactly: the default is the firmware as it is
        roll_rate_des = self._pid_roll.update(sp.roll * gain, roll)
        pitch_rate_des = self._pid_pitch.update(sp.pitch * gain, pitch)
        yaw_rate_des = self._pid_yaw.update(self._yaw_desired, yaw)
        # The legacy pitch axis is flipped, so is its gyro (controller_pid passes -gyro.y).
        roll_out = _saturate_int16(self._pid_roll_rate.update(roll_rate_des, gyro_x))
        pitch_out = _saturate_int16(self._pid_pitch_rate.update(pitch_rate_des, -gyro_y))
        yaw_out = _saturate_int16(self._pid_yaw_rate.update(yaw_rate_des, gyro_z))
        self.control_outputs = (roll_out, pitch_out, -yaw_out)
        return thrust
