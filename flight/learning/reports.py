"""The learner's reports: per-round records, /model and /training log messages, and the summary fields.

Mixed into ``OnlineLearner``, which owns the state these read."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cfknode.flight.learning.gate import GateVerdict
from cfknode.models.trainer_process import TrainOutcome
from cfknode.flight.learning.records import RoundRecord

if TYPE_CHECKING:
    from cfknode.models.modelfile import ModelFile



@dataclass(frozen=True)
class SwapTimes:
    """What a swap cost on the flight's thread (s; NaN where it does not apply)."""

    swap_s: float = math.nan  # the slot's swap itself
    install_s: float = math.nan  # the swap with its bookkeeping
    slice_s: float = math.nan  # the longest gate slice before it

class LearnerReports:
    """``_record``, ``_log_*`` and ``summary_fields`` of ``OnlineLearner``."""

    rounds: list[Any]
    log: Any
    attitude_lag: Any  # the attitude loop's lag identified beside the learner (attitude_lag.py), or None

    @property
    def learned_model(self) -> ModelFile | None:
        """The model file flying now if this flight's learning swapped it in (None: the nominal model, or the one
        the flight started with): what the flight keeps for the next one."""
        flying = self._flying  # type: ignore[attr-defined]
        learned = any(file is flying.file for _, file in self.recent_models)  # type: ignore[attr-defined]
        return flying.file if flying.model is not None and learned else None

    def _record(self, out: TrainOutcome, sent_t: float, latency: float, outcome: str, reason: str,
                applied_t: float = math.nan, verdict: GateVerdict | None = None, received_t: float = math.nan) -> None:
        self.rounds.append(RoundRecord(
            out.round, out.version, (out.window_t0, out.window_t1), sent_t, latency, out.wall_s, out.cpu_s, out.loss,
            outcome, reason, applied_t, received_t,
            verdict.rmse_candidate if verdict else math.nan, verdict.rmse_current if verdict else math.nan,
        ))

    def _log_model(self, t: float, version: int, event: str, reason: str = "", out: TrainOutcome | None = None,
                   latency: float = math.nan, verdict: GateVerdict | None = None,
                   times: SwapTimes = SwapTimes()) -> None:
        msg: dict[str, Any] = {"version": version, "event": event, "queue": list(self._flying.queue)}
        if reason:
            msg["reason"] = reason
        if out is not None:
            msg.update(round=out.round, window=[out.window_t0, out.window_t1], loss=out.loss,
                       train_wall_s=out.wall_s, latency_s=latency)
        if verdict is not None:
            msg.update(val_error=verdict.rmse_candidate, val_error_current=verdict.rmse_current,
                       val_error_nominal=verdict.rmse_nominal, max_residual=verdict.max_residual,
                       val_pairs=verdict.pairs, control_gain=list(verdict.control_gain),
                       velocity_gain=verdict.velocity_gain, cross_gain=verdict.cross_gain,
                       velocity_coupling=verdict.velocity_coupling,
                       climb_feedback=verdict.climb_feedback, tilt_climb=verdict.tilt_climb, score=list(verdict.score))
        for key, seconds in (("swap_ms", times.swap_s), ("install_ms", times.install_s), ("slice_ms", times.slice_s)):
            if math.isfinite(seconds):
                msg[key] = 1e3 * seconds
        self.log.write("/model", t, msg)

    def _log_training(self, t: float, out: TrainOutcome, latency: float) -> None:
        self.log.write("/training", t, {
            "round": out.round, "version": out.version, "base_version": out.base_version,
            "window": [out.window_t0, out.window_t1], "pairs": out.pairs, "loss": out.loss,
            "val_rmse_model": out.val_rmse_model, "val_rmse_nominal": out.val_rmse_nominal,
            "max_abs_residual": out.max_abs_residual, "train_wall_s": out.wall_s, "train_cpu_s": out.cpu_s,
            "latency_s": latency, "t_col": self.s.t_col, "ok": out.model is not None, "error": out.error,
        })

    def _log_event(self, t: float, level: str, text: str) -> None:
        self.log.write("/events", t, {"level": level, "text": text, "source": "online"})

    def inject_trainer_crash(self) -> None:
        """Kill the trainer now (for fault scenarios); the learner sees a crash and restarts it."""
        self.client.kill()

    def summary_fields(self) -> dict[str, Any]:
        """What the flight summary reports about online learning (flat, JSON-safe)."""
        s = self.stats
        mode = "paper-lockstep (reproduction only: the simulation waits for every model)" if self.s.paper_lockstep \
            else (f"honest latency (lockstep, {self.s.latency.describe()})" if self.s.lockstep else "real time")
        walls = np.asarray(s.train_wall_s)
        return {
            "online_mode": mode,
            "online_t_col_s": self.s.t_col,
            "online_wake_only": self.s.wake_only is not None,  # its networks learn the wake of a drone above
            "online_latency": (self.s.latency.mode if self.s.lockstep and not self.s.paper_lockstep
                               else ("paper" if self.s.paper_lockstep else "wall")),
            "models_trained": s.rounds_trained,
            "models_accepted": s.accepted,
            "models_rejected": s.rejected,
            "models_rolled_back": s.rollbacks,
            "models_dropped": s.drops,
            "training_failed": s.rounds_failed,
            "models_undecided": int(self._held is not None) + int(self._gating is not None),  # when the flight ended
            "rounds_in_flight": int(self._out is not None),
            "trainer_crashes": s.crashes,
            "trainer_hangs": s.hangs,
            "trainer_restarts": s.restarts,
            "trainer_failed": self.failed,
            "windows_completed": self.recorder.windows,
            "windows_sent": s.rounds_sent,
            "windows_superseded": s.windows_superseded,
            "windows_stale": s.windows_stale,
            "windows_no_drone_above": s.windows_no_drone_above,
            "windows_one_point_above": s.windows_one_point_above,
            "partial_windows_discarded": self.recorder.discarded,
            "windows_unsettled": self.recorder.unsettled,
            "swap_median_ms": _ms(np.median(s.swap_s)) if s.swap_s else None,
            "swap_max_ms": _ms(max(s.swap_s)) if s.swap_s else None,
            "install_median_ms": _ms(np.median(s.install_s)) if s.install_s else None,
            "install_max_ms": _ms(max(s.install_s)) if s.install_s else None,
            "install_slice_max_ms": _ms(s.max_slice_s) if s.install_s else None,
            "ticks_late_from_install": s.late_ticks,
            "train_wall_median_s": float(np.median(walls)) if walls.size else None,
            "train_wall_max_s": float(walls.max()) if walls.size else None,
            "train_wall_over_t_col": float(np.median(walls)) / self.s.t_col if walls.size else None,
            "rounds_slower_than_t_col": int((walls > self.s.t_col).sum()),
            "latency_median_s": float(np.median(s.latency_s)) if s.latency_s else None,
            "latency_max_s": float(max(s.latency_s)) if s.latency_s else None,
            "pace_wait_s": s.pace_wait_s,
            "trainer_cpu_s": round(s.trainer_cpu_s, 3),
            "gates_in_trainer": s.gate_jobs,
            "final_model_version": self._flying.version,
            **(self.attitude_lag.summary_fields() if self.attitude_lag is not None else {}),
        }




def _ms(seconds: float) -> float:
    return 1e3 * float(seconds)


__all__ = ["LearnerReports"]
