"""Checks before take-off: the trajectory fits the fence and the limits, the directories can be written."""

from __future__ import annotations

import math

import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.flight.trajectory import make_trajectory
from cfknode.app.flight_checks import refuse_unflyable
from cfknode.app.trajectory_fit import HEADROOM, fit_limits, limits_problem, trajectory_problem


def _cfg(tmp_path, **overrides):
    return load_config(overrides={"log.dir": str(tmp_path / "flights"), "safety.estop_dir": str(tmp_path / "estop"),
                                  **overrides})


@pytest.mark.parametrize("kind", ["circle", "figure8", "hover"])
def test_the_default_patterns_fit(kind, tmp_path):
    assert refuse_unflyable(_cfg(tmp_path, **{"trajectory.kind": kind})) == []
    assert (tmp_path / "flights").is_dir() and (tmp_path / "estop").is_dir()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"trajectory.height": 4.9}, "reaches z = 4.90 m, beyond the fence's 1.80 m"),
        ({"trajectory.radius": 1.4}, "reaches x = 1.40 m, beyond the fence's 1.30 m"),
        ({"trajectory.center": [-1.0, 0.0]}, "reaches x = -1.50 m, beyond the fence's -1.30 m"),
        ({"trajectory.kind": "figure8", "trajectory.radius": 1.35}, "reaches x = 1.35 m, beyond the fence's 1.30 m"),
        ({"trajectory.speed": 2.0, "trajectory.radius": 0.5}, "needs 8.00 m/s^2 sideways, a 39.2 deg tilt"),
    ],
)
def test_an_unfit_trajectory_is_refused_before_take_off(overrides, message, tmp_path):
    with pytest.raises(ConfigError) as err:
        refuse_unflyable(_cfg(tmp_path, **overrides))
    assert message in str(err.value) and str(err.value).startswith("refusing to take off: ")
    assert "\n" not in str(err.value)


def test_tilt_limit_is_the_centripetal_acceleration_against_headroom():
    # A circle at full speed needs v^2 / r sideways; the reference may use HEADROOM of tan(tilt).
    cfg = load_config(overrides={"trajectory.ramp_duration": 0.0})
    traj_cfg, g = cfg.trajectory, cfg.vehicle.gravity
    v_max = math.sqrt(HEADROOM * g * math.tan(math.radians(cfg.controller.max_tilt_deg)) * traj_cfg.radius)
    for speed, fits in ((0.97 * v_max, True), (1.03 * v_max, False)):
        c = load_config(overrides={"trajectory.ramp_duration": 0.0, "trajectory.speed": speed})
        problem = limits_problem(c, make_trajectory(c.trajectory, (0, 0, 0)), fit_limits(c))
        assert (problem is None) == fits, (speed, problem)


def test_thrust_limit_binds_on_a_heavy_vehicle():
    # 40 g on stock motors: 11.0 m/s^2 of thrust at the clamp, 10.75 usable by the reference; a
    # 5 m/s^2 circle needs sqrt(5^2 + g^2) = 11.0, within a 45 deg tilt limit.
    over = {"vehicle.mass": 0.04, "controller.max_tilt_deg": 45.0, "trajectory.radius": 0.5,
            "trajectory.speed": math.sqrt(5.0 * 0.5)}
    problem = trajectory_problem(load_config(overrides=over))
    assert problem is not None and "m/s^2 of thrust; the thrust clamp" in problem
    assert trajectory_problem(load_config(overrides={**over, "vehicle.mass": 0.029})) is None


def test_force_flies_an_unfit_trajectory_and_logs_why(tmp_path):
    events = refuse_unflyable(_cfg(tmp_path, **{"trajectory.height": 4.9, "hardware.force": True}))
    assert len(events) == 1 and events[0]["level"] == "warning"
    assert events[0]["text"].startswith("take-off FORCED despite: the trajectory")


def test_directories_that_cannot_be_written_are_refused(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    with pytest.raises(ConfigError, match=r"^log.dir .*a_file is a file, not a directory$"):
        refuse_unflyable(_cfg(tmp_path, **{"log.dir": str(a_file)}))
    with pytest.raises(ConfigError, match=r"^safety.estop_dir .*: cannot create the directory"):
        refuse_unflyable(_cfg(tmp_path, **{"safety.estop_dir": str(a_file / "sub")}))


def test_robots_file_values_are_bounded_with_the_robot_named(tmp_path):
    import dataclasses

    cfg = _cfg(tmp_path)
    bad = dataclasses.replace(cfg, safety=dataclasses.replace(cfg.safety, battery_land_v=3.9))
    with pytest.raises(ConfigError, match=r"^robot cf231: safety.battery_land_v = 3.9 V must be below"):
        refuse_unflyable(bad, where="robot cf231")


def test_a_low_thrust_to_weight_warns_before_take_off() -> None:
    from cfknode.app.flight_checks import LOW_THRUST_TO_WEIGHT, thrust_margin_warnings

    assert thrust_margin_warnings(load_config()) == []  # the Crazyflie 2.1 has about 1.5 at the clamp
    heavy = load_config(overrides={"sim.mass_changes": [{"t": 5.0, "factor": 1.33}]})
    (warning,) = thrust_margin_warnings(heavy)
    assert warning["level"] == "warning" and "1.33x mass" in warning["text"]
    assert f"below {LOW_THRUST_TO_WEIGHT}" in warning["text"]
