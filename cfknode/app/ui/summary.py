"""The flight summary: tracking error on the pattern window, tick timing, run speed.

The tracking metric is the paper's: the mean over time of the squared position error, per
axis, and averaged over the three axes ("MSE"). It is computed on the pattern window (the
circle, figure-8 or hover, without take-off and landing) and over the whole flight.
Percentiles use numpy's default (linear interpolation between order statistics).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from cfknode.app.logs.reader import LogData
from cfknode.flight.recovery import RECOVERY_THRESHOLD_M, step_recoveries

__all__ = [
    "FlightSummary",
    "TickSeries",
    "TrackingError",
    "compute_summary",
    "brief_rows",
    "drone_row",
    "render",
    "render_brief",
    "render_summary",
    "summary_from_dict",
    "summary_from_log",
    "summary_to_json",
    "tracking_error",
]


@dataclass(frozen=True)
class TrackingError:
    """Position error statistics over a set of samples (NaN when there are none)."""

    samples: int
    mse_xyz: tuple[float, float, float]  # m^2, mean over time of the squared error per axis
    mse: float  # m^2, mean of mse_xyz (the paper's metric)
    rms: float  # m, sqrt of the mean squared error norm
    max: float  # m, largest error norm


@dataclass(frozen=True)
class FlightSummary:
    """Everything `cfknode fly` reports about one flight. All times in the units named."""

    window: tuple[float, float]  # pattern window [t0, t1], flight time s
    window_samples: int
    mse_x: float  # m^2, on the pattern window
    mse_y: float
    mse_z: float
    mse: float  # m^2, mean over the axes (the paper's metric), on the pattern window
    rms_error: float  # m, on the pattern window
    max_error: float  # m, on the pattern window
    flight_mse_x: float  # m^2, over the whole flight
    flight_mse_y: float
    flight_mse_z: float
    flight_mse: float
    flight_rms_error: float
    flight_max_error: float
    ticks: int
    missed_deadlines: int  # slots whose command was late (a tick over its slot) or never sent (a slot passed over)
    compute_median_ms: float
    compute_p99_ms: float
    compute_max_ms: float
    solve_median_ms: float  # over ticks that ran a solve (finite, > 0 solve time)
    solve_p99_ms: float
    duration_s: float  # simulated (flight clock) time covered
    wall_time_s: float
    speed_factor: float  # simulated seconds per wall second
    log_path: str | None
    skipped_slots: int = 0  # wall clock: slots the loop passed over (counted in missed_deadlines; none in lockstep)
    extra: dict[str, Any] = field(default_factory=dict)
    # Per mass step (simulation): {"t", "factor", "time_to_recover_s" (None: never), "peak_error_m"}; see recovery.py
    recovery: tuple[dict[str, Any], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-safe dict: lists for tuples, None for non-finite numbers."""
        return _json_safe(dataclasses.asdict(self))


def tracking_error(p: np.ndarray, p_ref: np.ndarray) -> TrackingError:
    """Error statistics of positions ``p`` against ``p_ref`` (both (n, 3)); rows with NaN are skipped."""
    p = np.asarray(p, dtype=float).reshape(-1, 3)
    p_ref = np.asarray(p_ref, dtype=float).reshape(-1, 3)
    if p.shape != p_ref.shape:
        raise ValueError(f"p {p.shape} and p_ref {p_ref.shape} differ in shape")
    err = p - p_ref
    err = err[np.isfinite(err).all(axis=1)]
    if len(err) == 0:
        nan = math.nan
        return TrackingError(0, (nan, nan, nan), nan, nan, nan)
    sq = err * err
    mse_xyz = sq.mean(axis=0)
    norm_sq = sq.sum(axis=1)
    return TrackingError(
        samples=len(err),
        mse_xyz=(float(mse_xyz[0]), float(mse_xyz[1]), float(mse_xyz[2])),
        mse=float(mse_xyz.mean()),
        rms=float(math.sqrt(norm_sq.mean())),
        max=float(math.sqrt(norm_sq.max())),
    )


