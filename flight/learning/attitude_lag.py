"""The attitude loop's lag, identified in flight, so that the MPC plans from where the commands already sent take it.

The MPC's model flies a command at once (v' = u); the firmware tilts the thrust toward it through its attitude loop,
about a first-order lag of 0.1-0.2 s. On a fast loop that lag, not the air, is most of the error (docs/results.md,
"The attitude loop's lag, learned in flight"). It is a property of the vehicle (its firmware gains, propellers and
battery), not of the manoeuvre, and it can be measured without any model of the air: the horizontal acceleration the
measured attitude gives, |u + g| along the body's z axis, against the same along the attitude sent (the setpoint's
roll and pitch: what the thrust clamp and the tilt limit let through). Every ``span_s`` of tracking this identifier
fits flown = lag_tau(sent) + c per axis (the gain held at 1) over a grid of time constants; a fit that explains
the tilt (R^2 of at least ``min_fit``) and clearly better than no lag is kept, and the command path
(``flight/latency.py``) then predicts through the median of the lags kept, planning ``horizon`` times it ahead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.signal import lfilter

from cfknode.flight.adaptation.loop import body_z_floats
from cfknode.flight.mellinger import measured_yaw, setpoint_body_z

TAUS = np.round(np.arange(0.02, 0.4001, 0.02), 3)  # s: the grid of time constants tried (refined between points)
MIN_GAIN = 0.05  # the R^2 a kept fit must gain over no lag (a hover's noise fits any lag about as well)
MIN_TILT_STD = 0.05  # m/s^2: a span whose tilt moved less than this says nothing about its lag
RETUNE_STEP = 0.01  # s: the lag flown changes only by more than this (each change restarts the prediction)
MIN_KEPT = 3  # fits kept before a lag is flown: one span's best lag spreads 0.11-0.19 s where their median is 0.15
TRACK_STATES = ("", "TRACK")  # a take-off's or landing's tilt is the supervisor's, not the MPC's
FLOWN_SOURCES = ("mpc", "fallback", "geometric", "brake")  # ticks that sent an attitude the controller chose


@dataclass(frozen=True)
class LagFit:
    """One span's fit: the time constant (s), the R^2 with it and with no lag (the tilt following u at once)."""

    tau: float
    fit: float
    fit_none: float


@dataclass(frozen=True)
class AttitudeLagSettings:
    span_s: float  # s of tracking per fit
    min_fit: float  # the R^2 a fit needs to be kept
    horizon: float  # the MPC plans this times the lag ahead (estimator.command_delay)
    residual_tau: float  # s: the command path's low-pass of what the commands leave (estimator.command_residual_tau)


def sent_body_z(roll_deg: float, pitch_deg: float, q: Any) -> tuple[float, float]:
    """The world x and y of the body z axis the setpoint asks for: its roll and pitch about the measured yaw of ``q``
    (w, x, y, z), as the firmware's angle loop rebuilds it (``flight/mellinger.py``'s ``force_to_setpoint``). In
    floats, every tick: through ``models.quadrotor``'s numpy quaternions it took 9 us."""
    return setpoint_body_z(roll_deg, pitch_deg, measured_yaw(q))


def lagged(u: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``u`` (n, k), sampled every ``dt`` s, through a first-order lag of ``tau`` s that starts at ``u[0]``."""
    if tau <= 0.0:
        return u
    a = -math.expm1(-dt / tau)
    y, _ = lfilter([a], [1.0, a - 1.0], u, axis=0, zi=((1.0 - a) * u[:1]))
    return y


def _r2(ys: np.ndarray, flown: np.ndarray) -> np.ndarray:
    """R^2 of flown = y + c per axis (c least squares) over both axes, for each y of ``ys`` (m, n, 2), in one
    vectorised pass. The gain is held at 1: the firmware's angle loop holds an attitude in the end (its integral
    term), and a free gain would let a wrong lag's amplitude pass for a smaller tilt."""
    df = flown - flown.mean(axis=0)
    sst = float(np.sum(df * df))
    e = ys - flown
    e = e - e.mean(axis=1, keepdims=True)
    sse = np.sum(e * e, axis=(1, 2))
    return 1.0 - sse / sst if sst > 0.0 else np.zeros(len(ys))


def fit_lag(t: np.ndarray, u: np.ndarray, flown: np.ndarray) -> LagFit:
    """The first-order lag that best takes the commanded horizontal accelerations ``u`` (n, 2) to the flown ones
    (n, 2), sampled at the times ``t`` (n,): the grid's best, refined by a parabola through it and its neighbours."""
    dt = float(np.median(np.diff(t)))
    fits = _r2(np.stack([u, *(lagged(u, float(tau), dt) for tau in TAUS)]), flown)
    none, fits = float(fits[0]), fits[1:]
    i = int(np.argmax(fits))
    tau = float(TAUS[i])
    if 0 < i < len(TAUS) - 1:
        lo, mid, hi = fits[i - 1], fits[i], fits[i + 1]
        curve = lo - 2.0 * mid + hi
        if curve < 0.0:
            tau += float(TAUS[1] - TAUS[0]) * 0.5 * (lo - hi) / curve
    return LagFit(tau, float(fits[i]), none)


