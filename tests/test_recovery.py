"""Time to recover from a mass step and the peak error after it (pure), and their place in the flight summary."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfknode.flight.recovery import recovery, step_recoveries
from cfknode.app.ui.summary import TickSeries, compute_summary, summary_from_dict

T = np.arange(0.0, 10.0, 0.01)


def test_an_error_that_decays_recovers_when_it_crosses_the_threshold() -> None:
    err = np.where(T >= 2.0, 0.2 * np.exp(-(T - 2.0)), 0.0)  # 0.2 m at the step, e-folding 1 s
    ttr, peak = recovery(T, err, 2.0, 10.0)
    assert ttr == pytest.approx(math.log(0.2 / 0.03), abs=0.011)
    assert peak == pytest.approx(0.2)


def test_a_dip_under_the_threshold_that_rises_again_is_not_recovery() -> None:
    err = np.full_like(T, 0.01)
    err[(T >= 3.0) & (T < 4.0)] = 0.1
    err[(T >= 4.0) & (T < 5.0)] = 0.02  # dips under ...
    err[(T >= 5.0) & (T < 6.0)] = 0.05  # ... and rises again: recovered only from 6 s
    ttr, peak = recovery(T, err, 3.0, 10.0)
    assert ttr == pytest.approx(3.0, abs=0.011) and peak == pytest.approx(0.1)


def test_never_recovered_is_inf_and_never_left_is_zero() -> None:
    assert recovery(T, np.full_like(T, 0.05), 1.0, 9.0) == (math.inf, pytest.approx(0.05))
    assert recovery(T, np.full_like(T, 0.01), 1.0, 9.0) == (0.0, pytest.approx(0.01))
    ttr, peak = recovery(T, np.full_like(T, 0.01), 20.0, 30.0)  # no samples
    assert ttr == math.inf and math.isnan(peak)


def test_non_finite_errors_count_as_not_recovered() -> None:
    err = np.full_like(T, 0.01)
    err[T > 9.5] = np.nan
    assert recovery(T, err, 1.0, 10.0)[0] == math.inf


def test_each_step_is_judged_until_the_next_one() -> None:
    err = np.full_like(T, 0.01)
    err[(T >= 2.0) & (T < 2.5)] = 0.3
    err[(T >= 5.0)] = 0.08  # the second step never recovers; the first did, before it
    first, second = step_recoveries(T, err, [(5.0, 1.33), (2.0, 0.5)], t_end=9.0)
    assert (first.t_step, first.factor, second.factor) == (2.0, 0.5, 1.33)
    assert first.time_to_recover == pytest.approx(0.5, abs=0.011) and first.peak_error == pytest.approx(0.3)
    assert second.time_to_recover == math.inf and second.peak_error == pytest.approx(0.08)


def test_the_flight_summary_reports_recovery_per_step_and_round_trips() -> None:
    p_ref = np.zeros((len(T), 3))
    p = p_ref.copy()
    p[:, 2] = np.where(T >= 2.0, 0.1 * np.exp(-2.0 * (T - 2.0)), 0.0)
    n = len(T)
    s = compute_summary(TickSeries(T, p, p_ref, np.zeros(n), np.zeros(n), np.zeros(n, bool)), (1.0, 9.0), 1.0,
                        steps=[(2.0, 0.5), (20.0, 1.33)])
    assert len(s.recovery) == 1  # the step after the pattern is not judged
    r = s.recovery[0]
    assert r["factor"] == 0.5 and r["time_to_recover_s"] == pytest.approx(math.log(0.1 / 0.03) / 2, abs=0.011)
    assert r["peak_error_m"] == pytest.approx(0.1)
    late = p.copy()
    late[T > 8.5, 0] = 0.05  # an excursion in the last second of the pattern: outside a 1 s margin only
    kept = compute_summary(TickSeries(T, late, p_ref, np.zeros(n), np.zeros(n), np.zeros(n, bool)), (1.0, 9.0), 1.0,
                           steps=[(2.0, 0.5)], recovery_margin_s=1.0)
    assert kept.recovery[0]["time_to_recover_s"] == pytest.approx(r["time_to_recover_s"])
    back = summary_from_dict(s.to_dict())
    assert back.recovery[0]["time_to_recover_s"] == pytest.approx(r["time_to_recover_s"])
