"""The mass fitted to the mocap frames around a detected step: exact on clean data, silent without a step,
and in the fast layer, known within a few frames of the alarm without ringing."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from cfknode.app.config import load_config
from cfknode.flight.adaptation import FastAdaptation, settings_from_controller
from cfknode.flight.adaptation import StepFit
from cfknode.flight.adaptation.layer import LoopExtras

G = 9.81
RATE = 400.0
FRAME_TICKS = 4  # 100 Hz mocap under a 400 Hz loop


def _fly(theta_at: Callable[[float], float], thrust_at: Callable[[float], float], seconds: float, noise: float,
         seed: int, lags: tuple[float, ...] = (0.0,), true_lag: float = 0.0, flown: int = 0) -> StepFit:
    """A vertical point mass under a known thrust history through a first-order motor lag ``true_lag``; frames of
    its height every 4th tick, with noise. The fit is given the acting thrust under each of ``lags`` and told
    that the layer flew lag ``flown``."""
    rng = np.random.default_rng(seed)
    fit = StepFit(RATE)
    z, v, dt = 1.0, 0.0, 1.0 / RATE

    def alpha(lag: float) -> float:
        return 1.0 - float(np.exp(-dt / lag)) if lag > 0.0 else 1.0

    acting = np.full(len(lags), thrust_at(0.0))
    true_acting = thrust_at(0.0)
    for i in range(int(seconds * RATE)):
        t = i * dt
        fresh = i % FRAME_TICKS == 0
        fit.tick(t, z + (noise * rng.standard_normal() if fresh else 0.0), acting.copy(), -G, 1.0, 0.0, fresh, flown)
        a = theta_at(t) * true_acting - G
        z += dt * v + 0.5 * dt * dt * a
        v += dt * a
        sent = thrust_at(t + dt)
        acting += np.array([alpha(x) for x in lags]) * (sent - acting)
        true_acting += alpha(true_lag) * (sent - true_acting)
    return fit


def test_the_fit_is_exact_on_clean_data() -> None:
    def thrust(t: float) -> float:
        return G * (1.0 if t < 1.02 else 0.6)

    got = _fly(lambda t: 1.0 if t < 1.0 else 1.35, thrust, 1.08, 0.0, seed=0).estimate(1.0, 0.01)
    assert got is not None and got.significant and abs(got.theta - 1.35) < 1e-6


def test_the_fit_tells_a_mass_step_from_none_under_mocap_noise() -> None:
    onset = 1.0

    def thrust(t: float) -> float:  # a controller reacting after the step: the thrust changes under the fit
        return G * (1.0 if t < onset + 0.02 else 0.6 + 0.2 * np.sin(40.0 * t))

    step = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.045, 3e-4, seed=1)  # mass 0.5x
    got = step.estimate(onset, 0.01)
    assert got is not None and got.significant
    assert abs(got.theta - 2.0) < 0.15  # within 8 % after four frames
    quiet = _fly(lambda t: 1.0, thrust, onset + 0.045, 3e-4, seed=1)
    got = quiet.estimate(onset, 0.01)
    assert got is not None and not got.significant and got.theta == 1.0  # no change the frames can tell


def test_the_fit_tells_the_motor_lag_the_layer_flew_wrong() -> None:
    """A 150 ms motor flown as a 15 ms one: the first frames cannot tell the lags apart and keep the flown
    one; a few tenths of a second of the controller's thrust changes pick the right lag and the right mass,
    where the flown lag's fit would be off by half."""
    onset, lags = 1.0, (0.015, 0.04, 0.08, 0.15)

    def thrust(t: float) -> float:  # the controller cuts the thrust after a 0.5x step, then settles
        return G * (1.0 if t < onset + 0.03 else 0.5 + 0.25 * np.exp(-(t - onset - 0.03) / 0.05))

    early = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.035, 3e-4, 2, lags, 0.15, 0).estimate(onset, 0.01)
    assert early is not None and early.lag == 0
    late = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.2, 3e-4, 2, lags, 0.15, 0).estimate(onset, 0.01)
    assert late is not None and late.significant and late.lag == 3
    assert abs(late.theta - 2.0) < 0.05
    flown_only = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.2, 3e-4, 2, (0.015,), 0.15, 0)
    wrong = flown_only.estimate(onset, 0.01)
    assert wrong is not None and abs(wrong.theta - 2.0) > 2.0 * abs(late.theta - 2.0)


