"""Online learning, flight side (the paper's Algorithm 1): windows, trainer client, validation gate, hot swap.

No torch here: the trainer is a child process (``cfknode.models.trainer_process``) and this
side only sends numpy windows and receives numpy ``ModelFile``s.

One ``OnlineLearner`` is a loop observer. Its ``on_tick`` runs after every tick's setpoint is
decided, i.e. between ticks, and does, in order:

1. record the tick (``WindowRecorder``): airborne MPC ticks are cut into windows of ``t_col``;
   a swap or rollback discards the partial window, so every window was flown under one model;
2. watch the ticks right after a swap: MPC fallbacks there roll the model back;
3. talk to the trainer (``TrainerClient``): at most one request outstanding; a newer finished
   window replaces an unsent older one (no backlog); crashes and hangs restart the trainer;
4. a finished candidate goes through the validation gate (``gate_steps``: finite weights;
   bounded residual and plausible Jacobians on the recent data *and* the whole operating
   envelope, where the MPC may linearise it; a lower one-step error than the flying model on
   fresh data it never saw), one slice of a fraction of a millisecond per tick gap, and is then
   swapped into the ``ModelSlot``: a reference assignment, so no rebuild and no missed tick.

Honest latency in lockstep simulation: a model is applied no earlier than the moment its
request was sent (its window's end) plus the observed training round trip. The simulation is
paced only while the trainer works (a round, or a restart after a fault), and only when sim
time would otherwise run ahead of the wall time the trainer has had (the loop blocks on the
result pipe until the wall catches up); the rest of the flight runs at full lockstep speed.
``paper_lockstep`` instead waits for every model and applies it at once, as the paper's code
does (reproduction only).
"""

from __future__ import annotations

import functools
import math
import multiprocessing
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Generator, Protocol

import numpy as np
from scipy.signal import butter, filtfilt

from cfknode.flight.model_monitor import ModelMonitor, MonitorSettings, MonitorVerdict
from cfknode.flight.model_slot import ModelSlot
from cfknode.models.modelfile import ModelFile
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import (
    TrainerReady,
    TrainerSettings,
    TrainOutcome,
    TrainRequest,
    Window,
    trainer_main,
)

# Same rules as offline training data (cfknode.flight_data, which imports torch through its Segment):
MIN_HEIGHT = 0.1  # m above the first estimate: ground effect and contact are not the model's business
ELIGIBLE_SOURCES = ("mpc",)  # ticks the MPC flew with the model; fallback ticks were not
FILTER_ORDER = 2  # as cfknode.models.training: Butterworth, zero phase (filtfilt)
GAP_FACTOR = 3.0


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


class TickLike(Protocol):
    t: float
    est: Any
    acc: np.ndarray
    source: str
    model_version: int
    compute_s: float


# --- windows (Algorithm 1) ---------------------------------------------------------------------


class WindowRecorder:
    """Cuts the run of eligible ticks into windows of ``t_col``; keeps the run for the gate.

    A *run* is the newest contiguous stretch of eligible ticks under one model; anything else
    (on the ground, a fallback tick, another model version, ``reset``) ends it and discards the
    partial window. Storage is preallocated (``keep_s`` of ticks); adding a tick is a few
    array stores.
    """

    def __init__(self, t_col: float, rate_hz: float, start_time: float = 0.0, keep_s: float = 4.0) -> None:
        self.t_col = t_col
        self.start_time = start_time
        cap = int(math.ceil(max(keep_s, 3.0 * t_col) * rate_hz)) + 8
        self._t = np.empty(cap)
        self._x = np.empty((cap, 6))
        self._u = np.empty((cap, 3))
        self._n = 0  # ticks in the run buffer
        self._w0 = 0  # first tick of the current window in the buffer
        self._version: int | None = None
        self._ground: float | None = None
        self.windows = 0  # windows completed
        self.discarded = 0  # partial windows thrown away (swap, rollback, run broken)
        self.last_added = False  # whether the newest tick joined the run (the model monitor follows the run)

    def add(self, tick: TickLike) -> Window | None:
        """Record one tick; returns a window when this tick completes one."""
        self.last_added = False
        est = tick.est
        if est is None:
            self._break()
            return None
        if self._ground is None:
            self._ground = float(est.p[2])
        if (
            tick.source not in ELIGIBLE_SOURCES
            or tick.t < self.start_time
            or est.p[2] <= self._ground + MIN_HEIGHT
        ):
            self._break()
            return None
        if self._version is not None and tick.model_version != self._version:
            self._break()  # defensive: the learner resets on its own swaps; anyone else's also ends the run
        if self._n == self._t.shape[0]:
            self._compact()
        i = self._n
        self._t[i] = tick.t
        self._x[i, 0:3] = est.p
        self._x[i, 3:6] = est.v
        self._u[i] = tick.acc
        if not (math.isfinite(self._x[i].sum()) and math.isfinite(self._u[i].sum())):
            self._break()
            return None
        self._version = tick.model_version
        self._n = i + 1
        self.last_added = True
        if tick.t - self._t[self._w0] < self.t_col - 1e-9:
            return None
        w0, self._w0 = self._w0, self._n
        self.windows += 1
        return Window(self.windows, self._t[w0 : self._n].copy(), self._x[w0 : self._n].copy(),
                      self._u[w0 : self._n].copy(), tick.model_version)

    def reset(self) -> None:
        """A model change: the partial window (flown under the old model) is discarded."""
        self._break()

    def count_after(self, after: float) -> int:
        """How many of the run's ticks have t > ``after``."""
        return self._n - int(np.searchsorted(self._t[: self._n], after, side="right"))

    def fresh(self, after: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of the run's ticks with t > ``after`` (all flown under the current model)."""
        k = int(np.searchsorted(self._t[: self._n], after, side="right"))
        return self._t[k : self._n].copy(), self._x[k : self._n].copy(), self._u[k : self._n].copy()

    def _break(self) -> None:
        if self._n > self._w0:
            self.discarded += 1
        self._n = self._w0 = 0
        self._version = None

    def _compact(self) -> None:
        # Keep the newest half (always more than the current window, as capacity >= 3 t_col).
        keep = min(self._n - self._w0 + self._t.shape[0] // 2, self._n)
        start = self._n - keep
        self._t[:keep] = self._t[start : self._n]
        self._x[:keep] = self._x[start : self._n]
        self._u[:keep] = self._u[start : self._n]
        self._w0 -= start
        self._n = keep


# --- validation gate ---------------------------------------------------------------------------


@dataclass(frozen=True)
class GatePairs:
    """Filtered one-step pairs x0 --(u held for dt)--> x1 (numpy, for the gate)."""

    x0: np.ndarray
    u: np.ndarray
    dt: np.ndarray
    x1: np.ndarray

    def __len__(self) -> int:
        return int(self.dt.shape[0])


@functools.lru_cache(maxsize=8)
def _butter(order: int, wn: float) -> tuple[np.ndarray, np.ndarray]:
    return butter(order, wn)


def gate_pairs(t: np.ndarray, x: np.ndarray, u: np.ndarray, filter_hz: float) -> GatePairs:
    """Pairs from one contiguous run, low-pass filtered exactly as ``make_dataset`` filters training data.

    (That function lives with torch in ``cfknode.models.training``; this is its torch-free twin
    for one gap-free segment.)
    """
    x, u = x.copy(), u.copy()
    n = t.shape[0]
    if n >= 2 and filter_hz > 0.0:
        fs = 1.0 / float(np.median(np.diff(t)))
        wn = filter_hz / (0.5 * fs)
        if wn < 1.0 and n > 3 * (FILTER_ORDER + 1):
            b, a = _butter(FILTER_ORDER, round(wn, 12))
            padlen = min(int(math.ceil(3.0 * fs / filter_hz)), n - 1)
            # One pass over (x, u) together: this runs in a tick gap, where every 0.1 ms counts.
            xu = filtfilt(b, a, np.concatenate((x, u), axis=1), axis=0, padlen=padlen)
            x, u = xu[:, :6], xu[:, 6:]
    dt = np.diff(t)
    ok = dt > 0
    if ok.any():
        ok &= dt <= GAP_FACTOR * float(np.median(dt[ok]))
    return GatePairs(x[:-1][ok], u[:-1][ok], dt[ok], x[1:][ok])


def one_step_rmse(model: ResidualQueue | Any | None, pairs: GatePairs) -> float:
    """One-step velocity RMSE (m/s) of nominal + ``model`` (RK4 over each pair's dt); None = nominal."""
    if len(pairs) == 0:
        return math.nan
    dt = pairs.dt[:, None]
    u = pairs.u

    def vdot(v: np.ndarray) -> np.ndarray:
        if model is None:
            return u
        x = np.empty((v.shape[0], 6))
        x[:, 0:3] = 0.0  # the residual is translation invariant: position is not an input
        x[:, 3:6] = v
        return u + model.evaluate(x, u)

    # p does not feed back into v', so RK4 on v alone is RK4 on the whole state for the v rows.
    v0 = pairs.x0[:, 3:6]
    k1 = vdot(v0)
    k2 = vdot(v0 + 0.5 * dt * k1)
    k3 = vdot(v0 + 0.5 * dt * k2)
    k4 = vdot(v0 + dt * k3)
    v1 = v0 + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    err = v1 - pairs.x1[:, 3:6]
    return float(np.sqrt(np.mean(err * err)))


@dataclass(frozen=True)
class GateVerdict:
    accepted: bool
    reason: str  # why it was rejected ("" when accepted)
    rmse_candidate: float  # m/s, one-step velocity RMSE on the fresh pairs
    rmse_current: float
    rmse_nominal: float
    max_residual: float  # m/s^2, largest |residual| component on recent data and the envelope
    pairs: int
    control_gain: tuple[float, float] = (math.nan, math.nan)  # extreme eigenvalues of sym(I + dr/du)
    velocity_gain: float = math.nan  # largest eigenvalue of sym(dr/dv), 1/s
    cross_gain: float = math.nan  # largest |off-diagonal| of dr/du


@dataclass(frozen=True)
class GateLimits:
    """What a candidate must satisfy everywhere the MPC may evaluate it, not only where it was trained.

    The MPC linearises the residual at its predicted nodes, which saturate at the input box in a
    hard manoeuvre; a network is only trustworthy where it saw data, so the gate checks physical
    plausibility on samples of the whole operating envelope (``operating_envelope``):
    - |r| <= ``max_residual`` (knode.max_residual);
    - control effectiveness: the eigenvalues of sym(I + dr/du) lie in ``control_gain`` (a mass
      factor k gives 1/k; the paper's 0.5x and 1.33x give 2 and 0.75). Below it the MPC believes
      its commands barely act, and it saturates;
    - no phantom instability: the eigenvalues of sym(dr/dv) stay below ``max_velocity_gain`` 1/s
      (drag makes them negative; a positive one says velocity grows on its own);
    - no cross-coupling: |dr_i/du_j| <= ``max_cross_gain`` for i != j. The Mellinger layer points
      the thrust where the MPC asks, so a mass or thrust-map error scales each axis alike; a
      window whose commands drift together (u_x rising while a thrust-limited climb decays)
      fits a spurious dr_z/du_x, and the MPC then tilts hard to "climb" (measured: 0.26 made it
      command 5 m/s^2 sideways and leave the circle by 0.6 m). 0.2 still admits an 11 deg yaw
      misalignment between mocap and the vehicle.
    """

    max_residual: float
    control_gain: tuple[float, float]
    max_velocity_gain: float
    envelope_x: np.ndarray  # (m, 6)
    envelope_u: np.ndarray  # (m, 3)
    max_cross_gain: float = math.inf


def operating_envelope(
    speed: float, acc_lower: np.ndarray, acc_upper: np.ndarray, n: int = 96, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Samples (x, u) of the envelope: |v_i| <= ``speed``, u in the MPC's input box, including its corners."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(acc_lower, dtype=float), np.asarray(acc_upper, dtype=float)
    corners = np.array([[lo[0] if i & 1 else hi[0], lo[1] if i & 2 else hi[1], lo[2] if i & 4 else hi[2]]
                        for i in range(8)])
    u = np.concatenate((corners, rng.uniform(lo, hi, size=(n, 3))))
    x = np.zeros((u.shape[0], 6))
    x[8:, 3:6] = rng.uniform(-speed, speed, size=(n, 3))
    return x, u


def model_is_finite(model: ModelFile) -> bool:
    return all(
        np.all(np.isfinite(w)) and np.all(np.isfinite(b)) for net in model.networks for (w, b) in net.layers
    )


JACOBIAN_CHUNK = 20  # nodes per linearise call: the MPC's own batch size


def run_gate(
    candidate_file: ModelFile,
    candidate: ResidualQueue,
    current: Any | None,
    fresh: GatePairs,
    recent_x: np.ndarray,
    recent_u: np.ndarray,
    limits: GateLimits,
) -> GateVerdict:
    """The validation gate (beyond the paper) in one call; pure: no side effects.

    Rejects a candidate whose weights are non-finite, that is implausible on the recent data or
    the operating envelope (``GateLimits``), or whose one-step error on ``fresh`` (held-out
    data) is not lower than the flying model's.
    """
    steps = gate_steps(candidate_file, candidate, current, fresh, recent_x, recent_u, limits)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def gate_steps(
    candidate_file: ModelFile,
    candidate: ResidualQueue,
    current: Any | None,
    fresh: GatePairs,
    recent_x: np.ndarray,
    recent_u: np.ndarray,
    limits: GateLimits,
) -> Generator[None, None, GateVerdict]:
    """``run_gate`` in slices of a fraction of a millisecond: the flight loop runs one per tick gap."""
    nan = math.nan
    n = len(fresh)
    if not model_is_finite(candidate_file):
        return GateVerdict(False, "non-finite weights", nan, nan, nan, nan, n)
    xs = np.concatenate((recent_x, limits.envelope_x))
    us = np.concatenate((recent_u, limits.envelope_u))
    peak = float(np.max(np.abs(candidate.evaluate(xs, us))))
    if not math.isfinite(peak):
        return GateVerdict(False, "non-finite residual", nan, nan, nan, peak, n)
    if peak > limits.max_residual:
        return GateVerdict(False, f"residual {peak:.3g} m/s^2 exceeds knode.max_residual {limits.max_residual:g}",
                           nan, nan, nan, peak, n)
    yield
    # The MPC's Jacobians, at every 8th recent point and all envelope points, in the MPC's own
    # batch size: one call over ~150 nodes crossed OpenBLAS's threading threshold and took 10x
    # longer on the busy cores than the same work in small products.
    k = recent_x.shape[0]
    sel = np.concatenate((np.arange(0, k, 8), k + np.arange(limits.envelope_x.shape[0])))
    xs, us = xs[sel], us[sel]
    g_lo, g_hi, vgain, cross = math.inf, -math.inf, -math.inf, 0.0
    off = ~np.eye(3, dtype=bool)
    for i in range(0, xs.shape[0], JACOBIAN_CHUNK):
        _, jx, ju = candidate.linearise(xs[i : i + JACOBIAN_CHUNK], us[i : i + JACOBIAN_CHUNK])
        if not (math.isfinite(float(jx.sum())) and math.isfinite(float(ju.sum()))):
            return GateVerdict(False, "non-finite Jacobian", nan, nan, nan, peak, n)
        gain = np.linalg.eigvalsh(0.5 * (ju + ju.transpose(0, 2, 1)) + np.eye(3))
        jv = jx[:, :, 3:6]
        g_lo, g_hi = min(g_lo, float(gain.min())), max(g_hi, float(gain.max()))
        vgain = max(vgain, float(np.linalg.eigvalsh(0.5 * (jv + jv.transpose(0, 2, 1))).max()))
        cross = max(cross, float(np.abs(ju[:, off]).max()))
        yield
    e_cand = one_step_rmse(candidate, fresh)
    yield
    e_cur = one_step_rmse(current, fresh)
    yield
    e_nom = e_cur if current is None else one_step_rmse(None, fresh)
    lo, hi = limits.control_gain

    def verdict(reason: str) -> GateVerdict:
        return GateVerdict(reason == "", reason, e_cand, e_cur, e_nom, peak, n, (g_lo, g_hi), vgain, cross)

    if g_lo < lo or g_hi > hi:
        return verdict(f"control effectiveness {g_lo:.2f}..{g_hi:.2f} outside {lo:g}..{hi:g}")
    if vgain > limits.max_velocity_gain:
        return verdict(f"velocity feedback {vgain:.2f} 1/s above {limits.max_velocity_gain:g} (phantom instability)")
    if cross > limits.max_cross_gain:
        return verdict(f"cross-coupling |dr_i/du_j| {cross:.2f} above {limits.max_cross_gain:g}")
    if n == 0 or not math.isfinite(e_cand):
        return verdict("no held-out data to judge it on")
    if not e_cand < e_cur:
        return verdict(f"not better on held-out data ({e_cand:.4g} vs flying {e_cur:.4g} m/s)")
    return verdict("")


# --- trainer client ----------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainerFault:
    kind: str  # "crash" | "hang"
    reason: str


class TrainerClient:
    """The trainer child process: spawn, requests, results, crash and hang detection, restarts.

    States: ``starting`` (spawned, importing torch), ``idle``, ``busy`` (one request out),
    ``stopped``. Nothing here blocks unless asked to (``wait_ready``, ``poll(timeout)``).
    """

    def __init__(
        self,
        settings: TrainerSettings,
        timeout: float,
        start_timeout: float = 120.0,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.settings = settings
        self.timeout = timeout
        self.start_timeout = start_timeout
        self._wall = wall
        self._ctx = multiprocessing.get_context("spawn")
        self._proc: Any = None
        self._conn: Any = None
        self._dead: list[Any] = []  # killed processes not yet reaped
        self.state = "stopped"
        self.sent_wall = math.nan  # wall time the outstanding request was sent
        self.start_wall = math.nan  # wall time of the last start
        self.starts = 0
        self.pid: int | None = None
        self.warmup_s = math.nan

    def start(self) -> None:
        """Spawn a trainer (non-blocking: it reports ``TrainerReady`` when torch is up)."""
        self._reap()
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(target=trainer_main, args=(child, self.settings), name="cfknode-trainer", daemon=True)
        proc.start()
        child.close()  # only the child holds it now, so its death reads as EOF here
        self._proc, self._conn = proc, parent
        self.pid = proc.pid
        self.state = "starting"
        self.start_wall = self._wall()
        self.starts += 1

    def wait_ready(self, timeout: float) -> bool:
        """Block until the trainer is up (pre-flight); False on timeout or failure."""
        deadline = self._wall() + timeout
        while self.state == "starting":
            left = deadline - self._wall()
            if left <= 0:
                return False
            event = self.poll(left)
            if isinstance(event, TrainerFault):
                return False
        return self.state == "idle"

    @property
    def busy(self) -> bool:
        return self.state == "busy"

    def submit(self, request: TrainRequest) -> None:
        if self.state != "idle":
            raise RuntimeError(f"trainer is {self.state}, not idle")
        # Clock first: the child may start training before send() returns on a busy machine.
        self.sent_wall = self._wall()
        self._conn.send(request)
        self.state = "busy"

    def poll(self, timeout: float = 0.0) -> TrainOutcome | TrainerReady | TrainerFault | None:
        """The trainer's next message, or a fault; waits up to ``timeout`` s (0: never blocks)."""
        if self.state in ("stopped",):
            return None
        deadline = self._deadline()
        if deadline is not None:
            timeout = min(timeout, max(0.0, deadline - self._wall()))  # never wait past the hang deadline
        try:
            ready = self._conn.poll(timeout) if timeout > 0 else self._conn.poll()
            message = self._conn.recv() if ready else None
        except (EOFError, OSError):
            code = self._proc.exitcode if self._proc is not None else None
            if code is None:
                self._proc.join(0.05)
                code = self._proc.exitcode
            self._discard_process(kill=True)
            return TrainerFault("crash", f"trainer process exited (code {code})")
        if message is None:
            if deadline is not None and self._wall() >= deadline:
                what = (f"no result within online.trainer_timeout = {self.timeout:g} s" if self.state == "busy"
                        else f"not up within {self.start_timeout:g} s of starting")
                self._discard_process(kill=True)
                return TrainerFault("hang", f"{what}; killed")
            return None
        if isinstance(message, TrainerReady):
            self.state = "idle"
            self.warmup_s = message.warmup_s
        elif isinstance(message, TrainOutcome):
            self.state = "idle"
        return message

    def _deadline(self) -> float | None:
        if self.state == "busy":
            return self.sent_wall + self.timeout
        if self.state == "starting":
            return self.start_wall + self.start_timeout
        return None

    def kill(self) -> None:
        """Kill the trainer at once (fault injection; the next ``poll`` reports the crash)."""
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()

    def close(self, timeout: float = 2.0) -> None:
        """Ask the trainer to stop; kill it if it does not within ``timeout``."""
        if self._proc is not None:
            try:
                if self.state in ("idle", "starting"):
                    self._conn.send(None)
            except (OSError, ValueError):
                pass
            if self.state == "idle":
                self._proc.join(timeout)
            self._discard_process(kill=True)
        self._reap(timeout)
        self.state = "stopped"

    def _discard_process(self, kill: bool) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self.state = "stopped"
        if conn is not None:
            conn.close()
        if proc is not None:
            if kill and proc.is_alive():
                proc.kill()
            self._dead.append(proc)
        self._reap()

    def _reap(self, timeout: float = 0.0) -> None:
        alive = []
        for proc in self._dead:
            proc.join(timeout)
            if proc.exitcode is None:
                alive.append(proc)
            else:
                proc.close()
        self._dead = alive


# --- the learner (loop observer) -------------------------------------------------------------


@dataclass(frozen=True)
class LearnerSettings:
    t_col: float
    period: float  # s between ticks
    lockstep: bool  # flight clock is the simulator's (pace honest latency)
    paper_lockstep: bool
    gate: bool
    gate_min_pairs: int
    replay_windows: int
    start_time: float
    rollback_ticks: int
    rollback_fallbacks: int
    max_restarts: int
    limits: GateLimits
    filter_hz: float  # training.velocity_filter_hz
    holdout_fraction: float  # training.validation_fraction: the tail the paper-lockstep gate judges on
    queue_size: int  # knode.queue_size
    monitor: MonitorSettings | None = None  # drop a flying model the world changed under (None: never)


@dataclass(frozen=True)
class RoundRecord:
    """One training round as the flight saw it."""

    round: int
    version: int
    window: tuple[float, float]
    sent_t: float  # flight time the request was sent
    latency_s: float  # wall s from send to result (the honest delay)
    train_wall_s: float  # the trainer's own wall time for the round
    train_cpu_s: float
    loss: float
    outcome: str  # "swap" | "reject" | "failed" | "lost" (crash/hang/unfinished)
    reason: str = ""
    applied_t: float = math.nan  # flight time of the swap (the next tick flies it)
    received_t: float = math.nan  # flight time the result arrived
    rmse_candidate: float = math.nan
    rmse_current: float = math.nan


@dataclass(frozen=True)
class SwapEvent:
    t: float  # on_tick time of the swap; ticks after t fly the new model
    version: int
    swap_s: float  # the slot write (a reference assignment)
    install_s: float  # fold the file into numpy stacks + gate + swap, spread over tick gaps
    max_slice_s: float  # the longest of those slices: what one tick gap had to absorb
    kind: str  # "swap" | "rollback" | "drop"


@dataclass
class _Outstanding:
    request: TrainRequest
    sent_t: float
    sent_wall: float


@dataclass(frozen=True)
class _PaceFrom:
    """While the trainer works (a round or a restart), flight time may not outrun the wall time since this point."""

    t: float
    wall: float


@dataclass
class _Held:
    outcome: TrainOutcome
    window: Window  # the window it trained on
    received_t: float
    sent_t: float
    latency_s: float  # observed wall round trip
    apply_at: float  # earliest flight time the next tick may fly it


@dataclass
class _Gating:
    """A candidate going through the gate, one slice per tick gap."""

    held: _Held
    candidate: ResidualQueue | None  # set by the first slice
    steps: Generator[None, None, GateVerdict]
    work_s: float  # wall time of the slices so far (fold and filtering included)
    max_slice_s: float


@dataclass
class _Flying:
    """The model in the slot, with what rollback and the next round need."""

    model: Any | None
    version: int
    file: ModelFile | None
    queue: tuple[int, ...]  # versions of its networks, oldest first


@dataclass
class _Watch:
    previous: _Flying
    version: int
    ticks_left: int
    fallbacks: int = 0


@dataclass
class OnlineStats:
    rounds_sent: int = 0
    rounds_trained: int = 0
    rounds_failed: int = 0
    accepted: int = 0
    rejected: int = 0
    rollbacks: int = 0
    drops: int = 0  # flying models the monitor replaced by nominal
    crashes: int = 0
    hangs: int = 0
    restarts: int = 0
    windows_superseded: int = 0  # finished windows replaced by a newer one before being sent
    windows_stale: int = 0  # finished windows dropped because the model changed before they were sent
    pace_wait_s: float = 0.0  # wall time spent holding the simulation back for honest latency
    max_slice_s: float = 0.0  # longest gate/swap slice between two ticks
    late_ticks: int = 0  # ticks whose compute plus the learner's install work before them exceeded the period
    swap_s: list[float] = field(default_factory=list)
    install_s: list[float] = field(default_factory=list)
    train_wall_s: list[float] = field(default_factory=list)
    latency_s: list[float] = field(default_factory=list)


class OnlineLearner:
    """The flight side of online learning: a ``TickObserver`` (see the module docstring)."""

    def __init__(
        self,
        settings: LearnerSettings,
        slot: ModelSlot,
        client: TrainerClient,
        log: Log,
        base: ModelFile | None = None,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.s = settings
        self.slot = slot
        self.client = client
        self.log = log
        self._wall = wall
        self.recorder = WindowRecorder(settings.t_col, 1.0 / settings.period, settings.start_time)
        self.monitor = ModelMonitor(settings.monitor, 1.0 / settings.period) if settings.monitor is not None else None
        n0 = len(base.networks) if base is not None else 0
        self._flying = _Flying(slot.model, slot.version, base, (slot.version,) * n0)
        self._next_version = slot.version + 1
        self._round = 0
        self._pending: Window | None = None  # newest finished window not yet sent
        self._recent: deque[Window] = deque(maxlen=settings.replay_windows + 1)
        self._out: _Outstanding | None = None
        self._pace_from: _PaceFrom | None = None
        self._held: _Held | None = None
        self._gating: _Gating | None = None
        self._watch: _Watch | None = None
        self.failed = False  # restarts exhausted: learning stopped, flight goes on
        self._install_work_s = 0.0  # wall time of the last on_tick when it folded, gated or swapped a model
        self.stats = OnlineStats()
        self.rounds: list[RoundRecord] = []
        self.swaps: list[SwapEvent] = []
        self.windows: list[tuple[int, float, float, int]] = []  # (index, t0, t1, version) of finished windows
        self.recent_models: deque[tuple[int, ModelFile]] = deque(maxlen=8)  # newest swapped-in files, for inspection

    # The loop calls this after every tick.
    def on_tick(self, tick: TickLike) -> None:
        if self._install_work_s > 0.0 and tick.compute_s + self._install_work_s > self.s.period:
            self.stats.late_ticks += 1  # on a wall clock this tick started late because of the install work
        start, paced = self._wall(), self.stats.pace_wait_s
        installing = self._gating is not None or self._held is not None
        self._on_tick(tick)
        installing = installing or self._gating is not None
        # Pacing (lockstep waiting for the trainer) is simulated wall time, not work.
        self._install_work_s = (self._wall() - start) - (self.stats.pace_wait_s - paced) if installing else 0.0

    def _on_tick(self, tick: TickLike) -> None:
        t = tick.t
        window = self.recorder.add(tick)
        if window is not None:
            self._on_window(window)
        if self._watch is not None:
            self._watch_tick(tick)
        if self.monitor is not None and not self.s.paper_lockstep:
            self._monitor_tick(tick)
        if self.failed:
            return
        if self.s.paper_lockstep:
            self._paper_step(t)
        else:
            self._service(t)

    # --- honest mode -------------------------------------------------------------------------

    def _service(self, t: float) -> None:
        timeout = 0.0
        pace = self._pace_from
        if pace is not None and self.s.lockstep and self.client.state in ("busy", "starting"):
            # Pace: the next tick may not start before the trainer has had as much wall time as
            # the simulation will have advanced since the round (or restart) began.
            timeout = max(0.0, (self._next_tick_time(t) - pace.t) - (self._wall() - pace.wall))
        if timeout > 0.0:
            waited = self._wall()
            event = self.client.poll(timeout)
            self.stats.pace_wait_s += self._wall() - waited
        else:
            event = self.client.poll(0.0)
        if event is not None:
            self._pace_from = None
            self._on_event(event, t)
        if self._gating is not None:
            self._step_gate(t)
        elif self._held is not None:
            self._start_gate(t)
        self._maybe_send(t)

    def _maybe_send(self, t: float) -> None:
        if self.client.state != "idle" or self._held is not None or self._gating is not None or self._pending is None:
            return
        window, self._pending = self._pending, None
        if window.version != self._flying.version:
            self.stats.windows_stale += 1
            return
        earlier = [w for w in self._recent if w.index < window.index]
        replay = tuple(earlier[-self.s.replay_windows :]) if self.s.replay_windows > 0 else ()
        self._round += 1
        holdout = self.s.holdout_fraction if (self.s.paper_lockstep and self.s.gate) else 0.0
        request = TrainRequest(self._round, self._next_version, window, replay, self._flying.file, holdout)
        self._next_version += 1
        self.client.submit(request)
        self._out = _Outstanding(request, t, self.client.sent_wall)
        self._pace_from = _PaceFrom(t, self.client.sent_wall)
        self.stats.rounds_sent += 1

    def _on_window(self, window: Window) -> None:
        self.windows.append((window.index, window.t0, window.t1, window.version))
        self._recent.append(window)
        if self._pending is not None:
            self.stats.windows_superseded += 1  # no backlog: the newest window wins
        self._pending = window

    def _on_event(self, event: Any, t: float) -> None:
        if isinstance(event, TrainOutcome):
            out, self._out = self._out, None
            if out is None or out.request.round != event.round:
                return  # a result from before a restart: nothing waits for it
            latency = self._wall() - out.sent_wall
            self.stats.latency_s.append(latency)
            self.stats.train_wall_s.append(event.wall_s)
            self._log_training(t, event, latency)
            if event.model is None:
                self.stats.rounds_failed += 1
                self._record(event, out.sent_t, latency, "failed", event.error, received_t=t)
                self._log_model(t, event.version, "reject", f"training failed: {event.error}", event, latency)
                self.stats.rejected += 1
                return
            self.stats.rounds_trained += 1
            # On a wall clock the round trip has already elapsed in flight time; in lockstep it is added.
            apply_at = out.sent_t + latency if self.s.lockstep and not self.s.paper_lockstep else t
            self._held = _Held(event, out.request.window, t, out.sent_t, latency, apply_at)
        elif isinstance(event, TrainerFault):
            self._on_fault(event, t)
        elif isinstance(event, TrainerReady):
            self._log_event(t, "info", f"trainer ready (pid {event.pid}, warm-up {event.warmup_s:.2f} s)")

    def _on_fault(self, fault: TrainerFault, t: float) -> None:
        out, self._out = self._out, None
        version = out.request.version if out is not None else self._flying.version
        if fault.kind == "hang":
            self.stats.hangs += 1
        else:
            self.stats.crashes += 1
        if out is not None:
            r = out.request
            self.rounds.append(RoundRecord(r.round, r.version, (r.window.t0, r.window.t1), out.sent_t, math.nan,
                                           math.nan, math.nan, math.nan, "lost", fault.reason))
        self._log_model(t, version, "crash", f"{fault.kind}: {fault.reason}")
        if self.stats.restarts >= self.s.max_restarts:
            self.failed = True
            self._log_event(t, "error", f"online trainer failed {self.stats.restarts + 1} times; learning stopped, "
                            f"flying model {self._flying.version} to the end")
            return
        self.stats.restarts += 1
        self.client.start()
        self._pace_from = _PaceFrom(t, self.client.start_wall)  # a restart costs flight time too
        self._log_model(t, self._flying.version, "restart", f"trainer restart {self.stats.restarts} of {self.s.max_restarts}")

    # --- gate and swap -----------------------------------------------------------------------

    def _next_tick_time(self, t: float) -> float:
        """Earliest flight time of the next tick: tick k runs at the first clock reading >= k * period
        (a lockstep clock reads in plant steps), so the next one is at (floor(t / period) + 1) * period or later."""
        return (math.floor(t / self.s.period + 1e-9) + 1) * self.s.period

    def _start_gate(self, t: float) -> None:
        """Begin installing the held result once honest latency and fresh data allow it."""
        held = self._held
        assert held is not None
        if self._next_tick_time(t) < held.apply_at - 1e-9:
            return  # honest latency: the next tick is still too early for this model
        out = held.outcome
        if (not self.s.paper_lockstep and self.s.gate and out.base_version == self._flying.version
                and self.recorder.count_after(out.window_t1) - 1 < self.s.gate_min_pairs):
            return  # not enough fresh data yet to judge it
        self._held = None
        start = self._wall()
        if self.s.paper_lockstep:
            # No fresh data exists (the paper applies at once): judge on the window's held-out tail.
            fresh = _tail(out, held.window)
        else:
            fresh = self.recorder.fresh(out.window_t1)
        g = _Gating(held, None, self._install_steps(held, fresh), 0.0, 0.0)
        g.work_s = g.max_slice_s = self._wall() - start
        self._gating = g

    def _install_steps(self, held: _Held, fresh: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Generator[None, None, GateVerdict]:
        """Fold the candidate, filter the held-out data, then the gate: each a slice of its own."""
        g = self._gating
        out = held.outcome
        assert out.model is not None
        candidate = ResidualQueue.from_model_file(out.model)
        if g is not None:
            g.candidate = candidate
        yield
        if not self.s.gate:  # gate off is the paper: every trained model flies
            return GateVerdict(True, "", math.nan, math.nan, math.nan, math.nan, 0)
        ft, fx, fu = fresh
        pairs = gate_pairs(ft, fx, fu, self.s.filter_hz)
        yield
        return (yield from gate_steps(out.model, candidate, self._flying.model, pairs,
                                      np.concatenate((held.window.x, fx)), np.concatenate((held.window.u, fu)),
                                      self.s.limits))

    def _step_gate(self, t: float) -> None:
        """One slice of the gate per tick gap; the swap itself (a reference write) follows the last slice."""
        g = self._gating
        assert g is not None
        start = self._wall()
        try:
            next(g.steps)
        except StopIteration as done:
            self._gating = None
            self._finish_gate(t, g, done.value, start)
            return
        slice_s = self._wall() - start
        g.work_s += slice_s
        g.max_slice_s = max(g.max_slice_s, slice_s)

    def _finish_gate(self, t: float, g: _Gating, verdict: GateVerdict, start: float) -> None:
        held, out = g.held, g.held.outcome
        if out.base_version != self._flying.version:
            self._reject(t, held, f"stale: trained on version {out.base_version}, flying {self._flying.version}", None)
            return
        if not verdict.accepted:
            self._reject(t, held, verdict.reason, verdict)
            return
        candidate, candidate_file = g.candidate, out.model
        assert candidate_file is not None and candidate is not None
        queue = (self._flying.queue + (out.version,))[-self.s.queue_size :]
        previous = self._flying
        record = self.slot.swap(candidate, out.version, t)
        last_slice = self._wall() - start
        install_s = g.work_s + last_slice
        self.stats.max_slice_s = max(self.stats.max_slice_s, g.max_slice_s, last_slice)
        self._flying = _Flying(candidate, out.version, candidate_file, queue)
        self.recent_models.append((out.version, candidate_file))
        self._model_changed()
        self._watch = _Watch(previous, out.version, self.s.rollback_ticks)
        self.stats.accepted += 1
        self.stats.swap_s.append(record.swap_s)
        self.stats.install_s.append(install_s)
        max_slice = max(g.max_slice_s, last_slice)
        self.swaps.append(SwapEvent(t, out.version, record.swap_s, install_s, max_slice, "swap"))
        self._record(out, held.sent_t, held.latency_s, "swap", "", t, verdict, held.received_t)
        self._log_model(t, out.version, "swap", "", out, held.latency_s, verdict, record.swap_s, install_s, max_slice)

    def _reject(self, t: float, held: _Held, reason: str, verdict: GateVerdict | None) -> None:
        self.stats.rejected += 1
        self._record(held.outcome, held.sent_t, held.latency_s, "reject", reason, math.nan, verdict, held.received_t)
        self._log_model(t, held.outcome.version, "reject", reason, held.outcome, held.latency_s, verdict)

    def _model_changed(self) -> None:
        """Every model change ends the run: no window spans it, and unsent windows are stale."""
        self.recorder.reset()
        if self._pending is not None:
            self.stats.windows_stale += 1
            self._pending = None

    # --- rollback ----------------------------------------------------------------------------

    def _watch_tick(self, tick: TickLike) -> None:
        w = self._watch
        assert w is not None
        if tick.source == "fallback":
            w.fallbacks += 1
        w.ticks_left -= 1
        if w.fallbacks >= self.s.rollback_fallbacks:
            self._rollback(tick.t, w)
        elif w.ticks_left <= 0:
            self._watch = None

    def _rollback(self, t: float, w: _Watch) -> None:
        self._watch = None
        prev = w.previous
        record = self.slot.swap(prev.model, prev.version, t)
        self._flying = prev
        self._model_changed()
        self._held = None  # anything trained on the rolled-back model is stale
        if self._gating is not None:
            g, self._gating = self._gating, None
            self._reject(t, g.held, f"stale: its base {g.held.outcome.base_version} was rolled back", None)
        self.stats.rollbacks += 1
        self.swaps.append(SwapEvent(t, prev.version, record.swap_s, record.swap_s, record.swap_s, "rollback"))
        reason = f"{w.fallbacks} MPC fallbacks in the {self.s.rollback_ticks - w.ticks_left} ticks after swapping in {w.version}"
        self._log_model(t, prev.version, "rollback", reason, swap_s=record.swap_s)

    # --- model monitor -----------------------------------------------------------------------

    def _monitor_tick(self, tick: TickLike) -> None:
        monitor = self.monitor
        assert monitor is not None
        if not self.recorder.last_added:
            monitor.reset()  # the same ticks the windows use: airborne, flown by the MPC
            return
        if monitor.add(tick.t, tick.est.v, tick.acc) and self._flying.model is not None:
            verdict = monitor.judge(self._flying.model)
            if verdict.drop:
                self._drop(tick.t, verdict)

    def _drop(self, t: float, verdict: MonitorVerdict) -> None:
        """Fly nominal from the next tick: the flying model explains the newest motion worse than no model."""
        dropped = self._flying.version
        version, self._next_version = self._next_version, self._next_version + 1
        record = self.slot.swap(None, version, t)
        self._flying = _Flying(None, version, None, ())
        self._model_changed()
        self._watch = None
        self._held = None  # trained on the dropped model's data: stale
        if self._gating is not None:
            g, self._gating = self._gating, None
            self._reject(t, g.held, f"stale: its base {g.held.outcome.base_version} was dropped", None)
        self.stats.drops += 1
        self.swaps.append(SwapEvent(t, version, record.swap_s, record.swap_s, record.swap_s, "drop"))
        reason = (f"model {dropped} predicts the last {verdict.ticks} ticks worse than nominal "
                  f"({verdict.error_model:.2f} vs {verdict.error_nominal:.2f} m/s^2 mean acceleration error)")
        self._log_model(t, version, "drop", reason, swap_s=record.swap_s)
        self._log_event(t, "warning", f"online: {reason}; flying nominal until the next accepted model")

    # --- paper lockstep ----------------------------------------------------------------------

    def _paper_step(self, t: float) -> None:
        """The paper's code: every window is trained at once while the simulation waits."""
        event = self.client.poll(0.0)
        if event is not None:
            self._on_event(event, t)
        if self._pending is None:
            return
        while self.client.state == "starting":  # a restart: wait for it (the client reports one that never comes up)
            event = self.client.poll(1.0)
            if event is not None:
                self._on_event(event, t)
        self._maybe_send(t)
        while self._out is not None:
            event = self.client.poll(self.client.timeout)
            if event is not None:
                self._on_event(event, t)
        if self._held is not None:
            self._start_gate(t)
        while self._gating is not None:  # the simulation waits anyway: the whole gate at once
            self._step_gate(t)

    # --- logging and summary -----------------------------------------------------------------

    def _record(self, out: TrainOutcome, sent_t: float, latency: float, outcome: str, reason: str,
                applied_t: float = math.nan, verdict: GateVerdict | None = None, received_t: float = math.nan) -> None:
        self.rounds.append(RoundRecord(
            out.round, out.version, (out.window_t0, out.window_t1), sent_t, latency, out.wall_s, out.cpu_s, out.loss,
            outcome, reason, applied_t, received_t,
            verdict.rmse_candidate if verdict else math.nan, verdict.rmse_current if verdict else math.nan,
        ))

    def _log_model(self, t: float, version: int, event: str, reason: str = "", out: TrainOutcome | None = None,
                   latency: float = math.nan, verdict: GateVerdict | None = None, swap_s: float = math.nan,
                   install_s: float = math.nan, slice_s: float = math.nan) -> None:
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
                       velocity_gain=verdict.velocity_gain, cross_gain=verdict.cross_gain)
        if math.isfinite(swap_s):
            msg["swap_ms"] = 1e3 * swap_s
        if math.isfinite(install_s):
            msg["install_ms"] = 1e3 * install_s
        if math.isfinite(slice_s):
            msg["slice_ms"] = 1e3 * slice_s
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
            else ("honest latency (lockstep, paced while training)" if self.s.lockstep else "real time")
        walls = np.asarray(s.train_wall_s)
        return {
            "online_mode": mode,
            "online_t_col_s": self.s.t_col,
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
            "partial_windows_discarded": self.recorder.discarded,
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
            "final_model_version": self._flying.version,
        }


def _tail(out: TrainOutcome, window: Window) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part of the training window the trainer held out (samples from its last training sample on)."""
    k = int(np.searchsorted(window.t, out.train_t1 - 1e-9))
    return window.t[k:], window.x[k:], window.u[k:]


def _ms(seconds: float) -> float:
    return 1e3 * float(seconds)


__all__ = [
    "GateLimits",
    "GatePairs",
    "GateVerdict",
    "LearnerSettings",
    "OnlineLearner",
    "OnlineStats",
    "RoundRecord",
    "SwapEvent",
    "TrainerClient",
    "TrainerFault",
    "WindowRecorder",
    "gate_pairs",
    "model_is_finite",
    "one_step_rmse",
    "operating_envelope",
    "run_gate",
]
