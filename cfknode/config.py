"""Configuration: frozen dataclasses, filled from default.yaml, a user file and CLI overrides.

The defaults live only in ``config/default.yaml`` (with their sources); the dataclasses
are the schema. A wrong key, a wrong type or a missing file raises ``ConfigError`` whose
one-line message names the key or the file.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml

Vec3 = tuple[float, float, float]


class ConfigError(ValueError):
    """A configuration problem, with a one-line message naming the key or file."""


@dataclass(frozen=True)
class VehicleConfig:
    mass: float
    inertia: Vec3
    arm_length: float
    thrust_max_per_motor: float
    thrust_cmd_clamp: int
    thrust_to_torque: float
    motor_time_constant: float
    gravity: float

    @property
    def newton_per_cmd(self) -> float:
        """Collective force per unit of thrust command (all four motors)."""
        return 4.0 * self.thrust_max_per_motor / 65535.0

    @property
    def max_thrust(self) -> float:
        """Collective force at the RPYT clamp, N."""
        return self.thrust_cmd_clamp * self.newton_per_cmd


@dataclass(frozen=True)
class ControllerConfig:
    kind: Literal["mpc", "knode-mpc", "geometric"]
    model: str
    rate_hz: float
    horizon: int
    dt: float
    solver: Literal["rti", "ipopt"]
    qp_solver: Literal["qrqp", "osqp"]
    codegen: bool
    q_position: Vec3
    q_velocity: Vec3
    r_acceleration: Vec3
    terminal_scale: float
    max_tilt_deg: float
    yaw_rate_gain: float
    max_yaw_rate_deg: float
    geometric_kp: Vec3
    geometric_kd: Vec3


@dataclass(frozen=True)
class EstimatorConfig:
    process_accel_std: float
    position_std: float
    latency: float


@dataclass(frozen=True)
class TrajectoryConfig:
    kind: Literal["hover", "circle", "figure8"]
    radius: float
    speed: float
    center: tuple[float, float]
    height: float
    duration: float
    takeoff_duration: float
    settle_duration: float
    land_duration: float
    ramp_duration: float


@dataclass(frozen=True)
class MassChange:
    t: float
    factor: float


@dataclass(frozen=True)
class SimConfig:
    seed: int
    dt: float
    realtime: bool
    initial_position: Vec3
    battery_voltage: float
    mocap_rate_hz: float
    mocap_position_noise: float
    mocap_attitude_noise: float
    mocap_latency: float
    mocap_dropout_prob: float
    mass_changes: tuple[MassChange, ...]
    wind: Vec3
    drag: Vec3


@dataclass(frozen=True)
class KnodeConfig:
    hidden: tuple[int, ...]
    activation: Literal["tanh", "softplus", "relu"]
    queue_size: int
    max_residual: float


@dataclass(frozen=True)
class TrainingConfig:
    epochs: int
    lr: float
    weight_decay: float
    method: Literal["rk4", "dopri5"]
    adjoint: bool
    seed: int
    velocity_filter_hz: float
    validation_fraction: float


@dataclass(frozen=True)
class RadioConfig:
    uri: str
    tx_rate_hz: float


@dataclass(frozen=True)
class LogConfig:
    dir: str


@dataclass(frozen=True)
class Config:
    backend: Literal["sim", "cf"]
    vehicle: VehicleConfig
    controller: ControllerConfig
    estimator: EstimatorConfig
    trajectory: TrajectoryConfig
    sim: SimConfig
    knode: KnodeConfig
    training: TrainingConfig
    radio: RadioConfig
    log: LogConfig

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))


# Checks that a type alone cannot express: (key, predicate, what it must be).
_RULES: tuple[tuple[str, Any, str], ...] = (
    ("vehicle.mass", lambda v: v > 0, "> 0"),
    ("vehicle.thrust_cmd_clamp", lambda v: 0 < v <= 65535, "in 1..65535"),
    ("controller.rate_hz", lambda v: 0 < v <= 1000, "in (0, 1000]"),
    ("controller.horizon", lambda v: 2 <= v <= 200, "in 2..200"),
    ("controller.dt", lambda v: v > 0, "> 0"),
    ("controller.max_tilt_deg", lambda v: 0 < v < 80, "in (0, 80)"),
    ("trajectory.radius", lambda v: v > 0, "> 0"),
    ("trajectory.speed", lambda v: v > 0, "> 0"),
    ("trajectory.height", lambda v: 0 < v <= 5, "in (0, 5] m"),
    ("trajectory.duration", lambda v: v >= 0, ">= 0"),
    ("trajectory.takeoff_duration", lambda v: v > 0, "> 0"),
    ("trajectory.land_duration", lambda v: v > 0, "> 0"),
    ("trajectory.settle_duration", lambda v: v >= 0, ">= 0"),
    ("trajectory.ramp_duration", lambda v: v >= 0, ">= 0"),
    ("sim.dt", lambda v: 0 < v <= 0.01, "in (0, 0.01] s"),
    ("sim.mocap_rate_hz", lambda v: 0 < v <= 1000, "in (0, 1000]"),
    ("sim.mocap_dropout_prob", lambda v: 0 <= v < 1, "in [0, 1)"),
    ("knode.queue_size", lambda v: 1 <= v <= 10, "in 1..10"),
    ("knode.hidden", lambda v: len(v) >= 1 and all(0 < h <= 1024 for h in v), "a non-empty list of widths in 1..1024"),
    ("training.epochs", lambda v: v >= 1, ">= 1"),
    ("training.lr", lambda v: v > 0, "> 0"),
    ("training.validation_fraction", lambda v: 0 < v < 1, "in (0, 1)"),
    ("radio.tx_rate_hz", lambda v: 0 < v <= 500, "in (0, 500]"),
)


def default_dict() -> dict[str, Any]:
    """The default configuration as a plain nested dict (from default.yaml)."""
    text = resources.files("cfknode").joinpath("config/default.yaml").read_text()
    return yaml.safe_load(text)


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Defaults, then the YAML file at ``path``, then dotted-key ``overrides``."""
    data = default_dict()
    if path is not None:
        data = _merge(data, _read_yaml(Path(path)), prefix="")
    for key, value in (overrides or {}).items():
        data = _merge(data, _nest(key, value), prefix="")
    return build_config(data)


def build_config(data: Mapping[str, Any]) -> Config:
    cfg = _build(Config, data, "")
    for key, ok, what in _RULES:
        value = _get(cfg, key)
        if not ok(value):
            raise ConfigError(f"config key '{key}' must be {what}, got {value!r}")
    return cfg


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``key.path=value`` (value in YAML syntax) from ``--set``."""
    if "=" not in text:
        raise ConfigError(f"--set expects key=value, got {text!r}")
    key, raw = text.split("=", 1)
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        raise ConfigError(f"--set {key}: cannot parse value {raw!r}") from None
    return key.strip(), value


def _read_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        raise ConfigError(f"config file {path}{where} is not valid YAML") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top level")
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
            raise ConfigError(f"config key '{key}' must be one of {', '.join(map(str, choices))}; got {value!r}")
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
            raise ConfigError(f"config key '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}' must be a number, got {value!r}")
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"config key '{key}' must be finite, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' must be a string, got {value!r}")
        return value
    if isinstance(tp, types.UnionType) or origin is typing.Union:
        raise TypeError(f"unsupported union in schema at {key}")
    raise TypeError(f"unsupported schema type {tp!r} at {key}")


def _get(cfg: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj
