"""Robots files in Crazyswarm2's vocabulary: which Crazyflie, where, and its physical numbers.

A robots file has ``fileversion``, ``robots`` (name -> entry), ``robot_types`` and ``all``.
A robot's settings are the deep merge of ``all``, then its type, then its own entry (the
robot wins, as in Crazyswarm2). The robot's name is its mocap rigid-body name.

cfknode reads ``uri``, ``initial_position``, ``enabled``, ``type``, ``mass``,
``thrust_max_per_motor``, ``hover_thrust``, ``battery`` and ``firmware_params``; the other
Crazyswarm2 keys are accepted and left alone, and anything else is a one-line
``ConfigError`` naming the file and the key (a typo must not silently fall back to a default).

``write_robot_values`` edits one robot's entry in place (``cfknode calibrate``), keeping the
rest of the file byte for byte, comments included, and replaces the file atomically.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tempfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import yaml

from cfknode.app.config import MAX_YAML_BYTES, ConfigError, VehicleConfig, read_yaml_mapping
from cfknode.kernel.bounded_input import quote, read_regular

FILEVERSION = 3
CMD_FULL_SCALE = 65535  # the motor command at which a motor gives thrust_max_per_motor

# Keys per level: ours, plus the Crazyswarm2 keys a shared file may carry.
_OURS = {"uri", "initial_position", "enabled", "type", "mass", "thrust_max_per_motor", "hover_thrust",
         "battery", "firmware_params"}
_CRAZYSWARM = {"firmware_logging", "reference_frame", "motion_capture", "big_quad", "broadcasts",
               "initial_orientation", "connection"}
_LEVEL_KEYS = {
    "robots": _OURS | _CRAZYSWARM,
    "robot_types": _OURS - {"uri", "initial_position", "type"} | _CRAZYSWARM,
    "all": _OURS - {"uri", "initial_position", "type"} | _CRAZYSWARM,
}
_TOP_KEYS = ("fileversion", "robots", "robot_types", "all")
_BATTERY_KEYS = ("voltage_warning", "voltage_critical", "voltage_land")


@dataclass(frozen=True)
class BatteryLimits:
    """Volts. Idle pre-flight: warn below ``voltage_warning``, refuse below ``voltage_critical``.
    In flight (the voltage sags under load): land below ``voltage_land``."""

    voltage_warning: float
    voltage_critical: float
    voltage_land: float


@dataclass(frozen=True)
class Robot:
    name: str  # also the mocap rigid-body name
    uri: str
    initial_position: tuple[float, float, float]
    type: str
    enabled: bool
    mass: float  # kg
    thrust_max_per_motor: float  # N at command 65535, as configured
    hover_thrust: int | None  # calibrated hover command; defines the thrust mapping when set
    battery: BatteryLimits
    firmware_params: Mapping[str, float]  # "group.name" -> value, applied in this order
    source: Path  # the robots file

    @property
    def newton_per_cmd(self) -> float:
        """Collective force per unit thrust command: from the hover calibration if there is one."""
        if self.hover_thrust is not None:
            return self.mass * _G / self.hover_thrust
        return 4.0 * self.thrust_max_per_motor / CMD_FULL_SCALE

    @property
    def effective_thrust_max_per_motor(self) -> float:
        """Per-motor force at full command implied by ``newton_per_cmd``."""
        return self.newton_per_cmd * CMD_FULL_SCALE / 4.0

    def vehicle(self, base: VehicleConfig) -> VehicleConfig:
        """``base`` with this robot's mass and thrust mapping."""
        return dataclasses.replace(base, mass=self.mass, thrust_max_per_motor=self.effective_thrust_max_per_motor)


_G = 9.81  # only to turn a calibrated hover command back into N per command (vehicle.gravity is 9.81 too)


@dataclass(frozen=True)
class RobotsFile:
    path: Path
    robots: Mapping[str, Robot]
    data: Mapping[str, Any]  # the parsed file, for tools that need the raw entries

    def robot(self, name: str) -> Robot:
        if name not in self.robots:
            known = ", ".join(sorted(self.robots)) or "none"
            raise ConfigError(f"robots file {self.path}: no robot {quote(name)} (robots: {known})")
        return self.robots[name]


def example_robots_path() -> Path:
    """The packaged example robots file."""
    return Path(str(resources.files("cfknode").joinpath("config/robots.yaml")))


def load_robots(path: str | Path | None = None) -> RobotsFile:
    """Read and validate every robot of a robots file (``None`` or "" = the packaged example)."""
    file = Path(path) if path else example_robots_path()
    data = _read(file)
    where = str(file)
    if data.get("fileversion") != FILEVERSION:
        raise ConfigError(f"robots file {where}: 'fileversion' must be {FILEVERSION}, got {quote(data.get('fileversion'))}")
    for key in data:
        if key not in _TOP_KEYS:
            raise ConfigError(f"robots file {where}: unknown key '{key}' (expected {', '.join(_TOP_KEYS)})")
    robots = _mapping(data.get("robots"), where, "robots")
    types = _mapping(data.get("robot_types", {}), where, "robot_types")
    common = _mapping(data.get("all", {}), where, "all")
    _check_keys(common, "all", where, "all")
    for type_name, entry in types.items():
        _check_keys(_mapping(entry, where, f"robot_types.{type_name}"), "robot_types", where, f"robot_types.{type_name}")
    resolved = {}
    for name, entry in robots.items():
        entry = _mapping(entry, where, f"robots.{name}")
        _check_keys(entry, "robots", where, f"robots.{name}")
        resolved[str(name)] = _resolve(str(name), entry, types, common, file)
    return RobotsFile(path=file, robots=resolved, data=data)


