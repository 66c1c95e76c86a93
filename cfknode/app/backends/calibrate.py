"""``cfknode calibrate --backend cf``: the hover thrust command and the mass, from a short hover.

The robot flies the normal stack (``--backend cf``, the supervisor, the MPC) on a hover
trajectory. In steady hover the collective force balances the weight, so from the logged
thrust commands ``T`` and attitudes (body z axis ``R33``) on the hover window, with the
vertical acceleration ``a_z`` fitted from the logged velocity (about zero):

    m (g + a_z) = n * mean(T R33)      ->   hover command = mean(T R33) g / (g + a_z)

where ``n`` is the robot's thrust mapping in N per command. A hover alone cannot separate
the mass from the thrust scale: the mass is reported in the robot's current mapping
(``thrust_max_per_motor``, or a previous calibration), and the hover command, which is what
the thrust mapping needs, is measured directly. Both are written into the robot's own entry
of the robots file; with ``hover_thrust`` set, the robot's mapping is ``mass g / hover_thrust``.
"""

from __future__ import annotations

import dataclasses
import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cfknode.app.config import Config, ConfigError
from cfknode.app.logs.reader import LogData, read_log
from cfknode.flight.trajectory import make_trajectory
from cfknode.app.backends.robots import Robot, load_robot, write_robot_values

MAX_HOVER_SPEED = 0.1  # m/s: samples faster than this are not steady hover
MIN_SAMPLES = 100  # ticks on the hover window (0.25 s at 400 Hz)
SETTLE_FRACTION = 0.3  # of the hover window skipped at its start (the take-off transient)
MAX_SETTLE_S = 1.0


class CalibrationError(RuntimeError):
    """The hover gave nothing usable; one line saying why."""


@dataclass(frozen=True)
class HoverEstimate:
    hover_thrust: int  # command that hovers the robot
    mass: float  # kg, in the thrust mapping below
    newton_per_cmd: float  # the thrust mapping the mass is expressed in
    samples: int
    window: tuple[float, float]  # flight time of the samples used
    thrust_std: float  # of T * R33 on the window: how steady the hover was
    vertical_acc: float  # m/s^2 fitted on the window (should be ~0)


@dataclass(frozen=True)
class CalibrationResult:
    robot: str
    estimate: HoverEstimate
    previous_mass: float
    previous_hover_thrust: int | None
    written: dict[str, float | int] | None  # what went into the robots file (None: not written)
    robots_file: Path
    log_path: str

    @property
    def message(self) -> str:
        e = self.estimate
        where = f"written to {self.robots_file}" if self.written else "not written"
        return (f"{self.robot}: hover thrust {e.hover_thrust}, mass {e.mass * 1e3:.1f} g "
                f"(was {self.previous_mass * 1e3:.1f} g) from {e.samples} ticks; {where}")


def calibration_config(cfg: Config, *, height: float = 0.5, hover_s: float = 4.0) -> Config:
    """The run's config with a hover trajectory of ``hover_s`` seconds at ``height``."""
    traj = dataclasses.replace(cfg.trajectory, kind="hover", height=height, duration=hover_s)
    return dataclasses.replace(cfg, trajectory=traj, backend="cf")


def hover_window(cfg: Config) -> tuple[float, float]:
    """Flight times of steady hover in the calibration trajectory (the start position only
    shifts it in space, so the nominal one gives the times)."""
    t0, t1 = make_trajectory(cfg.trajectory, np.zeros(3)).pattern_window
    return t0 + min(MAX_SETTLE_S, SETTLE_FRACTION * (t1 - t0)), t1


