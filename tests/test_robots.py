"""Robots files: Crazyswarm2 vocabulary, precedence, validation, and the calibration write-back."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from cfknode.app.config import ConfigError, load_config
from cfknode.app.backends.robots import (
    example_robots_path,
    load_robot,
    load_robots,
    write_robot_values,
)

BASE = """\
fileversion: 3
robots:
  cf1:
    enabled: true
    uri: radio://0/80/2M/E7E7E7E701
    initial_position: [0.5, -0.25, 0.0]
    type: small
    mass: 0.031          # the robot's own value beats its type's
    battery:
      voltage_warning: 3.9
  cf2:
    uri: radio://0/80/2M/E7E7E7E702
    initial_position: [1, 2, 0]
    type: small
robot_types:
  small:
    motion_capture: {tracking: vendor}
    big_quad: false
    mass: 0.029
    thrust_max_per_motor: 0.12
    battery: {voltage_warning: 3.8, voltage_critical: 3.7, voltage_land: 3.1}
    firmware_params:
      ctrlMel: {mass: 0.029}
all:
  firmware_logging: {enabled: false}
  thrust_max_per_motor: 0.5      # lowest precedence: the type's value wins
  firmware_params:
    locSrv: {extPosStdDev: 0.001}
    ctrlMel: {mass: 0.04, kp_xy: 0.4}
  reference_frame: world