def test_a_plant_flown_with_its_own_lag_keeps_it() -> None:
    onset, lags = 1.0, (0.015, 0.04, 0.08, 0.15)

    def thrust(t: float) -> float:
        return G * (1.0 if t < onset + 0.03 else 0.5 + 0.25 * np.exp(-(t - onset - 0.03) / 0.05))

    for seed in range(4):
        fit = _fly(lambda t: 1.0 if t < onset else 2.0, thrust, onset + 0.3, 3e-4, seed, lags, 0.015, 0)
        got = fit.estimate(onset, 0.01)
        assert got is not None and got.lag == 0 and abs(got.theta - 2.0) < 0.05, seed


def layer(**kw: Any) -> FastAdaptation:
    cfg = load_config(overrides={"controller.adaptation": "dob"})
    return FastAdaptation(dataclasses.replace(settings_from_controller(cfg.controller), **kw), RATE)


def hover(lay: FastAdaptation, seconds: float, theta_at: Callable[[float], float], noise: float,
          seed: int, imu_noise: float | None = None, glitch: tuple[float, float, float] | None = None) -> dict[str, Any]:
    """The layer holding a vertical point mass at 1 m (a PD on the frames, thrust from the estimated mass);
    the layer sees mocap heights at 100 Hz with ``noise`` m and a velocity differenced from them, and with
    ``imu_noise`` (m/s^2) an accelerometer at 100 Hz between the frames; ``glitch`` (start, end, dz): the
    frames read dz off in that span (a mocap glitch the accelerometer does not feel)."""
    rng = np.random.default_rng(seed)
    imu_rng = np.random.default_rng(seed + 1000)
    dt = 1.0 / RATE
    z, v = 1.0, 0.0
    seen_z, seen_v, last_z = 1.0, 0.0, 1.0
    alarms, scales, heights = [], [], []
    for i in range(int(seconds * RATE)):
        t = (i + 1) * dt
        e = lay.estimate
        u = float(np.clip(-25.0 * (seen_z - 1.0) - 10.0 * seen_v - e.offset[2], -8.0, 8.0))
        a = (e.thrust_scale / theta_at(t)) * (u + G) - G  # thrust s m (u + g) on the true mass
        z += dt * v + 0.5 * dt * dt * a
        v += dt * a
        fresh = i % FRAME_TICKS == 0
        if fresh:
            measured = z + noise * rng.standard_normal()
            if glitch is not None and glitch[0] <= t < glitch[1]:
                measured += glitch[2]
            seen_v = 0.5 * seen_v + 0.5 * (measured - last_z) / (FRAME_TICKS * dt)
            seen_z = last_z = measured
        else:
            seen_z += dt * seen_v
        before = lay.steps
        cmd = np.array([0.0, 0.0, u])
        imu = None
        if imu_noise is not None and i % FRAME_TICKS == 2:  # specific force over the thrust per nominal mass
            thrust = e.thrust_scale * (u + G)
            imu = (t, (a + G + imu_noise * imu_rng.standard_normal()) / thrust)
        lay.update(t, np.array([0.0, 0.0, seen_v]), np.array([0.0, 0.0, seen_z, 0.0, 0.0, seen_v]), cmd, cmd,
                   (False, False), fresh, LoopExtras(imu_theta=imu))
        if lay.steps > before:
            alarms.append(t)
        scales.append(lay.estimate.thrust_scale)
        heights.append(z)
    return {"alarms": alarms, "scale": np.array(scales), "z": np.array(heights)}


def test_the_layer_knows_the_mass_within_frames_of_a_step_and_does_not_ring() -> None:
    step_t = 3.0
    res = hover(layer(), 4.0, lambda t: 1.0 if t < step_t else 0.5, 3e-4, seed=4)
    assert len(res["alarms"]) == 1 and step_t < res["alarms"][0] < step_t + 0.05
    after = res["scale"][int((res["alarms"][0] + 0.03) * RATE):int((step_t + 0.6) * RATE)]
    assert np.all(np.abs(after - 0.5) < 0.06)  # from 30 ms after the alarm on, within 12 %: no ringing
    assert res["alarms"][0] - step_t < 0.05 and float(np.max(res["z"])) - 1.0 < 0.04


def test_a_false_alarm_on_mocap_noise_leaves_the_mass_alone() -> None:
    for noise in (3e-4, 2e-3):  # Vicon-like and a poor mocap
        res = hover(layer(), 20.0, lambda t: 1.0, noise, seed=1)
        assert len(res["alarms"]) <= 2, noise  # the flown threshold fires now and then on noise ...
        assert float(np.max(np.abs(res["scale"] - 1.0))) < 0.01, noise  # ... and the fit then keeps the mass
        assert float(np.max(np.abs(res["z"] - 1.0))) < 0.005, noise


