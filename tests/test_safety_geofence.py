"""Geofence geometry, the reference clamp and the supervisor's landing reference (pure functions)."""

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.kernel.reference import RefSamples
from cfknode.safety.geofence import Geofence, clamp_reference
from cfknode.safety.landing import Landing
from cfknode.safety.watchdogs import LowPass, Persistence, tilt_deg

FENCE = Geofence(lo=(-1.0, -2.0, -0.2), hi=(1.0, 2.0, 2.0), margin=0.2, stop_distance=0.5)


def test_margin_is_the_signed_distance_to_the_nearest_face():
    assert FENCE.margin_of(0.0, 0.0, 1.0) == (pytest.approx(1.0), 0)
    assert FENCE.margin_of(0.9, 0.0, 1.0) == (pytest.approx(0.1), 0)
    assert FENCE.margin_of(0.0, -2.3, 1.0) == (pytest.approx(-0.3), 1)
    assert FENCE.margin_of(0.0, 0.0, 2.4) == (pytest.approx(-0.4), 2)


def test_excursion_is_zero_inside_and_the_distance_outside():
    p = np.array([[0.0, 0.0, 1.0], [1.3, 0.0, 1.0], [1.3, 2.4, 1.0], [np.nan, 0.0, 0.0]])
    np.testing.assert_allclose(FENCE.excursion(p), [0.0, 0.3, 0.5, 0.0])


def _ref(p: np.ndarray) -> RefSamples:
    n = len(p)
    return RefSamples(t=np.arange(n) * 0.05, p=p, v=np.ones((n, 3)), a=np.ones((n, 3)), yaw=np.zeros(n))


def test_reference_inside_the_soft_box_is_returned_as_is():
    ref = _ref(np.array([[0.0, 0.0, 1.0], [0.7, 1.7, 1.5]]))
    assert clamp_reference(ref, FENCE.soft_lo, FENCE.soft_hi) is ref


def test_reference_outside_is_clamped_and_holds_still_on_the_clamped_axes():
    ref = _ref(np.array([[0.0, 0.0, 1.0], [1.2, 0.0, 1.9], [0.0, -3.0, 0.0]]))
    out = clamp_reference(ref, FENCE.soft_lo, FENCE.soft_hi)
    np.testing.assert_allclose(out.p, [[0.0, 0.0, 1.0], [0.8, 0.0, 1.8], [0.0, -1.8, 0.0]])
    np.testing.assert_allclose(out.v, [[1, 1, 1], [0, 1, 0], [1, 0, 1]])
    np.testing.assert_allclose(out.a, out.v)
    assert out.p[2, 2] == 0.0  # the floor is not inset: landings end on the ground


def test_a_fence_too_small_for_its_margin_is_refused():
    with pytest.raises(ConfigError, match="no room on x"):
        Geofence.from_config(load_config(overrides={"safety.fence_min": [-0.2, -1, -0.2],
                                                    "safety.fence_max": [0.2, 1, 2]}).safety)


def test_landing_goes_straight_down_smoothly_at_the_set_peak_speed():
    landing = Landing.plan(np.array([0.3, -0.2, 1.2]), 0.0, t0=2.0, land_speed=0.5)
    assert landing.duration == pytest.approx(1.875 * 1.2 / 0.5)
    t = np.linspace(1.0, landing.t_end + 1.0, 2001)
    ref = landing.sample(t)
    np.testing.assert_allclose(ref.p[:, :2], np.broadcast_to([0.3, -0.2], (len(t), 2)))
    assert ref.p[0, 2] == pytest.approx(1.2) and ref.p[-1, 2] == pytest.approx(0.0)
    assert np.all(np.diff(ref.p[:, 2]) <= 1e-12)
    assert -ref.v[:, 2].min() == pytest.approx(0.5, rel=1e-3)
    ends = (t <= landing.t0) | (t >= landing.t_end)
    assert np.all(ref.v[ends] == 0.0) and np.allclose(ref.a[ends], 0.0)
    # Velocity is the derivative of position.
    np.testing.assert_allclose(np.gradient(ref.p[:, 2], t), ref.v[:, 2], atol=2e-3)


def test_a_landing_from_the_ground_still_takes_a_moment():
    assert Landing.plan(np.array([0.0, 0.0, 0.01]), 0.0, 0.0, 0.5).duration == 0.5


def test_persistence_low_pass_and_tilt():
    timer = Persistence(0.1)
    assert not timer.update(0.0, True) and not timer.update(0.05, True) and timer.update(0.1, True)
    assert not timer.update(0.11, False) and not timer.update(0.12, True)
    lp = LowPass(0.25)
    assert lp.update(0.0, 4.0) == 4.0
    assert lp.update(0.025, 3.0) == pytest.approx(3.9)
    assert tilt_deg([1.0, 0.0, 0.0, 0.0]) == 0.0
    assert tilt_deg([np.cos(0.5), np.sin(0.5), 0.0, 0.0]) == pytest.approx(np.degrees(1.0))