def load_robot(path: str | Path | None, name: str) -> Robot:
    return load_robots(path).robot(name)


def _read(file: Path) -> dict[str, Any]:
    return read_yaml_mapping(file, "robots file")


def _mapping(value: Any, where: str, key: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"robots file {where}: '{key}' must be a mapping, got {type(value).__name__}")
    return value


def _check_keys(entry: Mapping[str, Any], level: str, where: str, key: str) -> None:
    for k in entry:
        if k not in _LEVEL_KEYS[level]:
            raise ConfigError(f"robots file {where}: unknown key '{key}.{k}'")


def _deep_merge(low: Mapping[str, Any], high: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(low)
    for k, v in high.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def _resolve(name: str, entry: Mapping[str, Any], types: Mapping[str, Any], common: Mapping[str, Any],
             file: Path) -> Robot:
    where = str(file)
    key = f"robots.{name}"
    type_name = entry.get("type")
    if not isinstance(type_name, str):
        raise ConfigError(f"robots file {where}: '{key}.type' must name an entry of robot_types")
    if type_name not in types:
        raise ConfigError(f"robots file {where}: '{key}.type' is {quote(type_name)}, which is not in robot_types")
    merged = _deep_merge(_deep_merge(common, types[type_name] or {}), entry)

    def need(k: str) -> Any:
        if k not in merged or merged[k] is None:
            raise ConfigError(f"robots file {where}: robot {quote(name)} has no '{k}' (in its entry, its type or all)")
        return merged[k]

    uri = need("uri")
    if not isinstance(uri, str) or not re.match(r"^[a-z]+://", uri):
        raise ConfigError(f"robots file {where}: '{key}.uri' must be a cflib URI like radio://0/80/2M/E7E7E7E7E7")
    position = need("initial_position")
    if not isinstance(position, (list, tuple)) or len(position) != 3 or not all(_is_number(v) for v in position):
        raise ConfigError(f"robots file {where}: '{key}.initial_position' must be [x, y, z] in m")
    enabled = merged.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"robots file {where}: '{key}.enabled' must be true or false")
    mass = _positive(need("mass"), where, f"{name}: mass")
    thrust_max = _positive(need("thrust_max_per_motor"), where, f"{name}: thrust_max_per_motor")
    hover = merged.get("hover_thrust")
    if hover is not None and (isinstance(hover, bool) or not isinstance(hover, int) or not 0 < hover <= CMD_FULL_SCALE):
        raise ConfigError(f"robots file {where}: robot {quote(name)} hover_thrust must be an integer command in "
                          f"1..{CMD_FULL_SCALE}, got {quote(hover)}")
    battery = _battery(_mapping(need("battery"), where, f"{key}.battery"), where, name)
    params = _flatten_params(_mapping(merged.get("firmware_params", {}), where, f"{key}.firmware_params"),
                             where, name)
    return Robot(
        name=name,
        uri=uri,
        initial_position=tuple(float(v) for v in position),
        type=type_name,
        enabled=enabled,
        mass=mass,
        thrust_max_per_motor=thrust_max,
        hover_thrust=hover,
        battery=battery,
        firmware_params=params,
        source=file,
    )


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _positive(v: Any, where: str, what: str) -> float:
    if not _is_number(v) or v <= 0:
        raise ConfigError(f"robots file {where}: {what} must be a number > 0, got {quote(v)}")
    return float(v)


def _battery(entry: Mapping[str, Any], where: str, name: str) -> BatteryLimits:
    for k in entry:
        if k not in _BATTERY_KEYS:
            raise ConfigError(f"robots file {where}: unknown key 'battery.{k}' for robot {quote(name)}")
    values = {}
    for k in _BATTERY_KEYS:
        v = entry.get(k)
        if not _is_number(v) or not 2.5 <= v <= 4.5:
            raise ConfigError(f"robots file {where}: robot {quote(name)} battery.{k} must be a voltage in 2.5..4.5 V, got {quote(v)}")
        values[k] = float(v)
    limits = BatteryLimits(**values)
    if not limits.voltage_land < limits.voltage_critical <= limits.voltage_warning:
        raise ConfigError(f"robots file {where}: robot {quote(name)} battery needs voltage_land < voltage_critical "
                          f"<= voltage_warning, got {limits.voltage_land}, {limits.voltage_critical}, "
                          f"{limits.voltage_warning}")
    return limits


def _flatten_params(params: Mapping[str, Any], where: str, name: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for group, entries in params.items():
        if not isinstance(entries, dict):
            raise ConfigError(f"robots file {where}: robot {quote(name)} firmware_params.{group} must be a mapping of name: value")
        for param, value in entries.items():
            if isinstance(value, bool):
                value = int(value)
            if not _is_number(value):
                raise ConfigError(f"robots file {where}: robot {quote(name)} firmware_params.{group}.{param} must be a number")
            out[f"{group}.{param}"] = value
    return out


# --- writing calibrated values back -------------------------------------------------------------


def write_robot_values(
    path: str | Path, name: str, values: Mapping[str, float | int], comment: str = ""
) -> dict[str, float | int]:
    """Set ``values`` (key -> number) in robot ``name``'s own entry, keeping everything else.

    The file is edited as text, so comments and layout survive; the result is parsed back
    and must differ from the original exactly in those keys, or nothing is written. The new
    file replaces the old one atomically (same directory, fsync, ``os.replace``). Returns the
    values as written (floats to 6 significant digits).
    """
    file = Path(path)
    original = _read(file)
    if name not in _mapping(original.get("robots"), str(file), "robots"):
        raise ConfigError(f"robots file {file}: no robot {quote(name)} to update")
    written = {k: yaml.safe_load(_yaml_number(v)) for k, v in values.items()}
    text = read_regular(file, MAX_YAML_BYTES, ConfigError, "robots file").decode("utf-8")  # _read checked it is UTF-8
    new_text = _set_robot_keys(text, name, values, comment, file)
    try:
        updated = yaml.safe_load(new_text)
    except yaml.YAMLError:
        raise ConfigError(f"robots file {file}: could not update robot {quote(name)} safely; edit it by hand") from None
    expected = _deep_merge(original, {"robots": {name: written}})
    if updated != expected:
        raise ConfigError(f"robots file {file}: could not update robot {quote(name)} safely; edit it by hand: "
                          + ", ".join(f"{k}: {v}" for k, v in values.items()))
    _atomic_write(file, new_text)
    return written


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _is_content(line: str) -> bool:
    stripped = line.strip()
    return bool(stripped) and not stripped.startswith("#")


def _set_robot_keys(text: str, name: str, values: Mapping[str, float | int], comment: str, file: Path) -> str:
    lines = text.splitlines(keepends=True)
    newline = "\r\n" if lines and lines[0].endswith("\r\n") else "\n"
    top = next((i for i, ln in enumerate(lines) if re.match(r"^robots:\s*(#.*)?$", ln.rstrip("\r\n"))), None)
    if top is None:
        raise ConfigError(f"robots file {file}: no block-style 'robots:' section to update")
    # The robots' own indentation, then the robot's line and its block.
    body = [i for i in range(top + 1, len(lines)) if _is_content(lines[i])]
    if not body or _indent(lines[body[0]]) == 0:
        raise ConfigError(f"robots file {file}: 'robots:' has no entries")
    robot_indent = _indent(lines[body[0]])
    start = None
    for i in body:
        ind = _indent(lines[i])
        if ind == 0:
            break
        if ind == robot_indent and re.match(rf"^\s*{re.escape(name)}\s*:\s*(#.*)?$", lines[i].rstrip("\r\n")):
            start = i
            break
    if start is None:
        raise ConfigError(f"robots file {file}: robot {quote(name)} is not a block-style entry under 'robots:'")
    end = start + 1  # one past the block's last content line
    child_indent = None
    for i in range(start + 1, len(lines)):
        if not _is_content(lines[i]):
            continue
        if _indent(lines[i]) <= robot_indent:
            break
        child_indent = child_indent if child_indent is not None else _indent(lines[i])
        end = i + 1
    if child_indent is None:
        child_indent = robot_indent + 2
    suffix = f"  # {comment}" if comment else ""
    for key, value in values.items():
        new_line = f"{' ' * child_indent}{key}: {_yaml_number(value)}{suffix}{newline}"
        pattern = re.compile(rf"^ {{{child_indent}}}{re.escape(key)}\s*:")
        hit = next((i for i in range(start + 1, end) if pattern.match(lines[i])), None)
        if hit is not None:
            lines[hit] = new_line
        else:
            lines.insert(end, new_line)
            end += 1
    if not lines[-1].endswith(("\n", "\r")):
        lines[-1] += newline
    return "".join(lines)


def _yaml_number(value: float | int) -> str:
    """A YAML 1.1 number: PyYAML reads "1e-05" as a string, so a mantissa always has a dot."""
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    text = format(float(value), ".6g")
    mantissa, e, exponent = text.partition("e")
    if "." not in mantissa and mantissa.lstrip("-").isdigit():
        mantissa += ".0"
    return mantissa + (f"e{exponent}" if e else "")


def _atomic_write(file: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{file.name}.", suffix=".tmp", dir=file.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.chmod(tmp, file.stat().st_mode & 0o777)
        except OSError:
            pass
        os.replace(tmp, file)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
