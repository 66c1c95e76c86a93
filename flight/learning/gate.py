"""The validation gate (beyond the paper): a trained candidate flies only if it is plausible and better.

Checks, in order: finite weights; a bounded residual and plausible Jacobians on the recent data
*and* the MPC's whole operating envelope (``GateLimits``); a lower one-step error than the flying
model on fresh data it never saw (beside the fast layer: constants aside, over a few steps, and by more
than a network fitted to noise scores).
``gate_steps`` runs it in slices of about a millisecond, one per tick gap; ``run_gate`` runs it at
once. Pure numpy: no torch here.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Generator

import numpy as np
from scipy.signal import butter, filtfilt

from cfknode.models.modelfile import ModelFile
from cfknode.models.residual_check import explained, layer_estimate
from cfknode.models.residual_np import ResidualQueue

# Same rules as offline training data (cfknode.models.training, which imports torch):
FILTER_ORDER = 2  # as cfknode.models.training: Butterworth, zero phase (filtfilt)
GAP_FACTOR = 3.0


@dataclass(frozen=True)
class GatePairs:
    """Filtered one-step pairs x0 --(u held for dt)--> x1 (numpy, for the gate)."""

    x0: np.ndarray
    u: np.ndarray
    dt: np.ndarray
    x1: np.ndarray
    nb: np.ndarray | None = None  # (m, 3) the neighbour's relative position at x0 (docs/fleet.md#neighbour-input)

    def __len__(self) -> int:
        return int(self.dt.shape[0])


@functools.lru_cache(maxsize=8)
def _butter(order: int, wn: float) -> tuple[np.ndarray, np.ndarray]:
    return butter(order, wn)


def gate_pairs(t: np.ndarray, x: np.ndarray, u: np.ndarray, filter_hz: float,
               nb: np.ndarray | None = None) -> GatePairs:
    """Pairs from one contiguous run, low-pass filtered exactly as ``make_dataset`` filters training data.

    (That function lives with torch in ``cfknode.models.training``; this is its torch-free twin
    for one gap-free segment.) ``nb``: the neighbour's relative position at each tick, when recorded.
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
    return GatePairs(x[:-1][ok], u[:-1][ok], dt[ok], x[1:][ok], None if nb is None else nb[:-1][ok])


def _evaluate(model: Any, x: np.ndarray, u: np.ndarray, d: np.ndarray | None) -> np.ndarray:
    """``model``'s residual, with the neighbour at relative position ``d`` when it takes one and ``d`` was recorded."""
    if d is None or not getattr(model, "takes_neighbour", False):
        return model.evaluate(x, u)
    return model.evaluate(x, u, x[:, 0:3] + d)


def one_step_rmse(model: ResidualQueue | Any | None, pairs: GatePairs, constant_free: bool = False) -> float:
    """One-step velocity RMSE (m/s) of nominal + ``model`` (RK4 over each pair's dt); None = nominal.

    ``constant_free``: each axis's mean error over the pairs is taken out first, so only what varies
    with the state counts (what is left when the fast layer supplies the constant)."""
    return rollout_rmse(model, pairs, 1, constant_free)


