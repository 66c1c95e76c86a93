"""The fast adaptation layer in the flight loop: one object the loop asks before the solve and tells after.

Kept apart from the loop so it can move into a controller object as a whole. Per tick:
``before_solve`` (reset / freeze / re-base / update) -> ``residual`` (the model's residual with the
offset added to its constant term: a parameter write) -> ``shaping`` (thrust from the estimated mass,
tilt over the axis gain, the thrust cone) -> ``after_command`` (what was flown, for the next update).

Rules: reset off the air (not flying, landed, emergency); frozen near the ground and while landing
(ground effect and contact are not the model's, and a landing keeps the mass it knew); frozen while
mocap is stale (inside ``FastAdaptation``); re-based when the model slot's version changes.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Sequence

import numpy as np

from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.flight.adaptation.accel_path import (
    AccelState, AccelTuning, accel_part, accel_step, saturated, world_residual,
)
from cfknode.flight.adaptation.composite import CoefficientSettings, ModelCoefficients
from cfknode.models.residual_check import flown_axes
from cfknode.flight.adaptation.estimate import AdaptationEstimate
from cfknode.flight.adaptation.layer import FastAdaptation, LoopExtras
from cfknode.flight.adaptation.settings import settings_from_controller
from cfknode.flight.adaptation.thrust_lag import ThrustLagBank
from cfknode.flight.adaptation.wake_guard import LAG_HOLD_S
from cfknode.flight.mellinger import CommandShaping, ShapedForce
from cfknode.flight.mpc import ResidualLinearisation

GROUND_MARGIN = 0.1  # m above the floor: below, the ground carries part of the weight
_NO_RESIDUAL = np.zeros(3)  # the model's residual without a model: shared, so read-only
_NO_RESIDUAL.flags.writeable = False
_RESET_STATES = ("IDLE", "PREFLIGHT", "LANDED", "EMERGENCY")
_FROZEN_STATES = ("LAND",)


class LoopAdaptation:
    def __init__(self, ctrl: ControllerConfig, vehicle: VehicleConfig, ground_z: float | None = None) -> None:
        self.ctrl, self.vehicle = ctrl, vehicle
        self.layer = FastAdaptation(settings_from_controller(ctrl), ctrl.rate_hz, vehicle.gravity)
        self._u = np.zeros(3)  # last command after the Mellinger layer's limits (model input space)
        self._r = np.zeros(3)  # the model's residual for it
        self._thrust = 0.0  # N, collective thrust sent for it
        # The thrust acting now is the sent one through the motors' lag: configured, or (null) chosen in flight
        # among the candidates and the vehicle's (thrust_lag.py).
        tuning = ctrl.adaptation_settings
        fixed = tuning.thrust_lag_s is not None
        self.lags = ThrustLagBank(() if fixed else tuning.thrust_lag_candidates_s,
                                  tuning.thrust_lag_s if fixed else vehicle.motor_time_constant, ctrl.rate_hz)
        self._sat = (False, False)
        self._have_command = False
        self._version: int | None = None
        self._ground = ground_z  # None: the first estimate's height
        self._low = False  # on the pattern below the layer's floor margin: the layer holds, a model owns the vertical
        self.saturated_ticks = 0
        self._zeros: dict[int, ResidualLinearisation] = {}  # per horizon: the zero residual, built once
        self.stepping_ticks = 0  # ticks flown while a step was tracked
        self.frozen_ticks = 0  # ticks flown with the estimate frozen (stale pose, a stalled host)
        self.longest_step_s = 0.0  # s, the longest a step was tracked
        self._now = 0.0
        self._acting_recent: deque[tuple[float, float]] = deque(maxlen=64)  # (t, acting thrust N): 160 ms of ticks
        self._imu_t = -float("inf")  # the newest accelerometer sample used
        self._accel_tuning = accel_tuning(self.layer)  # None: the fast path is off
        self._accel: AccelState | None = None
        # The model's per-axis coefficients (composite.py): built when a model flies, None without one.
        self._coeff_settings = CoefficientSettings(tuning.coefficient_bounds, tuning.coefficient_memory_s,
                                                   tuning.coefficient_prior, tuning.model_mean_s)
        self.coefficients: ModelCoefficients | None = None
        # A fleet drone's view of the others (flight/neighbours.py ``NeighbourFeed``): the layer calls no heavier step
        # under the drone above (wake_guard.py). None: alone, or a model slot's neighbour stands in.
        self.neighbour: Any = None
        self._wake_t = -float("inf")  # s: the last tick under a wake or within its hold (wake_guard.py)
        self._coefficients_flown: tuple[np.ndarray, np.ndarray] | None = None  # (a, m) at the last off-air reset

    @property
    def estimate(self) -> AdaptationEstimate:
        """What the controller flies with: the estimate on the axes where it acts (``FastAdaptation.applied``)."""
        return self.layer.applied

    def f_max(self) -> float:
        """Specific thrust at the clamp [m/s^2] for the mass flown with."""
        mass = self.vehicle.mass * self.layer.applied.thrust_scale
        return self.ctrl.max_thrust_fraction * self.vehicle.max_thrust / mass

    def off_air(self) -> None:
        """A tick not flown by the controller (blind, motors off): start over next time."""
        if self._have_command:
            self.layer.reset()
            self.lags.forget_velocity()
            if self.coefficients is not None:  # the summary reports them as flown, not as reset on the ground
                self._coefficients_flown = (self.coefficients.a.copy(), self.coefficients.mean.copy())
                self.coefficients.reset()
        self._have_command = False
        self._low = False
        self._accel = None

    def before_solve(self, now: float, est: Any, pose_fresh: bool, state: str, model: Any) -> AdaptationEstimate:
        if self._ground is None:
            self._ground = float(est.p[2])
        if state in _RESET_STATES:
            self.off_air()
            return self.layer.applied
        version = model.version if model is not None else 0
        self._use_coefficients(model)
        if self._version is not None and version != self._version:
            self._rebase(model)
        self._version = version
        if not self._have_command:
            return self.layer.applied
        airborne = self._above_floor(est) and state not in _FROZEN_STATES
        self._low = state == "TRACK" and not airborne
        if self.layer.stalled(now):  # a stalled host: the lags start from the new pose too
            self.lags.forget_velocity()
        x = measured_state(est)
        bz = body_z_floats(est.q)
        u_flown = self.flown_acc(bz)
        coeffs = self.coefficients
        predicted = self._r if coeffs is None else coeffs.prediction(self._r)
        seen = getattr(model, "last_neighbour", None)
        above = seen if seen is not None or self.neighbour is None else self.neighbour.above(est.p)
        # Under another drone's wake, or just past one, its push would pass for the motors' lag (the longest fits it
        # best): not learned then, from the frames, the samples or a step's fit.
        e, wake = self.layer.estimate, self.layer.wake
        in_wake = wake.reaches(est.p, above) or wake.held(now, LAG_HOLD_S)
        self._wake_t = now if in_wake else self._wake_t
        learn_lag = not (e.stepping or self._sat[0] or in_wake)
        if airborne:  # the lag bank learns from the same frames as the layer
            self.lags.observe(est.v.item(2), bz[2], self.vehicle.mass * e.thrust_scale, self.vehicle.gravity,
                              predicted.item(2) + e.offset.item(2), pose_fresh, learn=learn_lag)
        else:
            self.lags.forget_velocity()
        by_lag = self.lags.acting_scaled(bz[2], self.vehicle.mass)
        imu = self._imu_theta(now, est, learn_lag) if airborne else None
        fast = self._accel_part(now, est, airborne, predicted)
        extras = LoopExtras(u_commanded=self._u, thrust_by_lag=by_lag, lag=self.lags.choice, imu_theta=imu,
                            accel_part=fast, neighbour=seen, above=above)
        self.layer.update(now, est.v, x, u_flown, u_flown + predicted, self._sat, pose_fresh and airborne, extras)
        if coeffs is not None and self.layer.s.enabled and not self.layer.estimate.frozen:
            e = self.layer.estimate
            shift = coeffs.tick(self._r, self.layer.sigma, self.layer.omega, self.layer.dt,
                                learn=not (e.stepping or e.saturated), steady=state == "TRACK")
            self.layer.reexpress(shift)
        # A step's fit is the lag's strongest evidence, but not of a step begun in a wake or its hold: fitted after
        # the hold, the wake's departure passed for the longest lag (150 ms) in crossings under another drone.
        fitted = self.layer.fit_lag
        if fitted is not None and fitted[1] > self._wake_t:
            self.lags.choose(fitted[0])
        self._count(now)
        return self.layer.applied

    def _count(self, now: float) -> None:
        """The layer's state over the flight, for the summary: a user sees when it was not learning."""
        e = self.layer.estimate
        self._now = now
        self.stepping_ticks += int(e.stepping)
        self.frozen_ticks += int(e.frozen)
        self.longest_step_s = max(self.longest_step_s, self.layer.tracker.tracked_s(now))

    def _imu_theta(self, now: float, est: Any, learn_lag: bool) -> tuple[float, float] | None:
        """(time, theta) of an accelerometer sample new since the last tick: the specific force along the body
        axis over the thrust acting when it was measured, per nominal mass. None without a new sample. The lag
        bank learns from the sample when ``learn_lag``."""
        acting = self.lags.acting()
        if acting is not None:
            self._acting_recent.append((now, acting))
        imu = getattr(est, "imu", None)
        if imu is None or imu.t <= self._imu_t or not self._acting_recent:
            return None
        self._imu_t = imu.t
        thrust = self._thrust_at(imu.t)
        if thrust is None or thrust <= 0.0:
            return None
        e = self.layer.estimate
        self.lags.observe_specific_force(float(imu.specific_force[2]), 1.0 / e.thrust_scale, self.vehicle.mass,
                                         learn=learn_lag)
        return imu.t, self._theta(imu, thrust)

    def needs_sample_now(self, now: float, est: Any) -> bool:
        """Whether ``est``'s accelerometer sample must be learned before this tick's solve: a step is being
        tracked (its samples set the mass), the sample raises a step's alarm, or the fast path (accel_path.py)
        moves with every sample. Any other sample only teaches the step detector its noise level and the bank
        its lag, which can wait for the send. Reads, changes nothing."""
        if self._accel_tuning is not None or self._ground is None:
            return True
        imu = getattr(est, "imu", None)
        if imu is None or imu.t <= self._imu_t or not self._have_command:
            return False
        if not self._above_floor(est):  # on the floor the layer does not read samples
            return False
        acting = self.lags.acting()
        thrust = self._thrust_at(imu.t, (now, acting) if acting is not None else None)
        if thrust is None or thrust <= 0.0:
            return False
        return self.layer.needs_sample(now, self._theta(imu, thrust))

    def _above_floor(self, est: Any) -> bool:
        """Above the floor's margin, where the ground carries none of the weight (the layer learns only there)."""
        return float(est.p[2]) > self._ground + GROUND_MARGIN  # type: ignore[operator]

    def _theta(self, imu: Any, thrust: float) -> float:
        """A sample's theta: the specific force along the body axis over the acting ``thrust`` per nominal mass."""
        return float(imu.specific_force[2]) * self.vehicle.mass / thrust

    def _thrust_at(self, t: float, newest: tuple[float, float] | None = None) -> float | None:
        """The acting thrust (N) of the tick a sample at ``t`` fell in: the newest tick at or before it (the
        oldest kept, for an older sample); ``newest``: a (tick, thrust) not yet recorded. None before any."""
        if newest is not None and newest[0] <= t:
            return newest[1]
        for tick, value in reversed(self._acting_recent):  # a sample is from the last few ticks: search back
            if tick <= t:
                return value
        if self._acting_recent:
            return self._acting_recent[0][1]
        return newest[1] if newest is not None else None

    def _accel_part(self, now: float, est: Any, airborne: bool, predicted: np.ndarray) -> np.ndarray | None:
        """The accelerometer fast path's part this tick (accel_path.py), None when it is off, on the ground, or
        without a usable sample for ``accel_stale_s``. A new sample's residual is its measured acceleration in
        the world less the model's for the thrust acting when it was measured, along the measured attitude, with
        the residual the MPC predicts with (``predicted``)."""
        tuning = self._accel_tuning
        if tuning is None:
            return None
        if not airborne:  # the floor's reaction is no disturbance to learn
            self._accel = None
            return None
        imu = getattr(est, "imu", None)
        newest = self._accel.t if self._accel is not None else -float("inf")
        if imu is not None and imu.t > newest and not saturated(imu.specific_force):
            thrust = self._thrust_at(imu.t)
            if thrust is not None:
                mass = self.vehicle.mass * self.layer.estimate.thrust_scale
                model = (thrust / mass) * body_z(est.q) + predicted  # gravity cancels: world_residual takes g e_z
                model[2] -= self.vehicle.gravity
                d = world_residual(est.q, imu.specific_force, self.vehicle.gravity, model)
                self._accel = accel_step(self._accel, imu.t, d, tuning)
        return accel_part(self._accel, now, tuning)

    def flown_acc(self, bz: Sequence[float]) -> np.ndarray:
        """The last command as flown: the acting thrust along the measured body z axis ``bz`` (three floats), over
        the estimated mass."""
        mass = self.vehicle.mass * self.layer.estimate.thrust_scale
        acting = self.lags.acting()
        k = (self._thrust if acting is None else acting) / mass
        x, y, z = bz  # floats: one array built, not three
        return np.array([k * x, k * y, k * z - self.vehicle.gravity])

    def residual(self, model_residual: ResidualLinearisation | None, horizon: int) -> ResidualLinearisation | None:
        """The MPC's residual: the model's, with the applied offset added to every stage's constant. No model and
        no offset (the layer acting on no axis): None, which the MPC flies as a zero residual, with no arrays
        built for it."""
        if not self.layer.s.enabled:
            return model_residual
        applied = self.layer.applied
        offset = applied.offset
        if model_residual is not None and self.coefficients is not None:
            return self.coefficients.linearisation(model_residual, offset, vertical_acts=applied.acts[2],
                                                   model_vertical=self._low)
        if model_residual is None:
            if not any(offset.tolist()):
                return None
            zero = self._zeros.get(horizon)
            if zero is None:
                zero = self._zeros[horizon] = ResidualLinearisation.zeros(horizon)
            c = np.empty(zero.c.shape)  # the offset on every stage: a fill costs a tenth of np.broadcast_to
            c[:] = offset
            return ResidualLinearisation(c, zero.jx, zero.ju)
        return ResidualLinearisation(model_residual.c + offset, model_residual.jx, model_residual.ju)

    def shaping(self) -> CommandShaping:
        e = self.layer.applied
        return CommandShaping(thrust_scale=e.thrust_scale, axis_gain=(float(e.axis_gain[0]), float(e.axis_gain[1])))

    def after_command(self, x0: np.ndarray, shaped: ShapedForce, thrust_cmd: int,
                      model_residual: ResidualLinearisation | None) -> None:
        """Remember what was flown: the command after the limits, the thrust sent, the model's residual for it."""
        u = np.asarray(shaped.applied_acc, dtype=float)
        r = _NO_RESIDUAL
        if model_residual is not None:  # stage 0 of the model's own linearisation (no extra network pass)
            r = model_residual.c[0] + model_residual.jx[0] @ x0 + model_residual.ju[0] @ u
            if self.coefficients is not None:  # the thrust's effectiveness is the thrust scale's (composite.py)
                r[2] -= model_residual.ju[0, 2, 2] * u[2]
        self._u, self._r = u, r
        self._thrust = thrust_cmd * self.vehicle.newton_per_cmd
        # The observer compares the vehicle with the thrust that acts, not the one just sent: without the motors'
        # lag every thrust change looks like a disturbance for a few ticks, and the observer rings on it.
        self.lags.sent(self._thrust)
        self._sat = (shaped.thrust_saturated, shaped.tilt_saturated)
        self.saturated_ticks += int(shaped.thrust_saturated or shaped.tilt_saturated)
        self._have_command = True

    def _use_coefficients(self, model: Any) -> None:
        """Coefficients while a model flies (and ``model_coefficients`` is on); none without one, so a flight
        without a model is the layer's alone."""
        flying = model is not None and model.model is not None and self.layer.s.model_coefficients
        if flying and self.coefficients is None:
            self.coefficients = ModelCoefficients(self._coeff_settings, self.ctrl.rate_hz, self._flown(model))
        elif not flying:
            self.coefficients = None

    def _flown(self, model: Any) -> tuple[bool, bool, bool]:
        """The axes ``model`` flies on beside the layer: by its stored score (all of them without one)."""
        score = getattr(model.model, "beyond_layer", None) if model is not None else None
        return flown_axes(score, self.layer.s.model_min_score) or (True, True, True)

    def _rebase(self, model: Any) -> None:
        """A swap: the new model's prediction on the recent ticks, the coefficients restarted on it (a = 1,
        its mean there), and the layer's offset re-based so that model + layer is continuous."""
        x, u, _, nb = self.layer.recent()
        inner = model.model if model is not None else None
        new_acc = u.copy()
        if inner is not None and x.shape[0]:
            if self.coefficients is not None:
                c, jx, ju = where_flown(inner.linearise, inner, x, u, nb)
                r = self.coefficients.features(c, jx, ju, x, u)
            else:
                r = np.asarray(where_flown(inner.evaluate, inner, x, u, nb), dtype=float)
            if r.shape == u.shape and np.all(np.isfinite(r)):
                if self.coefficients is not None:
                    self.coefficients.restart(r, self._flown(model), self.layer.estimate.offset)
                    r = self.coefficients.predictions(r)
                new_acc = u + r
        elif self.coefficients is not None:
            self.coefficients.reset()
        self.layer.rebase(new_acc)

    def log(self) -> dict[str, Any]:
        e = self.layer.estimate
        return {**self.layer.applied.to_log(), "f_max": self.f_max(), "mode": self.layer.s.mode,
                "estimate_offset": e.offset.tolist(), "estimate_thrust_scale": e.thrust_scale,
                "tracking_s": self.layer.tracker.tracked_s(self._now)}

    def summary(self) -> dict[str, Any]:
        e = self.layer.estimate
        return {"adaptation": self.layer.s.mode, "adaptation_thrust_scale_end": round(e.thrust_scale, 4),
                "adaptation_steps": self.layer.steps, "adaptation_thrust_lag_s": self.lags.lag_s,
                "adaptation_offset_end": [round(float(v), 4) for v in e.offset],
                "adaptation_saturated_ticks": self.saturated_ticks, "adaptation_resets": self.layer.resets,
                "adaptation_rebases": self.layer.rebases,
                "adaptation_acts_end": list(self.layer.applied.acts),
                "adaptation_state": self.state_summary(), **self._coefficient_summary()}

    def _coefficient_summary(self) -> dict[str, Any]:
        """The model's coefficients and mean at the end (as flown, before the landing's reset) and the axes it
        flew on, when a model flew with them."""
        c = self.coefficients
        if c is None:
            return {}
        flown = self._coefficients_flown if not self._have_command else None  # on the ground: as last flown
        a, mean = (c.a, c.mean) if flown is None else flown
        return {"adaptation_model_coefficients_end": [round(float(v), 4) for v in a],
                "adaptation_model_mean_end": [round(float(v), 4) for v in mean],
                "adaptation_model_axes": "".join(ax for ax, f in zip("xyz", c.flown.tolist()) if f) or "none"}

    def state_summary(self) -> dict[str, Any]:
        """The layer's state over the flight, one summary field: whether it was tracking a step at the end, for
        how many ticks it tracked one or was frozen, its longest step and how many the cap ended."""
        return {"stepping_end": self.layer.estimate.stepping, "stepping_ticks": self.stepping_ticks,
                "frozen_ticks": self.frozen_ticks, "longest_step_s": round(self.longest_step_s, 4),
                "steps_capped": self.layer.tracker.capped}


def accel_tuning(layer: FastAdaptation) -> AccelTuning | None:
    """The fast path's constants from the layer's settings: it complements the layer's own observer and output
    poles (x, y, vertical). None when ``accel_cutoff_hz`` is 0 or the layer is off."""
    s = layer.s
    if s.accel_cutoff_hz <= 0.0 or not s.enabled:
        return None
    return AccelTuning(s.accel_cutoff_hz, layer.omega.copy(), layer.omega_out.copy(), s.accel_max_offset,
                       s.accel_stale_s)


def where_flown(method: Any, model: Any, x: np.ndarray, u: np.ndarray, neighbour: np.ndarray) -> Any:
    """``model.evaluate`` or ``model.linearise`` (``method``) on recent ticks, each at the neighbour position the
    flying model saw there (NaN rows, or a model without the neighbour input: as ``method(x, u)``)."""
    known = np.all(np.isfinite(neighbour), axis=1)
    if not getattr(model, "takes_neighbour", False) or not known.any():
        return method(x, u)
    if known.all():
        return method(x, u, neighbour)
    out, part = method(x, u), method(x[known], u[known], neighbour[known])
    if isinstance(out, tuple):
        for whole, some in zip(out, part):
            whole[known] = some
        return out
    out[known] = part
    return out


def measured_state(est: Any) -> np.ndarray:
    """(position, velocity) in one array. The position is the newest mocap frame's carried to the estimate's time
    with the estimated velocity (the filter's own position lags under a sudden acceleration, which would bias the
    step fit); the filter's without one. Floats: p + (t - t_frame) v element by element, the arrays' numbers."""
    v = est.v.tolist()
    frame = getattr(est, "frame", None)
    if frame is None:
        return np.array([*est.p.tolist(), *v])
    t_frame, p = frame
    dt = est.t - t_frame
    px, py, pz = p.tolist()
    return np.array([px + dt * v[0], py + dt * v[1], pz + dt * v[2], *v])


def body_z(q: Any) -> np.ndarray:
    """The body z axis in the world from a (w, x, y, z) quaternion."""
    return np.array(body_z_floats(q))


def body_z_floats(q: Any) -> tuple[float, float, float]:
    """``body_z`` as three floats (what the tick's scalar arithmetic reads, without an array between)."""
    w, x, y, z = np.asarray(q, dtype=float).tolist()
    return 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)


__all__ = ["GROUND_MARGIN", "LoopAdaptation", "body_z", "body_z_floats", "measured_state", "where_flown"]