@dataclass(frozen=True)
class CommandPathModel:
    """What the command path flies: its horizon (s ahead) and the lag (s)."""

    delay: float
    lag: float


class AttitudeLagIdentifier:
    """A tick observer: identifies the lag from the ticks it sees and retunes ``path`` (a ``CommandDelayPredictor``).

    ``slot``: the drone's ``ModelSlot``: a fleet drone's drone above is taken as far ahead as the plan starts, and a
    wake-only model's vertical force where the drone is when the thrust acts. ``log``: where each kept fit is said
    (``/events``)."""

    def __init__(self, settings: AttitudeLagSettings, path: Any, log: Any, gravity: float,
                 rate_hz: float, slot: Any = None) -> None:
        self.s = settings
        self._path = path
        self._log = log
        self._g = gravity
        self._slot = slot
        self._max_gap = 3.0 / rate_hz
        n = int(math.ceil(settings.span_s * rate_hz)) + 8
        self._t = np.empty(n)
        self._u = np.empty((n, 2))
        self._f = np.empty((n, 2))
        self._n = 0
        self.fits: list[LagFit] = []  # every span fitted
        self.kept: list[float] = []  # the lags of the fits kept
        self.flown: CommandPathModel | None = None
        self._offset: Any = None  # the fast layer's newest offset: what the command path's residual starts from

    def on_tick(self, tick: Any) -> None:
        est = tick.est
        if (est is None or tick.source not in FLOWN_SOURCES or getattr(tick, "supervisor_state", "") not in TRACK_STATES
                or (self._n > 0 and not 0.0 < tick.t - self._t[self._n - 1] <= self._max_gap)):
            self._n = 0
            return
        acc = np.asarray(tick.acc, dtype=float)
        self._offset = None if tick.layer is None else tick.layer.offset
        i = self._n
        self._t[i] = tick.t
        thrust = math.sqrt(acc[0] ** 2 + acc[1] ** 2 + (acc[2] + self._g) ** 2)
        zx, zy, _ = body_z_floats(est.q)
        sx, sy = sent_body_z(tick.setpoint.roll_deg, tick.setpoint.pitch_deg, est.q)
        self._u[i] = (thrust * sx, thrust * sy)
        self._f[i] = (thrust * zx, thrust * zy)
        self._n = i + 1
        if tick.t - self._t[0] >= self.s.span_s or self._n == len(self._t):
            self._fit(tick.t)
            self._n = 0

    def _fit(self, now: float) -> None:
        f = self._f[: self._n]
        if float(np.sqrt(np.mean(np.var(f, axis=0)))) < MIN_TILT_STD:
            return
        fit = fit_lag(self._t[: self._n], self._u[: self._n], f)
        self.fits.append(fit)
        if fit.fit < self.s.min_fit or fit.fit - fit.fit_none < MIN_GAIN:
            return
        self.kept.append(fit.tau)
        if len(self.kept) < MIN_KEPT:
            return
        tau = float(np.median(self.kept))
        if self.flown is not None and abs(tau - self.flown.lag) <= RETUNE_STEP:
            return
        self.flown = CommandPathModel(self.s.horizon * tau, tau)
        self._path.retune(self.flown.delay, self.flown.lag, self.s.residual_tau, self._offset)
        if self._slot is not None:
            self._slot.vertical_lead = self.flown.delay
            if getattr(self._slot, "neighbour", None) is not None:
                self._slot.neighbour.lead = self.flown.delay
        self._log.write("/events", now, {
            "level": "info", "source": "online",
            "text": f"attitude loop lag {tau * 1e3:.0f} ms (fit R^2 {fit.fit:.3f}, {fit.fit_none:.3f} with none): "
                    f"the MPC plans {self.flown.delay * 1e3:.0f} ms ahead"})

    def summary_fields(self) -> dict[str, Any]:
        """The flight summary's account: the lag flown (s; absent when none was kept) and the spans fitted and kept."""
        out: dict[str, Any] = {"attitude_lag_fits": len(self.fits), "attitude_lag_kept": len(self.kept)}
        if self.flown is not None:
            out["attitude_lag_s"] = self.flown.lag
        return out


__all__ = ["AttitudeLagIdentifier", "AttitudeLagSettings", "CommandPathModel", "LagFit", "fit_lag", "lagged",
           "sent_body_z"]