@dataclass(frozen=True)
class TickSeries:
    """A flight's per-tick arrays, as ``compute_summary`` reads them (``FlightRecord`` has the same fields)."""

    t: np.ndarray
    p: np.ndarray
    p_ref: np.ndarray
    compute_s: np.ndarray
    solve_s: np.ndarray
    missed: np.ndarray
    skipped: np.ndarray | None = None  # slots passed over before each tick (wall clock); None: none


def compute_summary(
    ticks: Any,
    window: tuple[float, float],
    wall_time: float,
    log_path: str | None = None,
    *,
    duration: float | None = None,
    extra: Mapping[str, Any] | None = None,
    steps: Sequence[tuple[float, float]] = (),
    recovery_margin_s: float = 0.0,
) -> FlightSummary:
    """Summarise a flight from per-tick arrays (pure).

    ``ticks``: a ``TickSeries`` or a ``FlightRecord``. ``t`` (n,), ``p`` (n, 3) true position in simulation or the estimate, ``p_ref`` (n, 3).
    ``compute_s``, ``solve_s``, ``missed`` and ``skipped`` are per tick (any common length; a NaN or zero
    solve time means no solve ran that tick); a deadline is missed by a late tick and by each slot passed
    over. ``window`` selects t0 <= t <= t1 for the pattern metrics. ``duration`` defaults to the span of
    ``t``. ``steps``: (time, mass factor) of the simulator's mass changes; each gets its time to recover
    and peak error, judged until the next step or ``recovery_margin_s`` before the pattern's end (an MPC
    brakes for the pattern's end one preview horizon early, which is not the step's doing).
    """
    t = np.asarray(ticks.t, dtype=float).reshape(-1)
    p = np.asarray(ticks.p, dtype=float).reshape(-1, 3)
    p_ref = np.asarray(ticks.p_ref, dtype=float).reshape(-1, 3)
    if not len(t) == len(p) == len(p_ref):
        raise ValueError(f"t, p and p_ref must have the same length, got {len(t)}, {len(p)}, {len(p_ref)}")
    compute_s = np.asarray(ticks.compute_s, dtype=float).reshape(-1)
    solve_s = np.asarray(ticks.solve_s, dtype=float).reshape(-1)
    missed = np.asarray(ticks.missed, dtype=bool).reshape(-1)
    if len(missed) != len(compute_s):
        raise ValueError(f"missed ({len(missed)}) and compute_s ({len(compute_s)}) must have the same length")
    skipped = np.zeros(len(missed), dtype=int) if ticks.skipped is None else np.asarray(ticks.skipped).reshape(-1)
    if len(skipped) != len(missed):
        raise ValueError(f"skipped ({len(skipped)}) and missed ({len(missed)}) must have the same length")
    t0, t1 = float(window[0]), float(window[1])
    if t1 < t0:
        raise ValueError(f"window end {t1} is before its start {t0}")

    in_window = (t >= t0) & (t <= t1)
    pattern = tracking_error(p[in_window], p_ref[in_window])
    whole = tracking_error(p, p_ref)
    compute_ms = _finite(compute_s) * 1e3
    solve_ms = _finite(solve_s)
    solve_ms = solve_ms[solve_ms > 0] * 1e3
    if duration is None:
        duration = float(t[-1] - t[0]) if len(t) else 0.0
    err = np.linalg.norm(p - p_ref, axis=1) if len(t) else np.zeros(0)
    recoveries = tuple(r.to_dict() for r in step_recoveries(t, err, steps, t1 - recovery_margin_s))
    return FlightSummary(
        window=(t0, t1),
        window_samples=pattern.samples,
        mse_x=pattern.mse_xyz[0],
        mse_y=pattern.mse_xyz[1],
        mse_z=pattern.mse_xyz[2],
        mse=pattern.mse,
        rms_error=pattern.rms,
        max_error=pattern.max,
        flight_mse_x=whole.mse_xyz[0],
        flight_mse_y=whole.mse_xyz[1],
        flight_mse_z=whole.mse_xyz[2],
        flight_mse=whole.mse,
        flight_rms_error=whole.rms,
        flight_max_error=whole.max,
        ticks=len(compute_s),
        missed_deadlines=int(missed.sum() + skipped.sum()),
        compute_median_ms=_percentile(compute_ms, 50),
        compute_p99_ms=_percentile(compute_ms, 99),
        compute_max_ms=float(compute_ms.max()) if len(compute_ms) else math.nan,
        solve_median_ms=_percentile(solve_ms, 50),
        solve_p99_ms=_percentile(solve_ms, 99),
        duration_s=float(duration),
        wall_time_s=float(wall_time),
        speed_factor=float(duration) / wall_time if wall_time > 0 else math.nan,
        log_path=log_path,
        skipped_slots=int(skipped.sum()),
        extra=dict(extra or {}),
        recovery=recoveries,
    )


