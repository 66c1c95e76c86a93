"""Physical bounds and cross-key checks: unsafe values are refused at load, in one line with key and unit."""

from __future__ import annotations

import dataclasses
import types
import typing

import pytest

from cfknode.app.config import Config, ConfigError, load_config, parse_override
from cfknode.app.config_bounds import BOUNDS, Bound, leaves


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"controller.rate_hz": 1}, "controller.rate_hz = 1 is out of range: must be 50 to 1000 Hz"),
        ({"vehicle.gravity": -9.81}, "vehicle.gravity = -9.81 is out of range: must be 9 to 10.5 m/s^2"),
        ({"vehicle.gravity": 0}, "vehicle.gravity = 0 is out of range: must be 9 to 10.5 m/s^2"),
        ({"sim.drag": [-1, -1, -1]}, "sim.drag[0] = -1 is out of range: must be 0 to 1 N/(m/s)"),
        ({"controller.dt": 100}, "controller.dt = 100 is out of range: must be above 0 and at most 0.5 s"),
        ({"controller.q_position": [60, -1, 80]}, "controller.q_position[1] = -1 is out of range: must be 0 to"),
        ({"controller.q_velocity": [-4, 4, 6]}, "controller.q_velocity[0] = -4 is out of range"),
        ({"controller.r_acceleration": [0.2, 0.2, -0.2]}, "controller.r_acceleration[2] = -0.2 is out of range"),
        ({"vehicle.motor_time_constant": 0}, "vehicle.motor_time_constant = 0 is out of range: must be 0.005 to 0.2 s"),
        ({"radio.tx_rate_hz": 0.1}, "radio.tx_rate_hz = 0.1 is out of range: must be 20 to 500 Hz"),
        ({"safety.battery_land_v": 100}, "safety.battery_land_v = 100 is out of range: must be 3 to 4.35 V"),
        ({"safety.touchdown_height": -1},
         "safety.touchdown_height = -1 is out of range: must be above 0 and at most 0.2 m"),
        ({"controller.max_yaw_rate_deg": -1},
         "controller.max_yaw_rate_deg = -1 is out of range: must be above 0 and at most 360 deg/s"),
        ({"training.epochs": 10**9}, "training.epochs = 1000000000 is out of range: must be 1 to 100000"),
        ({"training.epochs": "1e9"}, "training.epochs = 1000000000 is out of range: must be 1 to 100000"),
        ({"sim.mass_changes": [{"t": 1.0, "factor": 0.0}]},
         "sim.mass_changes[0].factor = 0 is out of range: must be 0.25 to 4 x nominal mass"),
        ({"vehicle.inertia": [1.66e-5, 0, 2.93e-5]},
         "vehicle.inertia[1] = 0 is out of range: must be 5e-06 to 0.0005 kg m^2"),
        ({"vehicle.thrust_max_per_motor": 0},
         "vehicle.thrust_max_per_motor = 0 is out of range: must be 0.05 to 0.5 N"),
        ({"estimator.position_std": 0}, "estimator.position_std = 0 is out of range: must be 1e-05 to 0.1 m"),
        ({"sim.battery_voltage": 5.0}, "sim.battery_voltage = 5 is out of range: must be 3 to 4.35 V"),
        ({"safety.fence_max": [1.5, 1.5, 200.0]}, "safety.fence_max[2] = 200 is out of range: must be -50 to 50 m"),
        ({"faults.gusts": [{"t": 1.0, "duration": 1.0, "wind": [0, 0, 99]}]},
         "faults.gusts[0].wind[2] = 99 is out of range: must be -20 to 20 m/s"),
    ],
)
def test_unsafe_values_are_refused_with_key_bound_and_unit(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_config(overrides=overrides)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"safety.battery_land_v": 3.8},
         "safety.battery_land_v = 3.8 V must be below safety.battery_takeoff_min_v = 3.7 V"),
        ({"controller.rate_hz": 50, "safety.solve_deadline_s": 0.01},
         "radio.tx_rate_hz = 100 Hz must be at most controller.rate_hz = 50 Hz"),
        ({"vehicle.mass": 0.05}, "vehicle cannot hover"),
        ({"controller.max_tilt_deg": 50, "safety.max_tilt_deg": 45}, "controller.max_tilt_deg = 50 deg must be below"),
        ({"controller.dt": 0.001}, "controller.dt = 0.001 s must be at least one control tick"),
        ({"controller.horizon": 200, "controller.dt": 0.1},
         "controller.horizon x controller.dt = 20 s is out of range"),
        ({"controller.rate_hz": 1000}, "safety.solve_deadline_s = 0.002 s must be at most one control tick"),
        ({"safety.fence_min": [2.0, -1.5, -0.2]},
         "safety.fence_min x = 2 m must be below safety.fence_max x = 1.5 m"),
        ({"safety.touchdown_height": 0.2, "trajectory.height": 0.15}, "safety.touchdown_height = 0.2 m must be below"),
        ({"online.rollback_ticks": 2, "online.rollback_fallbacks": 3}, "online.rollback_fallbacks = 3 must be at most"),
    ],
)
def test_cross_key_checks(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_config(overrides=overrides)
    assert message in str(err.value)


def _numeric_keys(cls: type, prefix: str = "") -> list[str]:
    """Every dotted key of the schema that holds numbers (directly, in a list, or in list records)."""
    out = []
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        args = typing.get_args(tp)
        if isinstance(tp, types.UnionType) and len(args) == 2 and type(None) in args:  # ``X | None``
            tp = args[0] if args[1] is type(None) else args[1]
            args = typing.get_args(tp)
        inner = args[0] if typing.get_origin(tp) is tuple and args else tp
        if dataclasses.is_dataclass(tp):
            out += _numeric_keys(tp, f"{prefix}{f.name}.")
        elif dataclasses.is_dataclass(inner):
            out += _numeric_keys(inner, f"{prefix}{f.name}.")
        elif inner in (int, float) or (typing.get_origin(tp) is tuple
                                       and all(a in (int, float, Ellipsis) for a in args)):
            out.append(f"{prefix}{f.name}")
    return out


def test_every_numeric_key_has_a_bound_and_the_defaults_are_inside():
    keys = _numeric_keys(Config)
    assert len(keys) > 100
    assert sorted(set(keys) - set(BOUNDS)) == []
    assert sorted(set(BOUNDS) - set(keys)) == []  # no stale entries
    cfg = load_config()
    for key, bound in BOUNDS.items():
        for label, value in leaves(cfg, key):
            assert value is None or bound.contains(value), (label, value)


@pytest.mark.parametrize("key, high", [("sim.motor_time_constant", 0.3),
                                       ("controller.adaptation_settings.thrust_lag_s", 0.5)])
def test_an_optional_number_is_bounded_when_set_and_free_when_null(key, high):
    load_config(overrides={key: None})
    load_config(overrides={key: high})
    with pytest.raises(ConfigError, match=f"{key} = {high * 2:g} is out of range: must be 0 to {high:g} s"):
        load_config(overrides={key: high * 2})


def test_bound_descriptions():
    assert Bound(50, 1000, "Hz").describe() == "50 to 1000 Hz"
    assert Bound(0, 0.5, "s", low_open=True).describe() == "above 0 and at most 0.5 s"
    assert Bound(0, 1, high_open=True).describe() == "at least 0 and below 1"
    assert Bound(-float("inf"), 3600, "s").describe() == "at most 3600 s"
    assert not Bound(0, 1, low_open=True).contains(0.0) and Bound(0, 1).contains(0.0)


def test_exponents_without_a_decimal_point_are_numbers():
    key, value = parse_override("controller.dt=4e-2")
    assert value == "4e-2"  # YAML 1.1 reads it as a string ...
    assert load_config(overrides={key: value}).controller.dt == 0.04  # ... the schema makes it a number
    assert load_config(overrides={"training.epochs": "1e3"}).training.epochs == 1000
    with pytest.raises(ConfigError) as err:
        load_config(overrides=dict([parse_override("controller.dt=1e-9")]))
    assert "must be a number" not in str(err.value)
    assert "controller.dt = 1e-09 s must be at least one control tick" in str(err.value)
    with pytest.raises(ConfigError, match="'controller.dt' must be a number"):
        load_config(overrides={"controller.dt": "1e-9s"})
    with pytest.raises(ConfigError, match="'training.epochs' must be an integer"):
        load_config(overrides={"training.epochs": "1.5e0"})


def test_file_values_are_bounded_too_and_a_non_utf8_file_is_one_line(tmp_path):
    f = tmp_path / "my.yaml"
    f.write_text("vehicle:\n  gravity: 0\n")
    with pytest.raises(ConfigError, match=r"vehicle.gravity = 0 is out of range"):
        load_config(f)
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(b"vehicle:\n  mass: 0.03 # \xff\xfe\n")
    with pytest.raises(ConfigError) as err:
        load_config(bad)
    assert "latin1.yaml is not UTF-8 text" in str(err.value) and "\n" not in str(err.value)
