"""Replay: run a controller offline on a flight log's states and references, and compare commands.

For each tick whose command came from the controller (``/command`` source mpc, fallback or
geometric), the logged estimate (``/state`` p, v, q) and the tick time are fed to the same
parts the loop uses: the reference preview is sampled from the trajectory rebuilt from the
logged config, the MPC solves (falling back to the geometric controller when it fails, as
the loop does), and the Mellinger layer turns the acceleration into a setpoint. The result
holds the logged and replayed commands side by side.

The MPC is deterministic, and replaying visits the same ticks in the same order, so its warm
start (and a KNODE model's linearisation points, ``flight.model_slot``) follows the flight's:
with the flight's controller config a nominal flight replays to the last bit (JSON keeps
floats exact). A different solver (``--solver ipopt``), another
setting (``--set controller.q_position=...``) or a KNODE model (``--model``) shows how that
controller would have commanded the same states. It is open loop: the states stay the logged
ones, so differences do not compound.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cfknode.app.config import Config, ConfigError, build_config, default_dict
from cfknode.app.logs.reader import LogData
from cfknode.kernel.imu import ImuSample

__all__ = [
    "COMMAND_FIELDS",
    "ReplayError",
    "ReplayResult",
    "ResidualModel",
    "load_residual_model",
    "logged_config",
    "plot_replay",
    "replay_log",
    "write_csv",
]

# Compared per tick: world acceleration and the RPYT setpoint, with their units.
COMMAND_FIELDS: tuple[tuple[str, str], ...] = (
    ("acc_x", "m/s^2"), ("acc_y", "m/s^2"), ("acc_z", "m/s^2"),
    ("roll_deg", "deg"), ("pitch_deg", "deg"), ("yawrate_deg", "deg/s"), ("thrust", "cmd"),
)
CONTROLLER_SOURCES = ("mpc", "fallback", "geometric", "brake")


class ReplayError(ValueError):
    """A replay that cannot run (no states in the log, an unusable model); one line."""


@dataclass(frozen=True)
class _LoggedState:
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    t: float = 0.0
    frame: tuple[float, np.ndarray] | None = None  # the newest mocap frame the fast layer read (logs that have it)
    imu: ImuSample | None = None  # the accelerometer sample the tick saw (logs that have it)


class ResidualModel(Protocol):
    """What replay needs from a KNODE queue (``cfknode.models.residual_np.ResidualQueue``)."""

    def linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ReplayResult:
    t: np.ndarray  # (n,) tick times replayed
    logged: np.ndarray  # (n, 7) in COMMAND_FIELDS order
    replayed: np.ndarray  # (n, 7)
    logged_source: tuple[str, ...]  # per tick
    replayed_source: tuple[str, ...]
    skipped: Mapping[str, int]  # ticks not replayed, by logged source (cutoff, no_state, ...)
    reference_mismatch_m: float  # largest |rebuilt reference - logged reference| at node 0
    controller: str  # e.g. "mpc rti-qrqp-codegen"
    model: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def ticks(self) -> int:
        return len(self.t)

    @property
    def difference(self) -> np.ndarray:
        return self.replayed - self.logged

    def rms(self) -> dict[str, float]:
        """Root mean square of replayed - logged per field (NaN rows skipped)."""
        return {name: _rms(self.difference[:, i]) for i, (name, _) in enumerate(COMMAND_FIELDS)}

    def max_abs(self) -> dict[str, float]:
        d = np.abs(self.difference)
        return {name: _nanmax(d[:, i]) for i, (name, _) in enumerate(COMMAND_FIELDS)}

    def source_changes(self) -> int:
        """Ticks where the replay used another controller than the flight (e.g. fell back)."""
        return sum(a != b for a, b in zip(self.logged_source, self.replayed_source))


def logged_config(log: LogData, overrides: Mapping[str, Any] | None = None) -> tuple[Config, list[str]]:
    """The flight's config from its log, on top of today's defaults, then dotted ``overrides``.

    Keys the log has that the schema no longer knows are left out and returned (so old logs
    still replay); keys it lacks take today's defaults. Raises ``ConfigError`` for a bad override.
    """
    if log.config is None:
        why = "; ".join(log.damage.warnings) or "no /config message or metadata"
        raise ReplayError(f"{log.path}: the log holds no configuration ({why})")
    dropped: list[str] = []
    data = _overlay(default_dict(), log.config, "", dropped)
    if not overrides:
        try:
            return build_config(data), dropped
        except ConfigError as exc:  # the file's fault, not the command line's: name the file
            raise ReplayError(f"{log.path}: the logged configuration is invalid: {exc}") from None
    for key, value in overrides.items():
        _set_dotted(data, key, value)
    return build_config(data), dropped


def load_residual_model(path: str | Path) -> tuple[ResidualModel, str]:
    """A KNODE model file's residual queue and a one-line description; ``ReplayError`` if unusable."""
    try:
        from cfknode.models.modelfile import ModelFileError, load_model
        from cfknode.models.residual_np import ResidualQueue
    except ImportError as exc:
        raise ReplayError(f"--model needs cfknode.models.modelfile and residual_np, missing here ({exc})") from None
    try:
        model = load_model(path)
    except ModelFileError as exc:
        raise ReplayError(str(exc)) from None
    queue = ResidualQueue.from_model_file(model)
    version = model.extra.get("version") if isinstance(model.extra, Mapping) else None
    desc = f"{Path(path).name}: {len(model.networks)} network(s), hidden {list(model.hidden)} {model.activation}"
    return queue, desc + (f", version {version}" if version is not None else "")


def replay_log(
    log: LogData, cfg: Config, model: ResidualModel | None = None, model_name: str | None = None,
    trajectory: Any = None,
) -> ReplayResult:
    """Run ``cfg``'s controller on every controller tick of ``log``; see the module docstring.

    The fast layer (``controller.adaptation``) is fed what it read in flight (fresh frames, the supervisor's
    phase, the newest frame, the accelerometer sample), so a flight replays exactly. Replayed with another model, the layer re-estimates
    from states those commands never flew and takes out part of what the model changes: compare models on a
    flight flown with ``controller.adaptation: none``, or replay with ``--set controller.adaptation=none``.

    ``trajectory``: the reference flown (default: rebuilt from ``cfg``; a fleet drone's is its own).
    """
    from cfknode.flight.controller import Controller
    from cfknode.flight.model_slot import ModelSlot
    from cfknode.flight.trajectory import make_trajectory

    states = {m["t"]: m for m in log.topic("/state")}
    refs = {m["t"]: m for m in log.topic("/reference")}
    commands = log.topic("/command")
    if not states or not commands:
        raise ReplayError(f"{log.path.name}: no /state or /command messages to replay")
    ctrl = cfg.controller
    if model is not None and ctrl.kind == "geometric":
        raise ReplayError("--model needs the MPC controller (controller.kind mpc), the log flew geometric")
    slot = ModelSlot(model, version=1) if model is not None else None
    controller = Controller(ctrl, cfg.vehicle, model=slot)
    controller.prepares_after_send = True  # as the flight loop: prepare() after each controller tick
    if trajectory is None:
        trajectory = make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float))

    rows_t: list[float] = []
    logged: list[list[float]] = []
    replayed: list[list[float]] = []
    logged_src: list[str] = []
    replayed_src: list[str] = []
    skipped: dict[str, int] = {}
    mismatch = 0.0
    followed = 0
    for cmd in commands:
        t, source = cmd["t"], cmd.get("source", "")
        state = states.get(t)
        if source not in CONTROLLER_SOURCES or state is None:
            skipped[source or "unknown"] = skipped.get(source or "unknown", 0) + 1
            if source == "blind":  # what the flight did to the controller on such ticks
                controller.reset()
            elif source != "stop":
                controller.idle()
            continue
        est = _logged_state(state, t)
        ref = trajectory.sample(controller.preview_times(t))
        if t in refs:
            mismatch = max(mismatch, float(np.max(np.abs(ref.p[0] - np.asarray(refs[t]["p"], dtype=float)))))
        # A tick that fell back in flight while the replayed solve succeeds missed its deadline
        # on the wall clock: it is flown as the flight flew it (geometric).
        command = controller.step(t, est, ref, force_fallback=source == "fallback",
                                  pose_fresh=bool(state.get("fresh", True)), phase=str(state.get("phase") or "TRACK"),
                                  brake_tilt_deg=cfg.safety.fence_brake_tilt_deg if source == "brake" else None)
        controller.prepare()
        followed += source == "fallback" and command.status == "deadline"
        acc, sp = command.acc, command.setpoint
        rows_t.append(t)
        logged.append([*_vector3(cmd.get("acc")), *(_float(cmd.get(k)) for k in
                                                    ("roll_deg", "pitch_deg", "yawrate_deg", "thrust"))])
        replayed.append([float(acc[0]), float(acc[1]), float(acc[2]), sp.roll_deg, sp.pitch_deg, sp.yawrate_deg,
                         float(sp.thrust)])
        logged_src.append(source)
        replayed_src.append(command.source)
    if not rows_t:
        raise ReplayError(f"{log.path.name}: no tick has both a state and a controller command")
    notes = _notes(followed, mismatch)
    label = f"{ctrl.kind} {controller.backend}" if controller.solver is not None else ctrl.kind
    return ReplayResult(
        t=np.asarray(rows_t), logged=np.asarray(logged, dtype=float), replayed=np.asarray(replayed, dtype=float),
        logged_source=tuple(logged_src), replayed_source=tuple(replayed_src), skipped=skipped,
        reference_mismatch_m=mismatch, controller=label, model=model_name, notes=tuple(notes),
    )


def _logged_state(state: dict[str, Any], t: float) -> _LoggedState:
    """The estimate a tick flew on, as its /state message logged it."""
    frame = (float(state["frame_t"]), np.asarray(state["frame_p"], dtype=float)) if "frame_t" in state else None
    return _LoggedState(np.asarray(state["p"], dtype=float), np.asarray(state["v"], dtype=float),
                        np.asarray(state["q"], dtype=float), t, frame, _logged_imu(state))


def _notes(followed: int, mismatch: float) -> list[str]:
    """Why replayed commands may differ from the logged ones."""
    notes = []
    if followed:
        notes.append(f"{followed} tick(s) fell back in flight (deadline) but solve in replay; flown as in flight")
    if mismatch > 1e-6:
        notes.append(f"the reference rebuilt from the config differs from the logged one by up to {mismatch:.3g} m "
                     "(clamped in flight, or another start pose): commands will differ")
    return notes


def write_csv(result: ReplayResult, path: str | Path) -> Path:
    """One row per replayed tick: t, both sources, then logged_* and replay_* for each field."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [name for name, _ in COMMAND_FIELDS]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t", "logged_source", "replay_source", *(f"logged_{n}" for n in names),
                         *(f"replay_{n}" for n in names)])
        for i in range(result.ticks):
            values = (*result.logged[i], *result.replayed[i])
            writer.writerow([repr(float(result.t[i])), result.logged_source[i], result.replayed_source[i],
                             *(repr(float(v)) for v in values)])
    return path


def plot_replay(result: ReplayResult, path: str | Path, title: str = "") -> Path:
    """PNG: logged and replayed commands against time, one panel per field."""
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(11, 9), layout="constrained")
    axes = fig.subplots(4, 2, sharex=True).ravel()
    rms = result.rms()
    for i, (name, unit) in enumerate(COMMAND_FIELDS):
        ax = axes[i]
        ax.plot(result.t, result.logged[:, i], color="0.55", lw=2.2, label="logged")
        ax.plot(result.t, result.replayed[:, i], color="tab:blue", lw=0.9, label="replayed")
        ax.set_ylabel(f"{name} [{unit}]")
        ax.set_title(f"RMS difference {rms[name]:.3g} {unit}", fontsize=9, loc="right")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    ax = axes[-1]
    ax.plot(result.t, np.linalg.norm(result.difference[:, :3], axis=1), color="tab:red", lw=0.8)
    ax.set_ylabel("|acc difference| [m/s^2]")
    ax.grid(alpha=0.3)
    for ax in axes[-2:]:
        ax.set_xlabel("flight time [s]")
    fig.suptitle(title or f"replay: {result.controller}" + (f" + {result.model}" if result.model else ""))
    fig.savefig(path, dpi=90)
    return path


def _overlay(base: dict[str, Any], logged: Mapping[str, Any], prefix: str, dropped: list[str]) -> dict[str, Any]:
    out = dict(base)
    for key, value in logged.items():
        if key not in base:
            dropped.append(prefix + key)
        elif isinstance(base[key], dict) and isinstance(value, Mapping):
            out[key] = _overlay(base[key], value, f"{prefix}{key}.", dropped)
        else:
            out[key] = value
    return out


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    node = data
    for i, part in enumerate(parents):
        child = node.get(part)
        if not isinstance(child, dict):
            raise ConfigError(f"unknown config key '{'.'.join(parents[:i + 1])}'")
        node = child
    if leaf not in node:
        raise ConfigError(f"unknown config key '{key}'")
    node[leaf] = value


def _logged_imu(state: Mapping[str, Any]) -> ImuSample | None:
    """The accelerometer sample a tick saw; None where it saw none (null) or the log predates the field."""
    t, f = state.get("imu_t"), state.get("imu_f")
    if t is None or f is None or not math.isfinite(float(t)):
        return None
    force = _vector3(f)
    return ImuSample(float(t), np.asarray(force, dtype=float)) if all(map(math.isfinite, force)) else None


def _vector3(value: Any) -> list[float]:
    if not isinstance(value, Sequence) or len(value) != 3:
        return [math.nan] * 3
    return [_float(v) for v in value]


def _float(value: Any) -> float:
    return math.nan if value is None else float(value)


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if len(x) else math.nan


def _nanmax(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.max()) if len(x) else math.nan
