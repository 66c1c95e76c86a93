"""The flight-log format shared by the writer (``flightlog``) and the reader (``logreader``).

The channel registry ``CHANNELS`` (adding a channel is one ``ChannelSpec(...)`` line),
each channel's JSON Schema, and the check of one message against it. ``channels_markdown()``
renders the registry as the table in docs/logs.md.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "CHANNELS",
    "ChannelSpec",
    "LogError",
    "MCAP_MAGIC",
    "METADATA_NAME",
    "channels_markdown",
    "check_message",
    "message_checker",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "cfknode"


class LogError(Exception):
    """A flight log cannot be written or read; the message is one line naming the file."""


# --- Channel registry --------------------------------------------------------------------------

def _num(description: str) -> dict[str, Any]:
    return {"type": "number", "description": description}


def _vec(n: int, description: str) -> dict[str, Any]:
    return {
        "type": "array",
        "items": {"type": "number"},
        "minItems": n,
        "maxItems": n,
        "description": description,
    }


def _flags(n: int, description: str) -> dict[str, Any]:
    return {**_vec(n, description), "items": {"type": "boolean"}}


def _bool(description: str) -> dict[str, Any]:
    return {"type": "boolean", "description": description}


def _str(description: str) -> dict[str, Any]:
    return {"type": "string", "description": description}


def _obj(description: str) -> dict[str, Any]:
    return {"type": "object", "description": description}


_T = _num("flight time, s (the MCAP log time is the same, in ns)")


@dataclass(frozen=True)
class ChannelSpec:
    """One topic of the flight log: its JSON Schema fields and its flush policy.

    ``flush=True`` writes the topic to disk at once (rare, precious messages: config, events,
    summary); other topics follow the periodic flush.
    """

    topic: str
    schema_name: str
    description: str
    required: Mapping[str, Mapping[str, Any]]
    optional: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    flush: bool = False

    def json_schema(self) -> dict[str, Any]:
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": self.schema_name,
            "description": self.description + " Non-finite numbers are written as null.",
            "type": "object",
            "properties": {"t": _T, **self.required, **self.optional},
            "required": ["t", *self.required],
            "additionalProperties": True,
        }


CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec(
        "/config", "cfknode.Config", "The flight's configuration and software version.",
        {"software_version": _str("cfknode version"), "config": _obj("cfknode Config.to_dict()")},
        flush=True,
    ),
    ChannelSpec(
        "/state", "cfknode.State", "State estimate used by the controller, one per tick.",
        {"p": _vec(3, "position, world, m"), "v": _vec(3, "velocity, world, m/s"),
         "q": _vec(4, "attitude quaternion body->world, w x y z")},
        {"p_true": _vec(3, "simulator: true position, m"), "v_true": _vec(3, "simulator: true velocity, m/s"),
         "q_true": _vec(4, "simulator: true attitude, w x y z"),
         "fresh": _bool("a new mocap frame arrived this tick"), "phase": _str("the supervisor's state this tick"),
         "frame_t": _num("the newest mocap frame's time, latency taken off, s"),
         "frame_p": _vec(3, "the newest mocap frame's position, unfiltered, m"),
         "imu_t": _num("the newest accelerometer sample's time, flight clock, s (null: none yet)"),
         "imu_f": _vec(3, "that sample's specific force, body frame, m/s^2 (about 0 0 9.81 at hover)")},
    ),
    ChannelSpec(
        "/reference", "cfknode.Reference", "Reference at the tick time.",
        {"p": _vec(3, "position, m"), "v": _vec(3, "velocity, m/s"), "a": _vec(3, "acceleration, m/s^2"),
         "yaw": _num("yaw, rad")},
    ),
    ChannelSpec(
        "/command", "cfknode.Command", "Command sent this tick: world acceleration and the RPYT setpoint.",
        {"acc": _vec(3, "commanded acceleration, world, m/s^2"), "roll_deg": _num("roll, deg"),
         "pitch_deg": _num("pitch, deg (cflib sign convention)"), "yawrate_deg": _num("yaw rate, deg/s"),
         "thrust": _num("thrust command, 0..65535"),
         "source": _str("which controller produced it: mpc, fallback, hold, stop, ...")},
    ),
    ChannelSpec(
        "/tick", "cfknode.Tick", "Timing of one control tick.",
        {"compute_s": _num("tick compute time, wall s"), "solve_s": _num("MPC solve time, wall s"),
         "missed": _bool("the tick missed its deadline"), "mpc_ok": _bool("the MPC solution was used")},
        {"status": _str("solver status"),
         "skipped": _num("slots the loop passed over before this tick (wall clock), each a missed deadline")},
    ),
    ChannelSpec(
        "/mocap", "cfknode.Mocap", "Motion-capture frame handed to the estimator.",
        {"received": _bool("a frame arrived (false: dropout, p and q absent)")},
        {"p": _vec(3, "position, m"), "q": _vec(4, "attitude, w x y z"),
         "stamp": _num("frame sample time, s, when it differs from t")},
    ),
    ChannelSpec(
        "/events", "cfknode.Event", "Discrete events: supervisor transitions, warnings, faults.",
        {"level": _str("debug, info, warning, error or critical"), "text": _str("what happened")},
        {"source": _str("the part that raised it"),
         "part": _str("internal errors: the part of the flight that raised"),
         "traceback": _str("internal errors: the traceback, logged once per distinct error")},
        flush=True,
    ),
    ChannelSpec(
        "/safety", "cfknode.Safety", "Safety supervisor status: at every transition and at 10 Hz.",
        {"state": _str("IDLE, PREFLIGHT, TAKEOFF, TRACK, LAND, LANDED or EMERGENCY")},
        {"reason": _str("why the supervisor is landing or stopped (empty when nominal)"),
         "pose_age_s": _num("age of the newest mocap frame, s"),
         "fence_margin_m": _num("distance inside the hard geofence, m (< 0: outside)"),
         "tracking_error_m": _num("position minus reference, m"), "battery_v": _num("filtered battery voltage, V"),
         "link_silence_s": _num("time since the radio link last answered, s"),
         "fallback_ticks": _num("MPC failures in a row (the geometric controller flew them)")},
    ),
    ChannelSpec(
        "/model", "cfknode.Model",
        "KNODE model events: a network swapped in, rejected by the gate, rolled back, dropped for nominal by the monitor, narrowed to the axes it still earns on; trainer crash or restart.",
        {"version": _num("model version the event is about (0 = nominal)"),
         "event": _str("swap, reject, rollback, drop, narrow, crash or restart")},
        {"reason": _str("why it was rejected or rolled back, or what failed"), "loss": _num("training loss"),
         "val_error": _num("validation error (online: candidate's one-step velocity RMSE on fresh data, m/s)"),
         "swap_ms": _num("time to write the solver parameters, ms"),
         "queue": {"type": "array", "items": _num("version"), "description": "versions flying after it, oldest first"},
         "round": _num("online training round"), "window": _vec(2, "training window [t0, t1], flight time s"),
         "val_error_current": _num("the flying model's one-step velocity RMSE on the same data, m/s"),
         "val_error_nominal": _num("the nominal model's one-step velocity RMSE on the same data, m/s"),
         "max_residual": _num("largest residual component on the recent data, m/s^2"),
         "val_pairs": _num("held-out pairs the gate judged on"),
         "control_gain": _vec(2, "extreme eigenvalues of sym(I + dr/du) on the envelope"),
         "velocity_gain": _num("largest eigenvalue of sym(dr/dv) on the envelope, 1/s"),
         "cross_gain": _num("largest |off-diagonal| of dr/du on the envelope"),
         "velocity_coupling": _num("largest |off-diagonal| of dr/dv on the envelope, 1/s"),
         "climb_feedback": _num("largest dr_z/dv_z on the envelope, 1/s"),
         "tilt_climb": _num("largest climb from tilting either way at the input box's top, m/s^2"),
         "train_wall_s": _num("trainer wall time of the round, s"),
         "latency_s": _num("wall time from sending the window to the result, s"),
         "install_ms": _num("gate + folding + swap, spread over tick gaps, ms"),
         "slice_ms": _num("the longest of those slices (what one tick gap absorbed), ms")},
        flush=True,
    ),
    ChannelSpec(
        "/training", "cfknode.Training", "One online training round's result (cfknode.models.trainer_process).",
        {"round": _num("training round, 1.."), "version": _num("candidate model version"),
         "window": _vec(2, "training window [t0, t1], flight time s"), "ok": _bool("the round produced a model")},
        {"base_version": _num("version the window was flown with"), "pairs": _num("training pairs"),
         "loss": _num("final data loss, (m/s^2)^2"), "val_rmse_model": _num("trainer's held-out RMSE, m/s"),
         "val_rmse_nominal": _num("nominal model's held-out RMSE, m/s"),
         "max_abs_residual": _num("largest residual on the training inputs, m/s^2"),
         "train_wall_s": _num("trainer wall time of the round, s"), "train_cpu_s": _num("trainer CPU time, s"),
         "latency_s": _num("wall time from sending the window to the result, s"),
         "t_col": _num("window length, s"), "error": _str("why the round failed (empty when ok)")},
    ),
    ChannelSpec(
        "/adaptation", "cfknode.Adaptation", "Fast adaptation estimate (flight/adaptation/), one per flown tick.",
        {"offset": _vec(3, "acceleration offset added to the model, world, m/s^2"),
         "thrust_scale": _num("estimated mass / nominal mass"), "axis_gain": _vec(2, "x, y tilt effectiveness"),
         "frozen": _bool("not updated this tick (stale mocap, near the ground, landing)"),
         "saturated": _bool("the last command was cut by the thrust clamp or the tilt limit")},
        {"f_max": _num("specific thrust at the clamp for the mass flown with, m/s^2"), "mode": _str("dob or l1"),
         "stepping": _bool("a vertical step was detected and is tracked at the step bandwidth"),
         "acts": _flags(3, "x, y, vertical: the estimate acts on the axis (else the model alone flies it)"),
         "estimate_offset": _vec(3, "the layer's offset estimate on every axis, acting or not, m/s^2"),
         "estimate_thrust_scale": _num("the layer's mass estimate, acting or not"),
         "tracking_s": _num("s the step being tracked has been tracked (0: none is)")},
    ),
    ChannelSpec(
        "/summary", "cfknode.Summary", "The flight summary (cfknode.app.ui.summary.FlightSummary.to_dict()).",
        {}, flush=True,
    ),
)


def channels_markdown(channels: tuple[ChannelSpec, ...] = CHANNELS) -> str:
    """The registry as a Markdown table (topic, schema, fields), for the README."""
    rows = ["| topic | schema | fields (optional in brackets) |", "|---|---|---|"]
    for spec in channels:
        fields = ["t", *spec.required, *(f"[{name}]" for name in spec.optional)]
        rows.append(f"| `{spec.topic}` | `{spec.schema_name}` | {', '.join(fields)} |")
    return "\n".join(rows)


def check_message(topic: str, msg: Mapping[str, Any], channels: tuple[ChannelSpec, ...] = CHANNELS) -> list[str]:
    """Problems of a message (as read back, with ``t``) against its channel's schema; [] if none.

    Checks presence of required fields, the JSON type of each known field and array lengths.
    For tests and offline checks, not the hot path.
    """
    spec = next((c for c in channels if c.topic == topic), None)
    if spec is None:
        return [f"unknown topic {topic!r}"]
    schema = spec.json_schema()
    problems = [f"{topic}: missing {name!r}" for name in schema["required"] if name not in msg]
    for name, prop in schema["properties"].items():
        if name in msg and not _matches(msg[name], prop):
            problems.append(f"{topic}: field {name!r} = {msg[name]!r} is not {prop['type']}"
                            + (f"[{prop['minItems']}]" if "minItems" in prop else ""))
    return problems


def _matches(value: Any, prop: Mapping[str, Any]) -> bool:
    kind = prop["type"]
    if kind == "number":  # null stands for a non-finite number
        return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
    if kind == "boolean":
        return isinstance(value, bool)
    if kind == "string":
        return isinstance(value, str)
    if kind == "object":
        return isinstance(value, dict)
    if kind == "array":
        return (isinstance(value, list) and prop.get("minItems", 0) <= len(value) <= prop.get("maxItems", len(value))
                and all(_matches(v, prop["items"]) for v in value))
    return True



def message_checker(topic: str, channels: tuple[ChannelSpec, ...] = CHANNELS) -> Callable[[Any], str | None]:
    """A fast check of one decoded message of ``topic``: None if usable, else what is wrong (a phrase).

    Used by the reader on every message: the payload must be an object with a numeric ``t``,
    the channel's required fields, and known fields of the right JSON type. An unknown topic
    only needs the object and ``t``.
    """
    spec = next((c for c in channels if c.topic == topic), None)
    props = dict(spec.json_schema()["properties"]) if spec is not None else {}
    props.pop("t", None)
    required = tuple(spec.required) if spec is not None else ()
    checks = tuple((name, _field_check(prop)) for name, prop in props.items())

    def check(msg: Any) -> str | None:
        if type(msg) is not dict:
            return f"not a JSON object ({type(msg).__name__})"
        t = msg.get("t")
        if type(t) is not float and type(t) is not int:
            return "missing 't'" if t is None else "'t' is not a number"
        for name in required:
            if name not in msg:
                return f"missing {name!r}"
        for name, ok in checks:
            if name in msg and not ok(msg[name]):
                return f"bad {name!r}"
        return None

    return check


def _is_number(v: Any) -> bool:
    # type() and not isinstance(): a JSON true must not pass as the number 1. An integer
    # beyond a float's range would fail every numeric use downstream.
    return v is None or type(v) is float or (type(v) is int and -1e300 < v < 1e300)


def _field_check(prop: Mapping[str, Any]) -> Callable[[Any], bool]:
    kind = prop["type"]
    if kind == "number":
        return _is_number
    if kind == "array" and prop.get("items", {}).get("type") == "number":
        lo, hi = prop.get("minItems", 0), prop.get("maxItems", 1 << 30)
        return lambda v: type(v) is list and lo <= len(v) <= hi and all(map(_is_number, v))
    return lambda v: _matches(v, prop)