def summary_from_log(
    log: LogData,
    window: tuple[float, float] | None = None,
    wall_time: float | None = None,
    use_true: bool = True,
) -> FlightSummary:
    """Recompute a summary from a flight log (for replay and plots; works on truncated logs).

    Positions are the simulator's true ones when logged and ``use_true``, else the estimate,
    matched to ``/reference`` by tick time. ``window`` and ``wall_time`` default to the values
    in the log's ``/summary`` message, else the whole flight and NaN.
    """
    logged = log.topic("/summary")
    previous = logged[-1] if logged else {}
    states, refs, ticks = log.topic("/state"), log.topic("/reference"), log.topic("/tick")
    t_state = log.times("/state")
    field_name = "p_true" if use_true and states and all("p_true" in m for m in states) else "p"
    p = log.array("/state", field_name) if states else np.zeros((0, 3))
    p_ref = log.array("/reference", "p") if refs else np.zeros((0, 3))
    t, i_state, i_ref = np.intersect1d(t_state, log.times("/reference"), return_indices=True)
    if window is None:
        window = tuple(previous["window"]) if "window" in previous else (
            (float(t[0]), float(t[-1])) if len(t) else (0.0, 0.0))
    if wall_time is None:
        wall_time = previous.get("wall_time_s") or math.nan
    extra = {"recomputed_from": str(log.path), "positions": field_name}
    if log.truncated:
        extra["truncated"] = True
    t_ticks = log.times("/tick")
    return compute_summary(
        TickSeries(
            t=t,
            p=p[i_state],
            p_ref=p_ref[i_ref],
            compute_s=log.array("/tick", "compute_s") if ticks else np.zeros(0),
            solve_s=log.array("/tick", "solve_s") if ticks else np.zeros(0),
            missed=log.array("/tick", "missed") if ticks else np.zeros(0, dtype=bool),
            skipped=np.array([m.get("skipped", 0) for m in ticks], dtype=int),
        ),
        window=window,
        wall_time=wall_time,
        log_path=str(log.path),
        duration=float(t_ticks[-1] - t_ticks[0]) if len(t_ticks) else None,
        extra=extra,
    )


def summary_to_json(summary: FlightSummary) -> str:
    """One-line JSON object (non-finite numbers as null), for `cfknode fly --json`."""
    return json.dumps(summary.to_dict(), allow_nan=False)


def summary_from_dict(data: Mapping[str, Any]) -> FlightSummary:
    """Inverse of ``FlightSummary.to_dict`` (null numbers come back as NaN)."""
    names = {f.name for f in dataclasses.fields(FlightSummary)}
    unknown = set(data) - names - {"t"}
    if unknown:
        raise ValueError(f"unknown flight-summary fields: {sorted(unknown)}")
    values: dict[str, Any] = {}
    for f in dataclasses.fields(FlightSummary):
        if f.name not in data:
            if f.name in ("extra", "recovery"):
                continue
            raise ValueError(f"flight summary lacks field {f.name!r}")
        value = data[f.name]
        if f.name == "window":
            value = tuple(math.nan if v is None else float(v) for v in value)
        elif f.name == "recovery":
            value = tuple(dict(v) for v in value)
        elif value is None and f.name not in ("log_path",):
            value = math.nan
        values[f.name] = value
    return FlightSummary(**values)


def render_summary(summary: FlightSummary, console: Console) -> None:
    """Print the summary as a rich table."""
    s = summary
    table = Table(title="Flight summary", show_header=True, header_style="bold")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("unit")

    t0, t1 = s.window
    table.add_row(f"[bold]pattern window[/] {t0:.2f}-{t1:.2f} s", f"{s.window_samples}", "samples")
    table.add_row("MSE x / y / z", " / ".join(_g(v) for v in (s.mse_x, s.mse_y, s.mse_z)), "m^2")
    table.add_row("[bold]MSE[/] (mean over axes)", f"[bold]{_g(s.mse)}[/]", "m^2")
    table.add_row("RMS / max error", f"{_g(s.rms_error)} / {_g(s.max_error)}", "m")
    table.add_section()
    table.add_row("[bold]whole flight[/]", "", "")
    table.add_row("MSE x / y / z", " / ".join(_g(v) for v in (s.flight_mse_x, s.flight_mse_y, s.flight_mse_z)), "m^2")
    table.add_row("MSE (mean over axes)", _g(s.flight_mse), "m^2")
    table.add_row("RMS / max error", f"{_g(s.flight_rms_error)} / {_g(s.flight_max_error)}", "m")
    if s.recovery:
        table.add_section()
        table.add_row(f"[bold]mass steps[/] (recovered: error < {100 * RECOVERY_THRESHOLD_M:g} cm to the next step)", "", "")
        for r in s.recovery:
            ttr = r.get("time_to_recover_s")
            table.add_row(f"{r['factor']:g}x at {r['t']:.2f} s: time to recover / peak error",
                          f"{'never' if ttr is None else f'{ttr:.2f}'} / {_g(r.get('peak_error_m'))}", "s / m")
    table.add_section()
    missed = f"{s.missed_deadlines} / {s.ticks + s.skipped_slots}"
    if s.skipped_slots:
        missed += f" ({s.skipped_slots} passed over)"
    table.add_row("missed deadlines / slots", f"[red]{missed}[/]" if s.missed_deadlines else missed, "")
    table.add_row("tick compute median / p99 / max",
                  " / ".join(_ms(v) for v in (s.compute_median_ms, s.compute_p99_ms, s.compute_max_ms)), "ms")
    table.add_row("MPC solve median / p99", f"{_ms(s.solve_median_ms)} / {_ms(s.solve_p99_ms)}", "ms")
    table.add_section()
    table.add_row("simulated duration", f"{s.duration_s:.2f}", "s")
    table.add_row("wall time", f"{s.wall_time_s:.2f}", "s")
    table.add_row("speed", _g(s.speed_factor, 3), "x real time")
    for key, value in s.extra.items():
        table.add_row(str(key), _g(value) if isinstance(value, float) else str(value), "")
    if s.log_path:
        table.add_row("log", s.log_path, "")
    console.print(table)


