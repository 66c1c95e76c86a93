"""What one tick writes to the flight log: its /state, /reference, /command and /tick messages (docs/logs.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cfknode.flight.estimator import StateEstimate
from cfknode.kernel.setpoint import AttitudeSetpoint

_NAN = float("nan")
_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


@dataclass(frozen=True)
class TickLogged:
    """What one tick writes to the log's /state, /reference, /command and /tick topics."""

    now: float
    est: StateEstimate | None
    truth: np.ndarray | None
    ref: Any
    sp: AttitudeSetpoint
    acc: np.ndarray
    source: str
    compute: float
    solve_s: float
    missed: bool
    ok: bool
    status: str = ""  # why the MPC was not used (fallback ticks only)
    fresh: bool = True
    phase: str = ""
    logs_imu: bool = False
    skipped: int = 0  # slots passed over before this tick (wall clock)


def log_tick(log: Log, t: TickLogged) -> None:
    now, est, truth, ref, sp = t.now, t.est, t.truth, t.ref, t.sp
    if est is not None:
        # fresh, phase and the newest frame are what the fast layer read this tick: replay feeds them back.
        state: dict[str, Any] = {"p": est.p, "v": est.v, "q": est.q, "fresh": bool(t.fresh), "phase": t.phase}
        if est.frame is not None:
            state["frame_t"], state["frame_p"] = est.frame
        if t.logs_imu:
            imu = est.imu
            state["imu_t"] = imu.t if imu is not None else _NAN
            state["imu_f"] = imu.specific_force if imu is not None else _NAN3
        if truth is not None:
            state["p_true"] = truth[:3]
            state["v_true"] = truth[3:6]
        log.write("/state", now, state)
    log.write("/reference", now, {"p": ref.p[0], "v": ref.v[0], "a": ref.a[0], "yaw": float(ref.yaw[0])})
    log.write(
        "/command",
        now,
        {
            "acc": t.acc,
            "roll_deg": sp.roll_deg,
            "pitch_deg": sp.pitch_deg,
            "yawrate_deg": sp.yawrate_deg,
            "thrust": sp.thrust,
            "source": t.source,
        },
    )
    tick: dict[str, Any] = {"compute_s": t.compute, "solve_s": t.solve_s, "missed": t.missed, "mpc_ok": t.ok}
    if t.status:
        tick["status"] = t.status  # why the MPC was not used (fallback ticks only)
    if t.skipped:
        tick["skipped"] = t.skipped  # wall clock only: lockstep never passes a slot over
    log.write("/tick", now, tick)
