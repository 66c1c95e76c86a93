"""The oracle row (controller.adaptation: oracle): the same MPC told the simulator's true mass at every tick."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.flight.controller import Controller
from cfknode.app.logs.writer import read_log
from cfknode.kernel.reference import RefSamples
from cfknode.app.mission import run_flight
from test_adaptation import HOVER

STEP = {"sim.mass_changes": [{"t": 2.5, "factor": 1.3}]}


class _State:
    p = np.array([0.0, 0.0, 1.0])
    v = np.zeros(3)
    q = np.array([1.0, 0.0, 0.0, 0.0])


def test_oracle_thrust_follows_the_true_mass_with_no_offset() -> None:
    cfg = load_config(overrides={"controller.adaptation": "oracle", "controller.codegen": False})
    mass = [cfg.vehicle.mass]
    ctrl = Controller(cfg.controller, cfg.vehicle, true_mass=lambda: mass[0], ground_z=0.0)
    n = cfg.controller.horizon + 1
    hover = RefSamples(t=np.zeros(n), p=np.tile([0.0, 0.0, 1.0], (n, 1)), v=np.zeros((n, 3)), a=np.zeros((n, 3)), yaw=np.zeros(n))
    thrust = []
    for m in (1.0, 1.3):
        mass[0] = m * cfg.vehicle.mass
        thrust.append(ctrl.step(0.0, _State(), hover).setpoint.thrust)
        est = ctrl.adaptation.estimate
        assert est.thrust_scale == pytest.approx(m) and np.all(est.offset == 0.0)
    assert thrust[1] / thrust[0] == pytest.approx(1.3, rel=0.02)  # hover thrust scales with the mass told


def test_oracle_without_a_true_mass_is_refused() -> None:
    cfg = load_config(overrides={"controller.adaptation": "oracle", "controller.codegen": False})
    with pytest.raises(ValueError, match="simulation only"):
        Controller(cfg.controller, cfg.vehicle)


def test_oracle_is_refused_on_hardware_with_a_one_line_error() -> None:
    cfg = load_config(overrides={"backend": "cf", "controller.adaptation": "oracle"})
    with pytest.raises(ConfigError, match="simulation only") as exc:
        run_flight(cfg)
    assert "\n" not in str(exc.value)


def test_oracle_flight_tracks_a_mass_step_better_than_nominal(tmp_path: Any) -> None:
    runs = {}
    for mode in ("none", "oracle"):
        cfg = load_config(overrides={**HOVER, **STEP, "log.dir": str(tmp_path), "controller.adaptation": mode})
        runs[mode] = run_flight(cfg, name_hint=f"oracle-{mode}")
    oracle, nominal = runs["oracle"].summary, runs["none"].summary
    assert runs["oracle"].outcome.message.startswith("flight complete")
    msgs = read_log(oracle.log_path).topic("/adaptation")
    assert max(m["thrust_scale"] for m in msgs) == pytest.approx(1.3) and msgs[0]["thrust_scale"] == pytest.approx(1.0)
    assert oracle.extra["adaptation"] == "oracle"
    assert oracle.mse < nominal.mse
    step = oracle.recovery[0]
    assert step["factor"] == 1.3 and step["peak_error_m"] < nominal.recovery[0]["peak_error_m"]