def brief_rows(summary: FlightSummary) -> list[str]:
    """The summary at a glance: at most eleven rows of at most 80 columns (a long log path aside).

    What a person checks after a flight; every other number is in ``--json``, the log's
    ``/summary`` and ``render_summary`` (``--verbose``).
    """
    s, x = summary, summary.extra
    t0, t1 = s.window
    rows = [f"Flight summary (pattern {t0:.1f}-{t1:.1f} s)",
            _row("tracking", f"MSE {_e(s.mse)} m^2, max error {_mm(s.max_error)}"),
            _row("tick compute", f"median {_ms(s.compute_median_ms)} ms, p99 {_ms(s.compute_p99_ms)} ms"),
            _row("missed", f"{s.missed_deadlines} of {s.ticks + s.skipped_slots} deadlines"),
            _row("speed", f"{_g(s.speed_factor, 3)}x real time" + (", lockstep" if x.get("lockstep") else ""))]
    if "models_accepted" in x:
        rows.append(_row("models", f"{x['models_accepted']} accepted of {x.get('models_trained', '?')} trained"))
    if x.get("learned_model"):  # beside the log: its name is enough
        rows.append(_row("learned model", f"kept as {Path(str(x['learned_model'])).name}"))
    if isinstance(x.get("adaptation_thrust_scale_end"), (int, float)):
        rows.append(_row("mass estimate", f"{x['adaptation_thrust_scale_end']:.3f} x nominal "
                                          f"(fast layer, {x.get('adaptation', '?')})"))
    if s.recovery:
        rows.append(_row("mass steps", _steps_text(s.recovery)))
    attention = _attention(x)
    if attention:
        rows.append(_row("attention", attention))
    rows.append(_row("log", str(s.log_path)))
    return rows


def render(summary: FlightSummary, console: Console, verbose: bool = False) -> None:
    """What ``cfknode fly`` prints: the rows at a glance, or with ``verbose`` every row."""
    (render_summary if verbose else render_brief)(summary, console)


def render_brief(summary: FlightSummary, console: Console) -> None:
    """Print ``brief_rows`` as plain lines (no table frame: rows, not borders, are what a person reads)."""
    for n, row in enumerate(brief_rows(summary)):
        console.print(f"[bold]{row}[/]" if n == 0 else row, highlight=False, soft_wrap=True, markup=n == 0)


def drone_row(name: str, summary: FlightSummary, outcome: str) -> str:
    """One fleet drone in one line: its tracking, tick timing, models accepted (of the wake above, for a drone
    whose networks learn it) and outcome."""
    s = summary
    models = s.extra.get("models_accepted")
    kind = " wake" if s.extra.get("online_wake_only") else ""
    learned = f", {models}{kind} models" if models is not None else ""
    tick = f"{s.compute_median_ms:.2f}/{s.compute_p99_ms:.2f}" if math.isfinite(s.compute_p99_ms) else "n/a"
    mse = f"{s.mse:.2e}" if math.isfinite(s.mse) else "n/a"
    return f"{name}: MSE {mse} m^2, tick {tick} ms{learned}, {outcome}"


def _row(label: str, value: str) -> str:
    return f"  {label:<15}{value}"


def _e(x: float) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.3e}"


def _mm(x: float) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x * 1e3:.1f} mm"


def _steps_text(recovery: Sequence[Mapping[str, Any]]) -> str:
    """Each mass step as factor@time->recovery, until the row is full; the rest only counted."""
    parts = []
    for r in recovery:
        ttr = r.get("time_to_recover_s")
        parts.append(f"{r['factor']:g}x@{r['t']:.1f}s {'never' if ttr is None else f'{ttr:.2f} s'}")
    text = ", ".join(parts[:2]) + (f" (+{len(parts) - 2} more)" if len(parts) > 2 else "")
    return "recovered in " + text


def _attention(extra: Mapping[str, Any]) -> str:
    """What went wrong in a flight that landed anyway; empty when nothing did."""
    notes = []
    if extra.get("fallback_ticks"):
        notes.append(f"{extra['fallback_ticks']} fallback ticks")
    if extra.get("fence_excursion_m"):
        notes.append(f"fence excursion {_mm(extra['fence_excursion_m'])}")
    if extra.get("internal_errors"):
        notes.append(f"{len(extra['internal_errors'])} internal errors")
    if extra.get("trainer_failed"):
        notes.append("trainer failed")
    if extra.get("flight_log"):
        notes.append(f"log {extra['flight_log']}")
    if extra.get("learned_model_error"):
        notes.append("the learned model was not kept")
    return ", ".join(notes)


def _finite(x: np.ndarray) -> np.ndarray:
    return x[np.isfinite(x)]


def _percentile(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else math.nan


def _g(x: float, digits: int = 4) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def _ms(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3f}"


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, Mapping):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj
