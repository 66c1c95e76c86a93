"""Configuration: the settings dataclasses, filled from default.yaml, a user file and CLI overrides.

The defaults live in ``config/default.yaml`` (the keys a user sets) and ``config/tuning.yaml`` (the
tuning and bench keys), or on the field where it has one; the dataclasses (``cfknode.app.settings``
and each layer's ``settings``) are the schema, each field declaring its unit, bounds and meaning
(``cfknode.kernel.setting``; docs/configuration.md lists them). A wrong key, a wrong
type or a missing file raises ``ConfigError`` whose one-line message names the key or the file.
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from importlib import resources
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml

from cfknode.app.config_bounds import check_bounds
from cfknode.app.settings import Config, DashboardConfig, HardwareConfig, LogConfig, OnlineConfig, RadioConfig
from cfknode.flight.settings import ControllerConfig, EstimatorConfig, TrajectoryConfig
from cfknode.kernel.bounded_input import QUOTE_CHARS, load_yaml, quote, read_regular
from cfknode.kernel.errors import ConfigError
from cfknode.kernel.vehicle import Vec3, VehicleConfig
from cfknode.models.settings import FaultInjection, KnodeConfig, TrainingConfig
from cfknode.safety.settings import SafetyConfig
from cfknode.sim_backend.settings import FaultsConfig, FaultWindow, Gust, MassChange, SimConfig

__all__ = [
    "Config", "ConfigError", "ControllerConfig", "DashboardConfig", "EstimatorConfig", "FaultInjection", "FaultWindow",
    "FaultsConfig", "Gust", "HardwareConfig", "KnodeConfig", "LogConfig", "MassChange", "OnlineConfig", "RadioConfig",
    "SafetyConfig", "SimConfig", "TrainingConfig", "TrajectoryConfig", "Vec3", "VehicleConfig", "build_config",
    "default_dict", "dotted", "load_config", "packaged_settings", "parse_override", "read_yaml_mapping", "with_defaults",
]


# Checks that neither a type nor a declared range (``setting(low=..., high=...)``) can express:
# (key, predicate, what it must be). A plain range belongs on the field.
_RULES: tuple[tuple[str, Any, str], ...] = (
    ("controller.adaptation_settings.thrust_scale_bounds", lambda v: 0 < v[0] <= 1 <= v[1], "[low, high] with 0 < low <= 1 <= high"),
    ("controller.adaptation_settings.axis_gain_bounds", lambda v: 0.5 <= v[0] <= 1 <= v[1] <= 2, "[low, high] within [0.5, 2] around 1"),
    ("knode.hidden", lambda v: len(v) >= 1 and all(0 < h <= 1024 for h in v), "a non-empty list of widths in 1..1024"),
    ("online.gate_control_gain", lambda v: 0 < v[0] < 1 < v[1], "[low, high] with 0 < low < 1 < high"),
    ("hardware.heartbeat_hz", lambda v: v == 0 or 2 <= v <= 50, "0 (off) or in [2, 50] Hz (the firmware allows 1 s)"),
    ("fleet.ray_radio_resource", lambda v: bool(v.strip()) and not re.search(r"[{}]", v.replace("{radio}", "")),
     "a Ray resource name, where {radio} stands for the radio index"),
)


PACKAGED = ("config/default.yaml", "config/tuning.yaml")  # the keys a user sets; the tuning and bench keys


def default_dict() -> dict[str, Any]:
    """The default configuration as a plain nested dict: default.yaml and tuning.yaml, which share no key."""
    data: dict[str, Any] = {}
    for name in PACKAGED:
        data = _union(data, yaml.safe_load(resources.files("cfknode").joinpath(name).read_text()), name, "")
    return data


def _union(a: Mapping[str, Any], b: Mapping[str, Any], name: str, prefix: str) -> dict[str, Any]:
    out = dict(a)
    for key, value in b.items():
        if key not in a:
            out[key] = value
        elif isinstance(a[key], dict) and isinstance(value, dict):
            out[key] = _union(a[key], value, name, f"{prefix}{key}.")
        else:
            raise ConfigError(f"config key '{prefix}{key}' is set twice in the packaged files (again in {name})")
    return out


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Defaults, then the YAML file at ``path``, then dotted-key ``overrides``.

    The geometric controller flies without the fast layer unless the file or an override names
    ``controller.adaptation``: the default layer is the MPC's (it feeds the MPC's residual), and
    ``--controller geometric`` means the firmware's Mellinger controller alone.
    """
    data = default_dict()
    asked = False
    if path is not None:
        user = read_yaml_mapping(Path(path))
        asked = isinstance(user.get("controller"), Mapping) and "adaptation" in user["controller"]
        data = _merge(data, user, prefix="")
    for key, value in (overrides or {}).items():
        asked = asked or key == "controller.adaptation" or (key == "controller" and isinstance(value, Mapping)
                                                            and "adaptation" in value)
        data = _merge(data, _nest(key, value), prefix="")
    if not asked and isinstance(data.get("controller"), Mapping) and data["controller"].get("kind") == "geometric":
        data = _merge(data, _nest("controller.adaptation", "none"), prefix="")
    return build_config(data)


def packaged_settings(name: str) -> dict[str, Any]:
    """The dotted keys and values of the packaged partial config ``config/<name>.yaml`` (e.g. "wake")."""
    return dotted(yaml.safe_load(resources.files("cfknode").joinpath(f"config/{name}.yaml").read_text()))


def with_defaults(cfg: Config, values: Mapping[str, Any], default: Config | None = None) -> Config:
    """``cfg`` with the dotted ``values`` wherever it keeps the packaged default (``default``, built here when
    None): defaults of a context, under the settings a user gave, e.g. a fleet drone learning a wake."""
    default = default if default is not None else load_config()
    data = cfg.to_dict()
    for key, value in values.items():
        changed = _merge(data, _nest(key, value), prefix="")  # an unknown key is refused here, in one line
        if _get(cfg, key) == _get(default, key):
            data = changed
    return build_config(data)


def dotted(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested config mapping as dotted keys and their leaf values (a list is one leaf), in file order."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(dotted(value, f"{prefix}{key}.") if isinstance(value, Mapping) else {f"{prefix}{key}": value})
    return out


def build_config(data: Mapping[str, Any]) -> Config:
    cfg = _build(Config, data, "")
    check_bounds(cfg)
    for key, ok, what in _RULES:
        value = _get(cfg, key)
        if not ok(value):
            raise ConfigError(f"config key '{key}' must be {what}, got {quote(value)}")
    return cfg


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``key.path=value`` (value in YAML syntax) from ``--set``."""
    if "=" not in text:
        raise ConfigError(f"--set expects key=value, got {quote(text)}")
    key, raw = text.split("=", 1)
    try:
        value = load_yaml(raw, ConfigError, "the value")
    except ConfigError as exc:
        raise ConfigError(f"--set {key.strip()[:QUOTE_CHARS]}: cannot parse value {quote(raw)}: {exc}") from None
    return key.strip(), value


# Config and robots files are a few kB; a cap keeps a huge or endless file from filling memory.
MAX_YAML_BYTES = 1 << 20


def read_yaml_mapping(path: Path, what: str = "config file") -> dict[str, Any]:
    """A YAML file holding a mapping; a missing file or bad YAML is a one-line ConfigError naming it."""
    if not (path.exists() or path.is_symlink()):
        raise ConfigError(f"{what} not found: {path}")
    raw = read_regular(path, MAX_YAML_BYTES, ConfigError, what)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} {path} is not UTF-8 text (byte {exc.start})") from None
    data = load_yaml(text, ConfigError, f"{what} {path}")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{what} {path} must hold a mapping at the top level")
    return data


def _nest(dotted: str, value: Any) -> dict[str, Any]:
    out: Any = value
    for part in reversed(dotted.split(".")):
        out = {part: out}
    return out


def _merge(base: dict[str, Any], new: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    out = dict(base)
    for key, value in new.items():
        dotted = f"{prefix}{key}"
        if key not in base:
            raise ConfigError(f"unknown config key '{dotted}'")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise ConfigError(f"config key '{dotted}' must be a mapping, got {type(value).__name__}")
            out[key] = _merge(base[key], value, prefix=f"{dotted}.")
        else:
            out[key] = value
    return out


def _build(cls: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"config key '{prefix.rstrip('.') or '<top>'}' must be a mapping")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            raise ConfigError(f"unknown config key '{prefix}{key}'")
    kwargs = {}
    for name in names:
        dotted = f"{prefix}{name}"
        if name not in data:
            raise ConfigError(f"missing config key '{dotted}'")
        kwargs[name] = _coerce(hints[name], data[name], dotted)
    return cls(**kwargs)


def _coerce(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, f"{key}.")
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ConfigError(f"config key '{key}' must be one of {', '.join(map(str, choices))}; got {quote(value)}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{key}' must be a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"config key '{key}' must have {len(args)} elements, got {len(value)}")
        return tuple(_coerce(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}' must be true or false, got {quote(value)}")
        return value
    if tp in (int, float) and isinstance(value, str) and _NUMBER.fullmatch(value.strip()):
        # YAML reads 1e-9 (an exponent without a decimal point) as a string.
        number = float(value)
        value = int(number) if tp is int and number.is_integer() else number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' must be an integer, got {quote(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}' must be a number, got {quote(value)}")
        try:
            value = float(value)
        except OverflowError:
            raise ConfigError(f"config key '{key}' must be finite, got {quote(value)}") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"config key '{key}' must be finite, got {quote(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' must be a string, got {quote(value)}")
        return value
    if isinstance(tp, types.UnionType) or origin is typing.Union:
        args = tuple(a for a in typing.get_args(tp) if a is not type(None))
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            # ``X | None``: YAML null means "not set" (e.g. the vehicle's value applies).
            return None if value is None else _coerce(args[0], value, key)
        raise TypeError(f"unsupported union in schema at {key}")
    raise TypeError(f"unsupported schema type {tp!r} at {key}")


_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")


def _get(cfg: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg
