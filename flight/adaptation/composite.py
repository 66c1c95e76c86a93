"""The learned model and the fast layer as one estimator: per-axis coefficients on the model's residual.

The residual the controller flies with is, per axis i,

    R_i(x, u) = a_i (r_i(x, u) - m_i) + k_i m_i + d_i

where r is the learned model's residual, m its slow mean over the ticks just flown (the model's constant part),
a the coefficients adapted here, and d the layer's constant (its observer's offset; vertically the thrust
scale). Who owns what:
- the constant: the layer. Horizontally the model's mean stays in the prediction (k = 1) beside the layer's
  offset: on a circle the mean turns with the vehicle, and handed to the layer (0.5 Hz) it is lost (a model
  that explains the speed force flew 4-12x its own error so). Vertically it is handed to the layer's observer
  (k = 0), which moves it into the thrust scale: the Mellinger layer then carries the model's mass, and the
  MPC, whose input cost is on u - a_ref, no longer needs a standing u to hover. Given to the MPC as a residual
  constant instead, that input cost left an offline model 2.7 cm low at 1.3x mass while the layer, seeing
  nothing left to explain, acted on no axis.
- a constant the layer already holds: at a swap, a new model whose horizontal mean (on the recent ticks) is
  within ``SHARED_CONSTANT`` of the layer's own offset on that axis learned the constant the layer has (a wind):
  the layer keeps it (k = 0 there) and the model flies its variation about that mean, held where the swap took
  it (a moving mean would hand the turning drag to the layer after all). Handed to the model, the constant left
  the layer an offset near 0, where its deadband shrinks what is left: drag + wind on the lab circle flew
  1.02-1.05x the layer alone. A mean the layer did not hold (a network fitted on the take-off) stays the model's.
- k is the same in what the layer's observer is told the model predicts and in what the MPC flies, whether
  or not the layer acts: a constant the MPC flies but the observer never saw is invisible to the layer's
  engagement. Flown while the layer's vertical did not act, a take-off network's 0.02 m/s^2 of vertical mean
  held a lab circle 6 mm low, 3.2x the layer's MSE (ideal plant).
- the thrust's effectiveness: the layer's thrust scale (a mass is one). The model's vertical feature is its
  residual without its slope in the vertical command u_z, and the MPC is not given that slope while the
  layer's vertical acts: a model trained beside the layer (its targets already shaped by the thrust scale)
  had learned a slope of about -0.7 in u_z that made the MPC over-command height, 3x the layer's MSE alone
  with it and 1.2x without it (1.3x mass, ideal plant, seed 0).
- what varies with the state: the model, weighted by a. a_i is an exponentially weighted least-squares fit of
  the layer's filtered residual on [the filtered feature r_i - m_i, 1] (the constant column keeps a constant
  error out of a), with a ridge prior toward 1 of constant strength, bounded. A model whose variation the
  flight confirms keeps a near 1; one whose slopes are wrong here (a drag learned on another trajectory)
  is turned down toward 0, and the layer's offset takes the constant.

Pure functions for the math; ``ModelCoefficients`` holds the state between ticks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cfknode.flight.mpc_problem import ResidualLinearisation

# A swapped-in model's horizontal mean within this share of the layer's offset is the layer's constant. Drag + wind's
# networks brought 0.73-0.76 of the layer's; take-off networks a constant where the layer had none.
SHARED_CONSTANT = 0.5


@dataclass(frozen=True)
class CoefficientSettings:
    """The fit's constants (``controller.adaptation_settings``: ``coefficient_*``, ``model_mean_s``)."""

    bounds: tuple[float, float]  # a_i is kept inside
    memory_s: float  # s, time constant of the fit's exponential forgetting
    prior: float  # m/s^2: a feature varying by this much (RMS) weighs as much as the prior a = 1
    mean_s: float  # s, time constant of the model's mean m


@dataclass(frozen=True)
class AxisFit:
    """One axis's weighted least squares in information form: R = sum w phi phi^T (+ prior), b = sum w phi y."""

    r00: float  # feature . feature
    r01: float  # feature . 1
    r11: float  # 1 . 1
    b0: float  # feature . target
    b1: float  # 1 . target


def prior_fit(prior_info: float, a_prior: float = 1.0) -> AxisFit:
    """The fit before any data: a = ``a_prior`` with information ``prior_info``; the constant almost free."""
    return AxisFit(prior_info, 0.0, 1e-6, prior_info * a_prior, 0.0)


def fit_step(fit: AxisFit, phi: float, y: float, keep: float, prior_info: float, a_prior: float = 1.0) -> AxisFit:
    """One sample (``phi``, ``y``) into the fit, older ones weighted down by ``keep`` (= exp(-dt / memory)).

    The prior's information is topped up by (1 - keep) per tick, so it stays ``prior_info`` however long the
    flight (plain forgetting would let it decay, and with no excitation the fit would wind up)."""
    top = (1.0 - keep) * prior_info
    return AxisFit(keep * fit.r00 + phi * phi + top, keep * fit.r01 + phi, keep * fit.r11 + 1.0,
                   keep * fit.b0 + phi * y + top * a_prior, keep * fit.b1 + y)


def fit_coefficient(fit: AxisFit, bounds: tuple[float, float]) -> float:
    """The fit's coefficient on the feature, bounded (the constant's is the layer's, and not used)."""
    det = fit.r00 * fit.r11 - fit.r01 * fit.r01
    if det <= 0.0:
        return min(max(fit.b0 / fit.r00 if fit.r00 > 0.0 else 1.0, bounds[0]), bounds[1])
    return min(max((fit.r11 * fit.b0 - fit.r01 * fit.b1) / det, bounds[0]), bounds[1])


def composite_prediction(r: np.ndarray, a: np.ndarray, mean: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """What the layer's observer is told the model predicts: a (r - m), plus m horizontally (see the module);
    ``keep`` (default 1, 1, 0) is k per axis (0 on an axis the model does not fly)."""
    x, y, z = r.tolist()
    ax, ay, az = a.tolist()
    mx, my, mz = mean.tolist()
    kx, ky, kz = (1.0, 1.0, 0.0) if keep is None else keep.tolist()
    return np.array([ax * (x - mx) + kx * mx, ay * (y - my) + ky * my, az * (z - mz) + kz * mz])


class ModelCoefficients:
    """The coefficients a, the model's mean m and the per-axis fits; ``tick`` once per layer update."""

    def __init__(self, settings: CoefficientSettings, rate_hz: float,
                 flown: tuple[bool, bool, bool] = (True, True, True)) -> None:
        self.s = settings
        self.dt = 1.0 / rate_hz
        # Axes the model flies on; on the others a = 0, k = 0 for good: the layer alone (the model's stored
        # score there is not above model_min_score, residual_check.flown_axes).
        self.flown = np.array(flown, dtype=bool)
        # Prior information in the fit's units: sum over ~memory/dt samples of prior^2.
        self._prior_info = settings.prior ** 2 / max(1.0 - math.exp(-self.dt / settings.memory_s), 1e-9)
        self.reset()

    def reset(self) -> None:
        """The model as it is: a = 1 (0 where it does not fly); its mean is taken on the first tick flown
        (take-off, landing, a new model) and again on the first tracking tick after the climb."""
        self.a = self.flown.astype(float)
        self._k = np.where(self.flown, [1.0, 1.0, 0.0], 0.0)  # k per axis: 1 horizontally, 0 vertically and unflown
        self.mean = np.zeros(3)
        self._mean_taken = False
        self._steady = False  # a steady tick flown since the take-off or a swap (the first tick's mean is taken again)
        self._phi_f = [0.0, 0.0, 0.0]  # the feature through the observer's own low-pass
        self._fits = [prior_fit(self._prior_info)] * 3
        self._started = False
        self._held = [False, False, False]  # the mean held where a swap took it (a constant the layer keeps)

    def restart(self, r_recent: np.ndarray, flown: tuple[bool, bool, bool] = (True, True, True),
                layer_offset: np.ndarray | None = None) -> None:
        """A new model: a = 1 again, its mean taken where the vehicle just flew (``r_recent`` (n, 3), the new
        model's residual on the layer's recent ticks), so that what it hands the layer is what it predicts
        there and the layer's re-base has little to move; ``flown`` the new model's axes. ``layer_offset``: the
        layer's offset at the swap; on a flown horizontal axis where the new mean is closer to it than
        ``SHARED_CONSTANT`` of it, the layer keeps that constant (k = 0) and the mean is held (see the module;
        a layer with no offset there holds none)."""
        self.flown = np.array(flown, dtype=bool)
        self.reset()
        # A swap's mean is the recent ticks', not one tick's at the floor: it is not taken again (online models
        # swapped in on the climb flew 1.3-1.9x the layer on a 150 ms motor lag when it was).
        self._steady = True
        if r_recent.shape[0]:
            self.mean = np.mean(r_recent, axis=0)
            self._mean_taken = True
        if layer_offset is None:
            return
        for i in range(2):
            d = float(layer_offset[i])
            if self.flown[i] and abs(float(self.mean[i]) - d) < SHARED_CONSTANT * abs(d):
                self._k[i] = 0.0
                self._held[i] = True

    def prediction(self, r: np.ndarray) -> np.ndarray:
        return composite_prediction(r, self.a, self.mean, self._k)

    def predictions(self, r: np.ndarray) -> np.ndarray:
        """``prediction`` for rows (n, 3)."""
        return self.a * (r - self.mean) + self._k * self.mean

    def linearisation(self, model: ResidualLinearisation, offset: np.ndarray,
                      vertical_acts: bool, model_vertical: bool = False) -> ResidualLinearisation:
        """The MPC's residual over the horizon: a (r - m) + k m + offset, from the model's linearisation (value
        and Jacobians scaled per row by a): what the layer's observer is told (``prediction``), plus its estimate
        where it acts.
        ``model_vertical``: the layer measures nothing here (held near the floor, where the model may learn the
        ground effect), so the vertical is the model's alone, whole (a = 1, k = 1), without the layer's held
        offset, which was measured elsewhere and is part of what the model learned."""
        a, keep = self.a, self._k
        if model_vertical and self.flown[2]:
            a, keep, offset = a.copy(), keep.copy(), np.asarray(offset, dtype=float).copy()
            a[2] = keep[2] = 1.0
            offset[2] = 0.0
        c = model.c * a + ((keep - a) * self.mean + offset)
        ju = model.ju * a[:, None]
        if vertical_acts:  # the thrust scale is the thrust's effectiveness: the model's own slope is not flown
            ju[:, 2, 2] = 0.0
        return ResidualLinearisation(c, model.jx * a[:, None], ju)

    @staticmethod
    def features(c: np.ndarray, jx: np.ndarray, ju: np.ndarray, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The features at points (n, 6), (n, 3) from the model's linearisation there: its residual, vertically
        without its slope in the vertical command (the thrust scale's part, see the module)."""
        r = c + np.einsum("nij,nj->ni", jx, x) + np.einsum("nij,nj->ni", ju, u)
        r[:, 2] -= ju[:, 2, 2] * u[:, 2]
        return r

    def tick(self, r: np.ndarray, sigma: np.ndarray, omega: np.ndarray, dt: float, learn: bool,
             steady: bool = True) -> np.ndarray:
        """One tick after the observer's: ``r`` the model's residual for the command flown, ``sigma`` the
        observer's estimate of what ``prediction(r)`` left, ``omega`` its bandwidths [rad/s]. ``learn`` False
        (a step being tracked, a saturated or frozen tick) keeps a and the fits. ``steady`` False: the take-off's
        climb, after which the mean is taken again. Returns the change of the prediction's filtered value, which
        the observer must take into its estimate (so that model + layer predicts the same acceleration before
        and after the coefficients move)."""
        rs = r.tolist()
        # The mean starts where the model is on the first tick, unless a swap took it, and again on the first
        # steady one: on the climb the model's output is also the ground effect and the inflow, and that mean
        # decayed for seconds into the pattern (4 mm low with the plant's own air as the model). Taken on the
        # climb all the same, a model's mass reaches the thrust scale before the pattern.
        first_mean = not self._mean_taken or (steady and not self._steady)
        self._mean_taken = True
        self._steady = self._steady or steady
        k_mean = 1.0 if first_mean else min(1.0, dt / self.s.mean_s)
        if not self._started or first_mean:  # the filtered feature starts where the feature is (0 with the mean)
            self._phi_f = [0.0 if first_mean else rs[i] - float(self.mean[i]) for i in range(3)]
            self._started = True
        keep = math.exp(-dt / self.s.memory_s)
        a_old, m_old = self.a.tolist(), self.mean.tolist()
        a_new, m_new, shift = list(a_old), list(m_old), [0.0, 0.0, 0.0]
        for i in range(3):
            m_new[i] = m_old[i] if self._held[i] else m_old[i] + k_mean * (rs[i] - m_old[i])
            w = min(1.0, float(omega[i]) * dt)
            phi_f = self._phi_f[i] = self._phi_f[i] + w * ((rs[i] - m_new[i]) - self._phi_f[i])
            if learn and self.flown[i]:
                y = float(sigma[i]) + a_old[i] * phi_f  # the filtered residual beyond the layer's constant
                self._fits[i] = fit_step(self._fits[i], phi_f, y, keep, self._prior_info)
                a_new[i] = fit_coefficient(self._fits[i], self.s.bounds)
            # The prediction moves by -(a_new - a_old) phi_f from a, and vertically by -a (m_new - m_old) from the
            # mean handed over (horizontally the mean stays in the prediction: no move).
            shift[i] = (a_old[i] - a_new[i]) * phi_f
            if i == 2:
                shift[i] += a_new[i] * (m_new[i] - m_old[i])
        self.a = np.array(a_new)
        self.mean = np.array(m_new)
        return np.array(shift)


__all__ = ["SHARED_CONSTANT", "AxisFit", "CoefficientSettings", "ModelCoefficients", "composite_prediction",
           "fit_coefficient", "fit_step", "prior_fit"]