def test_the_accelerometer_sees_a_step_a_sample_after_it_and_the_frames_confirm_it() -> None:
    step_t = 3.0
    frames_only = hover(layer(), 3.6, lambda t: 1.0 if t < step_t else 0.5, 3e-4, seed=4)
    lay = layer()
    with_imu = hover(lay, 3.6, lambda t: 1.0 if t < step_t else 0.5, 3e-4, seed=4, imu_noise=0.3)
    assert len(with_imu["alarms"]) == 1 and lay.imu_steps == 1
    assert with_imu["alarms"][0] - step_t < 0.012  # the first sample after the step (frames: 3-4 frames)
    assert frames_only["alarms"][0] - with_imu["alarms"][0] > 0.01
    after = with_imu["scale"][int((with_imu["alarms"][0] + 0.005) * RATE):int((step_t + 0.6) * RATE)]
    assert np.all(np.abs(after - 0.5) < 0.03)  # within 6 % from 5 ms after the alarm, through the frames' fit
    rise = lambda r: float(np.max(r["z"])) - 1.0  # noqa: E731
    assert rise(with_imu) < 0.6 * rise(frames_only)


def test_accelerometer_noise_and_offset_raise_no_alarm() -> None:
    for imu_noise in (0.1, 0.5):
        lay = layer()
        res = hover(lay, 20.0, lambda t: 1.02, 3e-4, seed=2, imu_noise=imu_noise)  # 2 % heavier than believed
        assert lay.imu_steps == 0, imu_noise
        assert float(np.max(np.abs(res["z"] - 1.0))) < 0.005


def test_the_step_estimate_from_samples_takes_their_usual_offset_off() -> None:
    from cfknode.flight.adaptation import ImuStepDetector

    rng = np.random.default_rng(0)
    det = ImuStepDetector()
    theta_layer, offset = 1.0, 0.04  # the accelerometer reads 4 % high
    onset = None
    for i in range(300):
        t = 0.01 * i
        true = 1.0 if t < 2.0 else 0.75
        got = det.sample(t, true + offset + 0.02 * rng.standard_normal(), theta_layer, onset is not None)
        onset = onset if got is None else got
    assert onset is not None and 1.99 <= onset <= 2.01
    assert abs(det.theta() - 0.75) < 0.02


def test_the_detector_tells_ahead_which_sample_raises_an_alarm_and_changes_nothing_by_it() -> None:
    """``would_alarm`` is what the controller asks before the solve: it must agree with ``sample`` on every
    sample (one far out, two beyond on one side, noise, the warm-up), and leave the detector as it was."""
    from cfknode.flight.adaptation import ImuStepDetector

    rng = np.random.default_rng(1)
    det = ImuStepDetector()
    thetas = 1.0 + 0.01 * rng.standard_normal(400)
    thetas[150] = 0.7  # one far out: an alarm on its own
    thetas[250:252] = 1.08  # two at 8 standard deviations on one side: the second raises it
    thetas[320] = 1.08  # one at 8 alone, then back: pending, no alarm
    said, raised = [], []
    for i, theta in enumerate(thetas):
        before = (det._n, det._bias, det._var, det._pending, det.alarms)
        said.append(det.would_alarm(float(theta), 1.0))
        assert (det._n, det._bias, det._var, det._pending, det.alarms) == before
        raised.append(det.sample(0.01 * i, float(theta), 1.0, False) is not None)
    assert said == raised
    assert [i for i, r in enumerate(raised) if r] == [150, 251]
    assert not det.would_alarm(float("nan"), 1.0) and not ImuStepDetector().would_alarm(0.5, 1.0)  # warm-up


def test_the_accelerometer_vetoes_a_glitch_and_sees_a_step_inside_the_frames_hold() -> None:
    """A mocap glitch raises the frames' alarm; the accelerometer feels nothing, so no step is fitted. And a
    real step 70 ms later, inside that alarm's hold, is seen by the accelerometer with its own onset (the
    fit searched for it at the glitch's)."""
    glitch = (2.93, 2.95, 0.004)
    lay = layer()
    quiet = hover(lay, 3.6, lambda t: 1.0, 3e-4, seed=4, imu_noise=0.3, glitch=glitch)
    assert quiet["alarms"] and quiet["alarms"][0] < 2.97 and lay.imu_steps == 0  # the frames' alarm only
    assert float(np.max(np.abs(quiet["scale"] - 1.0))) < 0.03
    lay = layer()
    step = hover(lay, 3.6, lambda t: 1.0 if t < 3.0 else 0.5, 3e-4, seed=4, imu_noise=0.3, glitch=glitch)
    assert lay.imu_steps == 1
    after = step["scale"][int(3.02 * RATE):int(3.6 * RATE)]
    assert np.all(np.abs(after - 0.5) < 0.03)
