"""The benchmark's controllers and learners, in the two formulations, importable from one place.

The formulations (paper vs cfknode) are in formulation.py, the geometric baseline in
geometric_baseline.py, the learners in learners.py. Controllers share one interface: the
runner calls ``before_tick``/``after_tick`` around a control tick and ``observe`` after every
plant step; ``residual`` is the model the MPC uses.
"""

from __future__ import annotations

from typing import Literal

from cfknode.app.bench.paper.formulation import Formulation, model_hover_thrust, mpc_reference
from cfknode.app.bench.paper.geometric_baseline import PAPER_POSITION_GAINS, AttitudeGains, GeometricController
from cfknode.app.bench.paper.learners import LatencyLearner, LockstepLearner, NoLearner, RoundRecord, train_offline

ControllerKind = Literal["mpc", "knode_offline", "geometric", "knode_online", "oracle"]
CONTROLLERS: tuple[ControllerKind, ...] = ("mpc", "knode_offline", "geometric", "knode_online", "oracle")

__all__ = [
    "CONTROLLERS",
    "PAPER_POSITION_GAINS",
    "AttitudeGains",
    "ControllerKind",
    "Formulation",
    "GeometricController",
    "LatencyLearner",
    "LockstepLearner",
    "NoLearner",
    "RoundRecord",
    "model_hover_thrust",
    "mpc_reference",
    "train_offline",
]