def rollout_rmse(model: ResidualQueue | Any | None, pairs: GatePairs, steps: int,
                 constant_free: bool = False) -> float:
    """Velocity RMSE (m/s) after ``steps`` consecutive pairs flown from each start by nominal + ``model``
    under the recorded commands (RK4 per pair); None = nominal. Only runs of linked pairs (one's end is the
    next one's start) are used; NaN if there is none. ``constant_free`` as in ``one_step_rmse``."""
    n = len(pairs)
    if n < steps or steps < 1:
        return math.nan
    if steps == 1:
        starts = np.arange(n)
    else:  # a start needs steps - 1 links after it: a gap removed from the pairs breaks the run
        broken = np.concatenate(([0], np.cumsum(~np.all(pairs.x1[:-1] == pairs.x0[1:], axis=1))))
        starts = np.flatnonzero(broken[steps - 1:] == broken[: n - steps + 1])
        if starts.size == 0:
            return math.nan

    def vdot(v: np.ndarray, u: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        if model is None:
            return u
        x = np.empty((v.shape[0], 6))
        x[:, 0:3] = 0.0  # the residual is translation invariant: position is only an input beside the neighbour's
        x[:, 3:6] = v
        return u + _evaluate(model, x, u, d)

    # p does not feed back into v', so RK4 on v alone is RK4 on the whole state for the v rows.
    v = pairs.x0[starts, 3:6]
    for k in range(steps):
        i = starts + k
        dt, u = pairs.dt[i, None], pairs.u[i]
        d = None if pairs.nb is None else pairs.nb[i]  # held over the pair, as the trainer holds it
        k1 = vdot(v, u, d)
        k2 = vdot(v + 0.5 * dt * k1, u, d)
        k3 = vdot(v + 0.5 * dt * k2, u, d)
        k4 = vdot(v + dt * k3, u, d)
        v = v + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    err = v - pairs.x1[starts + steps - 1, 3:6]
    if constant_free:
        err = err - err.mean(axis=0)
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
    velocity_coupling: float = math.nan  # largest |off-diagonal| of dr/dv, 1/s
    tilt_climb: float = math.nan  # m/s^2, largest climb gained by tilting either way at the box's top (``tilt_climb``)
    score: tuple[float, ...] = ()  # beside the layer: per axis, the share of what it leaves the candidate removes
    climb_feedback: float = math.nan  # largest dr_z/dv_z, 1/s
    # ``rejudge``: the flying model's score on the same fresh data in parts, per axis (``layer_scores``); empty when
    # not judged.
    flying_sums: tuple[tuple[float, ...], tuple[float, ...]] | tuple[()] = ()


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
      fits a spurious dr_z/du_x, and the MPC then tilts hard to "climb" (docs/history.md). The
      default still admits a small yaw misalignment between mocap and the vehicle.
    - no climb from tilt at the thrust limit: tilting either way at the top of the input box gains at most
      ``max_tilt_climb`` of climb (``tilt_climb``), a curvature a bound on each Jacobian cannot see.
    """

    max_residual: float
    control_gain: tuple[float, float]
    max_velocity_gain: float
    envelope_x: np.ndarray  # (m, 6); its velocities are rescaled to the data's when ``envelope_from_data``
    envelope_u: np.ndarray  # (m, 3)
    max_cross_gain: float = math.inf
    envelope_from_data: bool = False  # the envelope's speed is twice the recent data's fastest axis + 0.5 m/s
    # Beside the fast layer: compare one-step errors without their constant part, and ask the candidate
    # to be this fraction better. The layer already supplies the constant; a network that adds only
    # noise-fitted shape on top of it flew worse than the layer alone on plants with nothing to learn.
    constant_free: bool = False
    min_improvement: float = 0.0
    # ... and judge them over this many consecutive fresh pairs flown from each start, as the MPC uses a
    # model over its horizon: single steps passed networks a little better that made 1 s plans worse.
    steps: int = 1
    # ... and the gain must be at least this acceleration (m/s^2) over that rollout's time: on 0.1 s of fresh
    # data a few mm/s^2 is what a network fitted to noise scores, and such networks flew worse as often as better.
    min_gain: float = 0.0
    # m/s^2: the most climb a candidate may predict from tilting either way at the top of the input box (``tilt_climb``).
    max_tilt_climb: float = math.inf
    # Beside the fast layer: its observer and output cut-offs ((xy, z) Hz each). A candidate must remove part
    # of what the layer leaves on held-out data on some axis (``layer_scores``), the score `cfknode model
    # check` reports: one that only re-learns what the layer already takes is never flown.
    layer_hz: tuple[tuple[float, float], tuple[float, float]] | None = None
    # ... and remove more than this share of it on that axis (0: any positive share).
    min_score: float = 0.0
    # Beside the fast layer (its thrust scale carries the mass, and Mellinger tilts the thrust where the MPC asks):
    # the eigenvalues of sym(I + dr/du) over the horizontal commands. A model fitted while the attitude loop lagged
    # a ramp's commands learned 0.36 there, and the MPC then commanded 3x the tilt (a 10 cm error over the floor).
    horizontal_gain: tuple[float, float] = (0.0, math.inf)
    # Beside the fast layer: the largest |dr_i/dv_j|, i != j (1/s). A level quadrotor's drag acts along its own
    # velocity and its thrust loss along its climb; networks fitted on a take-off learned a vertical force from the
    # horizontal velocity (-0.15 to -0.38 per m/s), and on the slow circle it doubled the vertical error.
    max_velocity_coupling: float = math.inf
    # Beside the fast layer: the largest dr_z/dv_z (1/s). The air only takes thrust away with climb (-0.4 per m/s);
    # a vertical force growing with climb rate is the motors' lag left in the targets (+tau w^2 on an oscillation).
    # A network fitted under a 150 ms motor lag learned +0.24, and flown into the thrust limit it lost 20 cm sideways.
    max_climb_feedback: float = math.inf
    # Beside the fast layer: also score the flying model on every candidate's fresh data, which was flown under it,
    # so that the learner can stop flying the axes it no longer earns on (``flight/learning/rejudge.py``).
    rejudge: bool = False


def envelope_for(limits: GateLimits, recent_x: np.ndarray) -> np.ndarray:
    """The envelope's states: as configured, or scaled to the speed the recent data flew."""
    if not limits.envelope_from_data or recent_x.shape[0] == 0:
        return limits.envelope_x
    reach = float(np.max(np.abs(limits.envelope_x[:, 3:6]))) or 1.0
    speed = 2.0 * float(np.max(np.abs(recent_x[:, 3:6]))) + 0.5
    x = limits.envelope_x.copy()
    x[:, 3:6] *= speed / reach
    return x


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


def residual_verdict(model_file: ModelFile, model: ResidualQueue, xs: np.ndarray, us: np.ndarray,
                     max_residual: float) -> tuple[str, float]:
    """The gate's first rules: finite weights, and a finite residual no larger than ``max_residual``
    at every (xs, us). Returns (why it is refused, "" if it is not; the largest |residual|).
    Also what a model file given for a flight must pass before take-off."""
    if not model_is_finite(model_file):
        return "non-finite weights", math.nan
    with np.errstate(over="ignore", invalid="ignore"):  # an absurd model overflows: that is the verdict
        peak = float(np.max(np.abs(model.evaluate(xs, us))))
    if not math.isfinite(peak):
        return "non-finite residual", peak
    if peak > max_residual:
        return f"residual {peak:.3g} m/s^2 exceeds knode.max_residual {max_residual:g}", peak
    return "", peak


JACOBIAN_CHUNK = 20  # nodes per linearise call: the MPC's own batch size
TILT_FRACTIONS = (0.25, 0.5, 1.0)  # of the box's horizontal half-width: a bump inside the box counts too
TILT_STATES = 8  # envelope states (velocities) the tilt check is made at


def tilt_climb(model: ResidualQueue | Any, envelope_x: np.ndarray, envelope_u: np.ndarray) -> float:
    """Largest climb [m/s^2] ``model`` predicts from tilting the command either way along x or y, at the top of the
    input box (the thrust clamp), over the whole horizontal box: min over the two signs of r_z(+a) - r_z(0).

    At the clamp the thrust cannot grow, so a tilt either way can only cost climb. A residual that is even in
    u_x or u_y with its minimum at level (dr_z/du_y -0.04 below 0 and +0.04 above) passes a bound on each
    Jacobian, yet the MPC pinned at its vertical bound then swings the attitude to "climb". A term odd in the
    tilt (a yaw misalignment) gains on one side and loses on the other: the min over signs leaves it alone.
    """
    if envelope_u.shape[0] == 0:
        return 0.0
    top = float(envelope_u[:, 2].max())
    half = np.maximum(np.abs(envelope_u[:, :2]).max(axis=0), 1e-9)
    states = envelope_x[:: max(1, envelope_x.shape[0] // TILT_STATES)][:TILT_STATES]
    m = states.shape[0]
    offsets = [np.zeros(3)] + [sign * f * half[j] * np.eye(3)[j]
                               for j in (0, 1) for f in TILT_FRACTIONS for sign in (1.0, -1.0)]
    u = np.array([[0.0, 0.0, top] + o for o in offsets for _ in range(m)])
    x = np.tile(states, (len(offsets), 1))
    rz = np.asarray(model.evaluate(x, u))[:, 2].reshape(len(offsets), m)
    gain = rz[1:] - rz[0]  # (pairs of +/- offsets, states)
    return float(np.minimum(gain[0::2], gain[1::2]).max())




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


def _jacobian_extremes(candidate: Any, xs: np.ndarray, us: np.ndarray
                       ) -> Generator[None, None, tuple[float, ...] | None]:
    """Over the points, one slice per ``JACOBIAN_CHUNK``: the extreme eigenvalues of sym(I + dr/du) and of its
    horizontal block, the largest of sym(dr/dv), the largest |dr_i/du_j| and |dr_i/dv_j|, i != j, and the largest
    dr_z/dv_z. None: a non-finite one."""
    g_lo, g_hi, h_lo, h_hi, vgain, cross, vcross = math.inf, -math.inf, math.inf, -math.inf, -math.inf, 0.0, 0.0
    climb = -math.inf
    off = ~np.eye(3, dtype=bool)
    for i in range(0, xs.shape[0], JACOBIAN_CHUNK):
        _, jx, ju = candidate.linearise(xs[i : i + JACOBIAN_CHUNK], us[i : i + JACOBIAN_CHUNK])
        if not (math.isfinite(float(jx.sum())) and math.isfinite(float(ju.sum()))):
            return None
        gain = np.linalg.eigvalsh(0.5 * (ju + ju.transpose(0, 2, 1)) + np.eye(3))
        g_lo, g_hi = min(g_lo, float(gain.min())), max(g_hi, float(gain.max()))
        jh = ju[:, 0:2, 0:2]
        gain = np.linalg.eigvalsh(0.5 * (jh + jh.transpose(0, 2, 1)) + np.eye(2))
        h_lo, h_hi = min(h_lo, float(gain.min())), max(h_hi, float(gain.max()))
        jv = jx[:, :, 3:6]
        vgain = max(vgain, float(np.linalg.eigvalsh(0.5 * (jv + jv.transpose(0, 2, 1))).max()))
        cross = max(cross, float(np.abs(ju[:, off]).max()))
        vcross = max(vcross, float(np.abs(jv[:, off]).max()))
        climb = max(climb, float(jv[:, 2, 2].max()))
        yield
    return g_lo, g_hi, h_lo, h_hi, vgain, cross, vcross, climb


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
    envelope_x = envelope_for(limits, recent_x)
    xs = np.concatenate((recent_x, envelope_x))
    us = np.concatenate((recent_u, limits.envelope_u))
    reason, peak = residual_verdict(candidate_file, candidate, xs, us, limits.max_residual)
    if reason:
        return GateVerdict(False, reason, nan, nan, nan, peak, n)
    climb = tilt_climb(candidate, envelope_x, limits.envelope_u) if math.isfinite(limits.max_tilt_climb) else nan
    if climb > limits.max_tilt_climb:
        return GateVerdict(False, f"tilting either way gains {climb:.3g} m/s^2 of climb at the thrust limit "
                           f"(above {limits.max_tilt_climb:g})", nan, nan, nan, peak, n, tilt_climb=climb)
    yield
    # The MPC's Jacobians, at every 8th recent point and all envelope points, in the MPC's own
    # batch size: one call over ~150 nodes crossed OpenBLAS's threading threshold and took 10x
    # longer on the busy cores than the same work in small products.
    k = recent_x.shape[0]
    sel = np.concatenate((np.arange(0, k, 8), k + np.arange(envelope_x.shape[0])))
    extremes = yield from _jacobian_extremes(candidate, xs[sel], us[sel])
    if extremes is None:
        return GateVerdict(False, "non-finite Jacobian", nan, nan, nan, peak, n)
    g_lo, g_hi, h_lo, h_hi, vgain, cross, vcross, climb_fb = extremes
    cf, k = limits.constant_free, limits.steps
    e_cand = rollout_rmse(candidate, fresh, k, cf)
    yield
    e_cur = rollout_rmse(current, fresh, k, cf)
    yield
    e_nom = e_cur if current is None else rollout_rmse(None, fresh, k, cf)
    score = ()
    flying: tuple[tuple[float, ...], tuple[float, ...]] | tuple[()] = ()
    if limits.layer_hz is not None and n > 0:  # reported with every verdict from here on
        flying_too = limits.rejudge and current is not None and not getattr(current, "is_zero", True)
        judged, sums = layer_scores(candidate, current, fresh, limits.layer_hz, flying_too)
        score = tuple(float(v) for v in judged)
        if sums is not None:
            yield  # the flying model's parts make this slice a third longer: a tick gap before the rest
            flying = (tuple(float(v) for v in sums[0]), tuple(float(v) for v in sums[1]))

    def verdict(reason: str) -> GateVerdict:
        return GateVerdict(reason == "", reason, e_cand, e_cur, e_nom, peak, n, (g_lo, g_hi), vgain, cross, vcross,
                           climb, score, climb_fb, flying)

    implausible = _implausible(limits, extremes)
    if implausible:
        return verdict(implausible)
    if climb_fb > limits.max_climb_feedback:
        # Its vertical output does not fly; what it earned horizontally may (the score decides the axes flown).
        if not score or not max(score[:2]) > limits.min_score:
            return verdict(f"vertical force growing with climb rate, dr_z/dv_z {climb_fb:.2f} 1/s above "
                           f"{limits.max_climb_feedback:g} beside the fast layer (the motors' lag, not the air)")
        score = (score[0], score[1], min(score[2], 0.0))
    if n == 0 or not math.isfinite(e_cand):
        return verdict("no held-out data to judge it on")
    what = ("without constants, " if cf else "") + (f"over {k} steps, " if k > 1 else "")
    if not e_cand < e_cur * (1.0 - limits.min_improvement):
        need = f" by {limits.min_improvement:.0%}" if limits.min_improvement > 0.0 else ""
        return verdict(f"not better on held-out data{need} ({what}{e_cand:.4g} vs flying {e_cur:.4g} m/s)")
    gain = (e_cur - e_cand) / (k * float(np.median(fresh.dt)))  # m/s^2: the error removed per second of rollout
    if gain < limits.min_gain:
        return verdict(f"better by only {gain:.3g} m/s^2 on held-out data ({what}below {limits.min_gain:g}: noise)")
    if score:
        if not max(score) > limits.min_score:
            need = f", needs more than {limits.min_score:.0%} on some axis" if limits.min_score > 0.0 else ""
            return verdict("explains nothing beyond the fast layer on held-out data (score "
                           + " / ".join(f"{s:+.0%}" for s in score) + need + ")")
    return verdict("")


def _implausible(limits: GateLimits, extremes: tuple[float, ...]) -> str:
    """Why the Jacobians' extremes (``_jacobian_extremes``) are not a vehicle's, or ""."""
    g_lo, g_hi, h_lo, h_hi, vgain, cross, vcross, _ = extremes
    lo, hi = limits.control_gain
    if g_lo < lo or g_hi > hi:
        return f"control effectiveness {g_lo:.2f}..{g_hi:.2f} outside {lo:g}..{hi:g}"
    if h_lo < limits.horizontal_gain[0] or h_hi > limits.horizontal_gain[1]:
        return (f"horizontal control effectiveness {h_lo:.2f}..{h_hi:.2f} outside "
                f"{limits.horizontal_gain[0]:g}..{limits.horizontal_gain[1]:g} beside the fast layer")
    if vgain > limits.max_velocity_gain:
        return f"velocity feedback {vgain:.2f} 1/s above {limits.max_velocity_gain:g} (phantom instability)"
    if cross > limits.max_cross_gain:
        return f"cross-coupling |dr_i/du_j| {cross:.2f} above {limits.max_cross_gain:g}"
    if vcross > limits.max_velocity_coupling:
        return (f"velocity coupling |dr_i/dv_j| {vcross:.2f} 1/s above {limits.max_velocity_coupling:g} "
                "beside the fast layer")
    return ""


def layer_scores(candidate: Any, current: Any | None, pairs: GatePairs,
                 layer_hz: tuple[tuple[float, float], tuple[float, float]], flying_too: bool = False
                 ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """Per axis, the share of what the fast layer leaves of the flying model's error on ``pairs`` that the
    candidate (in its place) and the layer remove together (``residual_check.shares(...).beyond_layer``); with
    ``flying_too`` also the flying model's own score on ``pairs`` in parts that add up over rounds
    (``rejudge.py``): per axis, the sums of squares the layer leaves without it and with it. What the layer
    leaves of the flying model's error is computed once for both."""
    t = np.concatenate(([0.0], np.cumsum(pairs.dt[:-1])))
    raw = (pairs.x1[:, 3:6] - pairs.x0[:, 3:6]) / pairs.dt[:, None] - pairs.u
    flying = _evaluate(current, pairs.x0, pairs.u, pairs.nb) if current is not None else 0.0
    r = raw - flying
    layer_left = r - layer_estimate(t, r, *layer_hz)
    rest = r - (_evaluate(candidate, pairs.x0, pairs.u, pairs.nb) - flying)
    score = explained(layer_left, rest - layer_estimate(t, rest, *layer_hz))
    if not flying_too:
        return score, None
    alone = raw - layer_estimate(t, raw, *layer_hz)
    return score, (np.sum(alone**2, axis=0), np.sum(layer_left**2, axis=0))


__all__ = [
    "GateLimits",
    "layer_scores",
    "GatePairs",
    "GateVerdict",
    "gate_pairs",
    "gate_steps",
    "model_is_finite",
    "one_step_rmse",
    "operating_envelope",
    "rollout_rmse",
    "run_gate",
    "tilt_climb",
]
