"""Config loading: defaults, user files, overrides, and one-line errors naming the key or file."""

import pytest

from cfknode.app.config import ConfigError, load_config, parse_override


def test_defaults_load_and_are_frozen():
    cfg = load_config()
    assert cfg.backend == "sim"
    assert cfg.trajectory.kind == "circle" and cfg.trajectory.radius == 0.5 and cfg.trajectory.speed == 0.4
    assert cfg.controller.rate_hz == 400
    with pytest.raises(AttributeError):
        cfg.trajectory.radius = 1.0  # type: ignore[misc]


def test_vehicle_thrust_facts():
    v = load_config().vehicle
    # docs/hardware.md#thrust-map: F_total ~ cmd * 7.32e-6 N, and hover at 29 g needs about 38,800.
    assert v.newton_per_cmd == pytest.approx(7.32e-6, rel=2e-3)
    assert v.mass * v.gravity / v.newton_per_cmd == pytest.approx(38_800, rel=0.01)
    assert v.max_thrust / (v.mass * v.gravity) == pytest.approx(1.5, abs=0.06)


def test_user_file_and_overrides(tmp_path):
    f = tmp_path / "my.yaml"
    f.write_text("trajectory:\n  radius: 0.8\n  kind: figure8\nsim:\n  mass_changes: [{t: 2.0, factor: 0.5}]\n")
    cfg = load_config(f, {"trajectory.radius": 0.9})
    assert cfg.trajectory.radius == 0.9 and cfg.trajectory.kind == "figure8"
    assert cfg.sim.mass_changes[0].t == 2.0 and cfg.sim.mass_changes[0].factor == 0.5


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        ({"trajectory.radiuss": 1.0}, "unknown config key 'trajectory.radiuss'"),
        ({"trajectory.radius": "big"}, "'trajectory.radius' must be a number"),
        ({"controller.solver": "magic"}, "'controller.solver' must be one of"),
        ({"controller.horizon": 2.5}, "'controller.horizon' must be an integer"),
        ({"sim.realtime": "yes"}, "'sim.realtime' must be true or false"),
        ({"vehicle.inertia": [1, 2]}, "'vehicle.inertia' must have 3 elements"),
        ({"trajectory.radius": -1.0}, "trajectory.radius = -1 is out of range: must be 0.05 to 5 m"),
        ({"sim.mass_changes": [{"t": 1.0}]}, "missing config key 'sim.mass_changes[0].factor'"),
        ({"trajectory": 3}, "'trajectory' must be a mapping"),
    ],
)
def test_errors_name_the_key(overrides, fragment):
    with pytest.raises(ConfigError) as err:
        load_config(overrides=overrides)
    assert fragment in str(err.value)
    assert "\n" not in str(err.value)


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(ConfigError, match="config file not found: .*nope.yaml"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("trajectory: [unclosed\n")
    with pytest.raises(ConfigError, match="bad.yaml line"):
        load_config(bad)
    listy = tmp_path / "list.yaml"
    listy.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load_config(listy)


def test_parse_override():
    assert parse_override("trajectory.radius=0.7") == ("trajectory.radius", 0.7)
    assert parse_override("sim.wind=[1, 0, 0]") == ("sim.wind", [1, 0, 0])
    with pytest.raises(ConfigError):
        parse_override("noequals")
