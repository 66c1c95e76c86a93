"""cfknode: KNODE-MPC-Online flight stack for Crazyflie 2.x.

The public API, for flying cfknode's controller in any loop (see README "Using the controller
elsewhere"):

- ``Controller`` (``step(t, state, reference) -> Command``), ``Command``, ``TickInfo``;
- settings: ``load_config`` (the packaged defaults plus overrides), ``ControllerConfig``, ``VehicleConfig``;
- the firmware's side: ``read_setpoint`` (RPYT setpoint -> thrust in newtons and attitude),
  ``AttitudeSetpoint``, ``FirmwareTarget``;
- references: ``Circle``, ``make_trajectory``, ``RefSamples``; state: ``StateEstimate``;
- the fast layer: ``AdaptationLayer`` (the Protocol a controller's ``adaptation`` slot has),
  ``AdaptationEstimate`` (its state, on ``Command.layer`` and ``TickInfo.layer``), ``NoAdaptation``;
- models and learning: ``ModelSlot``, ``online_learning`` / ``OnlineLearning`` (``with`` or
  ``start``/``stop``), ``OnlineLearner`` (``stats``: ``OnlineStats``, ``rounds``: ``RoundRecord``,
  ``swaps``: ``SwapEvent``, ``summary_fields()``);
- protocols of what one plugs in: ``Solver``, ``Log`` (``write(topic, t, msg)``), ``TickObserver``.

See docs/api.md.

Names load on first use, so ``import cfknode`` stays cheap for the command line.
"""

from __future__ import annotations

import importlib
from typing import Any

from cfknode.kernel.version import __version__

_EXPORTS = {
    "AdaptationEstimate": "cfknode.flight.adaptation",
    "AdaptationLayer": "cfknode.flight.adaptation",
    "Log": "cfknode.flight.loop",
    "NoAdaptation": "cfknode.flight.adaptation",
    "OnlineLearner": "cfknode.flight.learning.learner",
    "OnlineLearning": "cfknode.app.learning",
    "OnlineStats": "cfknode.flight.learning.records",
    "RoundRecord": "cfknode.flight.learning.records",
    "Solver": "cfknode.flight.controller",
    "SolverStats": "cfknode.flight.solver_stats",
    "SwapEvent": "cfknode.flight.learning.records",
    "TickObserver": "cfknode.flight.controller",
    "AttitudeSetpoint": "cfknode.kernel.setpoint",
    "Circle": "cfknode.flight.trajectory",
    "Command": "cfknode.flight.controller",
    "Controller": "cfknode.flight.controller",
    "ControllerConfig": "cfknode.flight.settings",
    "FirmwareTarget": "cfknode.kernel.setpoint",
    "ModelSlot": "cfknode.flight.model_slot",
    "RefSamples": "cfknode.kernel.reference",
    "StateEstimate": "cfknode.flight.estimator",
    "TickInfo": "cfknode.flight.controller",
    "VehicleConfig": "cfknode.kernel.vehicle",
    "load_config": "cfknode.app.config",
    "make_trajectory": "cfknode.flight.trajectory",
    "online_learning": "cfknode.app.learning",
    "read_setpoint": "cfknode.kernel.setpoint",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'cfknode' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