def estimate_hover(
    log: LogData, window: tuple[float, float], newton_per_cmd: float, gravity: float,
    thrust_clamp: int = 60000,
) -> HoverEstimate:
    """Hover command and mass from a flight log's ``/command`` and ``/state`` on ``window``."""
    cmd, state = log.topic("/command"), log.topic("/state")
    if not cmd or not state:
        raise CalibrationError(f"{log.path.name}: the log has no commands or states to calibrate from")
    t_cmd = log.times("/command")
    t_state = log.times("/state")
    _, ic, is_ = np.intersect1d(t_cmd, t_state, return_indices=True)
    t = t_cmd[ic]
    thrust = log.array("/command", "thrust")[ic]
    v = log.array("/state", "v")[is_]
    q = log.array("/state", "q")[is_]
    r33 = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
    steady = (t >= window[0]) & (t <= window[1]) & (np.linalg.norm(v, axis=1) < MAX_HOVER_SPEED) & (thrust > 0)
    n = int(steady.sum())
    if n < MIN_SAMPLES:
        raise CalibrationError(f"only {n} steady-hover ticks in {window[0]:.1f}-{window[1]:.1f} s "
                               f"(need {MIN_SAMPLES}): the hover was not steady; fly longer or check the mocap")
    if np.any(thrust[steady] >= thrust_clamp):
        raise CalibrationError(f"the thrust reached the clamp ({thrust_clamp}) while hovering: the robot is too heavy "
                               "for its motors, or the thrust mapping is far off")
    ts = t[steady]
    a_z = float(np.polyfit(ts - ts[0], v[steady, 2], 1)[0]) if ts[-1] > ts[0] else 0.0
    lift = thrust[steady] * r33[steady]
    hover = float(lift.mean()) * gravity / (gravity + a_z)
    return HoverEstimate(
        hover_thrust=int(round(hover)),
        mass=newton_per_cmd * hover / gravity,
        newton_per_cmd=newton_per_cmd,
        samples=n,
        window=(float(ts[0]), float(ts[-1])),
        thrust_std=float(lift.std()),
        vertical_acc=a_z,
    )


FlyFunction = Callable[[Config, str], Any]  # (config, name hint) -> result with .summary.log_path


def calibrate(
    cfg: Config,
    *,
    write: bool = True,
    height: float = 0.5,
    hover_s: float = 4.0,
    fly: FlyFunction | None = None,
) -> CalibrationResult:
    """Fly the hover with ``fly`` (default: ``cfknode.app.mission.run_flight``), estimate, and
    write ``mass`` and ``hover_thrust`` into the robot's entry of ``hardware.robots_file``."""
    if write and not cfg.hardware.robots_file:
        raise ConfigError("calibrate writes into your robots file: set hardware.robots_file (--robots-file FILE); "
                          "the packaged example is not edited")
    robot = load_robot(cfg.hardware.robots_file or None, cfg.hardware.robot)
    hover_cfg = calibration_config(cfg, height=height, hover_s=hover_s)
    if fly is None:
        from cfknode.app.mission import run_flight as fly
    result = fly(hover_cfg, "calibrate")
    log_path = str(result.summary.log_path)
    estimate = estimate_hover(read_log(log_path), hover_window(hover_cfg), robot.newton_per_cmd,
                              cfg.vehicle.gravity, cfg.vehicle.thrust_cmd_clamp)
    written = None
    if write:
        stamp = datetime.datetime.now().isoformat(timespec="seconds")
        written = write_robot_values(robot.source, robot.name,
                                     {"mass": estimate.mass, "hover_thrust": estimate.hover_thrust},
                                     comment=f"cfknode calibrate {stamp}")
    return CalibrationResult(
        robot=robot.name,
        estimate=estimate,
        previous_mass=robot.mass,
        previous_hover_thrust=robot.hover_thrust,
        written=written,
        robots_file=robot.source,
        log_path=log_path,
    )


def expected_hover_thrust(robot: Robot, gravity: float = 9.81) -> float:
    """The hover command the robots file predicts (for the operator's comparison)."""
    return robot.mass * gravity / robot.newton_per_cmd


__all__ = ["CalibrationError", "CalibrationResult", "HoverEstimate", "calibrate", "calibration_config",
           "estimate_hover", "expected_hover_thrust", "hover_window"]