"""


def write(tmp_path: Path, text: str, name: str = "robots.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_precedence_robot_over_type_over_all(tmp_path: Path) -> None:
    robots = load_robots(write(tmp_path, BASE))
    cf1, cf2 = robots.robot("cf1"), robots.robot("cf2")
    assert cf1.mass == 0.031 and cf2.mass == 0.029  # robot > type
    assert cf1.thrust_max_per_motor == 0.12  # type > all
    assert cf1.battery.voltage_warning == 3.9 and cf1.battery.voltage_critical == 3.7  # merged key by key
    assert cf2.battery.voltage_warning == 3.8
    assert cf1.initial_position == (0.5, -0.25, 0.0)
    assert cf2.enabled  # Crazyswarm2's default
    # firmware_params merge per group and per name, the type's ctrlMel.mass over all's.
    assert dict(cf1.firmware_params) == {"locSrv.extPosStdDev": 0.001, "ctrlMel.mass": 0.029, "ctrlMel.kp_xy": 0.4}
    assert cf1.name == "cf1" and cf1.type == "small" and cf1.source == tmp_path / "robots.yaml"


def test_thrust_mapping_from_thrust_max_or_a_hover_command(tmp_path: Path) -> None:
    robots = load_robots(write(tmp_path, BASE.replace("    mass: 0.031 ", "    hover_thrust: 40000\n    mass: 0.031 ")))
    cf1, cf2 = robots.robot("cf1"), robots.robot("cf2")
    assert cf2.newton_per_cmd == pytest.approx(4 * 0.12 / 65535)
    # A calibrated hover command defines the mapping with the mass: hover * n = m g.
    assert cf1.newton_per_cmd * 40000 == pytest.approx(0.031 * 9.81)
    vehicle = cf1.vehicle(load_config().vehicle)
    assert vehicle.mass == 0.031
    assert vehicle.newton_per_cmd == pytest.approx(cf1.newton_per_cmd)
    assert vehicle.inertia == load_config().vehicle.inertia  # the rest stays


def test_packaged_example_is_valid_and_has_a_simulated_robot() -> None:
    robots = load_robots()
    assert robots.path == example_robots_path()
    assert robots.robot("cf231").uri == "radio://0/80/2M/E7E7E7E7E7"
    assert robots.robot("cf_sim").uri.startswith("sim://")
    assert not robots.robot("cf5").enabled
    assert load_config().hardware.robot in robots.robots


@pytest.mark.parametrize(
    "change, message",
    [
        (("fileversion: 3", "fileversion: 2"), "'fileversion' must be 3"),
        (("robot_types:", "robot_typos: {}\nrobot_types:"), "unknown key 'robot_typos'"),
        (("    mass: 0.031 ", "    masss: 0.031 "), "unknown key 'robots.cf1.masss'"),
        (("    type: small\n    mass", "    type: big\n    mass"), "'robots.cf1.type' is 'big'"),
        (("uri: radio://0/80/2M/E7E7E7E701", "uri: E7E7E7E701"), "'robots.cf1.uri' must be a cflib URI"),
        (("initial_position: [0.5, -0.25, 0.0]", "initial_position: [0.5, 0.0]"), "'robots.cf1.initial_position'"),
        (("    mass: 0.029", "    mass: -1"), "cf2: mass must be a number > 0"),
        (("voltage_land: 3.1", "voltage_land: 3.75"), "voltage_land < voltage_critical"),
        (("voltage_land: 3.1", "voltage_lnd: 3.1"), "unknown key 'battery.voltage_lnd'"),
        (("ctrlMel: {mass: 0.029}", "ctrlMel: {mass: fast}"), "firmware_params.ctrlMel.mass must be a number"),
        (("    thrust_max_per_motor: 0.12\n", ""), None),  # all's 0.5 then applies: still valid
    ],
)
def test_bad_files_fail_with_one_line_naming_the_key(tmp_path: Path, change: tuple[str, str], message: str | None) -> None:
    old, new = change
    assert old in BASE
    path = write(tmp_path, BASE.replace(old, new, 1))
    if message is None:
        assert load_robots(path).robot("cf1").thrust_max_per_motor == 0.5
        return
    with pytest.raises(ConfigError) as info:
        load_robots(path)
    text = str(info.value)
    assert message in text and "\n" not in text and str(path) in text


def test_missing_file_robot_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="robots file not found"):
        load_robots(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"no robot 'cf9' \(robots: cf1, cf2\)"):
        load_robot(write(tmp_path, BASE), "cf9")
    with pytest.raises(ConfigError, match=r"bad.yaml line \d+ is not valid YAML"):
        load_robots(write(tmp_path, "fileversion: 3\nrobots: [unclosed\n", "bad.yaml"))
    no_mass = BASE.replace("    mass: 0.029\n", "").replace("    mass: 0.031          # the robot's own value beats its type's\n", "")
    with pytest.raises(ConfigError, match="robot 'cf1' has no 'mass' \\(in its entry, its type or all\\)"):
        load_robots(write(tmp_path, no_mass, "nomass.yaml"))


def test_write_back_keeps_the_rest_of_the_file_and_is_atomic(tmp_path: Path) -> None:
    path = write(tmp_path, BASE)
    before = path.read_text()
    written = write_robot_values(path, "cf1", {"mass": 0.0327654321, "hover_thrust": 43210}, comment="calibrated")
    assert written == {"mass": 0.0327654, "hover_thrust": 43210}
    after = path.read_text()
    robot = load_robot(path, "cf1")
    assert (robot.mass, robot.hover_thrust) == (0.0327654, 43210)
    # Only the robot's mass line changed and one line was added; comments and the rest survive.
    old_lines, new_lines = before.splitlines(), after.splitlines()
    assert len(new_lines) == len(old_lines) + 1
    changed = [(a, b) for a, b in zip(old_lines, new_lines) if a != b]
    assert changed[0] == ("    mass: 0.031          # the robot's own value beats its type's",
                          "    mass: 0.0327654  # calibrated")
    assert "    hover_thrust: 43210  # calibrated" in new_lines
    data_before, data_after = yaml.safe_load(before), yaml.safe_load(after)
    data_before["robots"]["cf1"].update(mass=0.0327654, hover_thrust=43210)
    assert data_after == data_before
    # The other robot and the type are untouched, and no temporary file is left behind.
    assert load_robot(path, "cf2").mass == 0.029
    assert sorted(os.listdir(tmp_path)) == ["robots.yaml"]
    # Writing again replaces the same lines instead of adding more.
    write_robot_values(path, "cf1", {"mass": 0.03, "hover_thrust": 40000})
    assert len(path.read_text().splitlines()) == len(new_lines)
    # A robot that inherits everything gets its own keys.
    write_robot_values(path, "cf2", {"hover_thrust": 39000})
    assert load_robot(path, "cf2").hover_thrust == 39000
    assert load_robot(path, "cf1").hover_thrust == 40000


def test_write_back_refuses_what_it_cannot_edit_safely(tmp_path: Path) -> None:
    flow = write(tmp_path, "fileversion: 3\nrobots: {cf1: {uri: radio://0/80/2M/E7, initial_position: [0, 0, 0], "
                           "type: t}}\nrobot_types: {t: {mass: 0.03, thrust_max_per_motor: 0.12, battery: "
                           "{voltage_warning: 3.8, voltage_critical: 3.7, voltage_land: 3.1}}}\n")
    before = flow.read_text()
    with pytest.raises(ConfigError, match="block-style"):
        write_robot_values(flow, "cf1", {"mass": 0.031})
    assert flow.read_text() == before
    with pytest.raises(ConfigError, match="no robot 'cf7'"):
        write_robot_values(write(tmp_path, BASE, "b.yaml"), "cf7", {"mass": 0.031})
