"""Translational MPC: x = (p, v), u = commanded world acceleration, with a per-stage affine residual.

Model: p' = v, v' = u + r_k(x, u), r_k(x, u) = c_k + Jx_k x + Ju_k u, discretised with RK4
over ``ctrl.dt``, horizon ``ctrl.horizon``.  The residual is KNODE's network queue
linearised outside CasADi (batched numpy, elsewhere); its arrays are solver
*parameters*, so a new model is a parameter write, never a rebuild or a recompile.
All zeros is the nominal model.

Because the dynamics are affine in (x, u) for given parameters and the cost is
quadratic, the optimal control problem is a convex QP.  The real-time iteration
(``solver: rti``) therefore solves it exactly with one QP per tick, built once as a
single CasADi Function (parameters, warm start) -> solution, optionally compiled to
C (``codegen``).  ``solver: ipopt`` solves the same problem with IPOPT: the
converged reference.  u is the net acceleration (gravity excluded): u = 0 holds a hover.

Each tick warm-starts from the previous solution as it is.  Shifting it by the elapsed
time was measured and gained nothing (at 400 Hz a tick is a small part of an interval;
docs/solver-timings.md).  Every RTI answer is checked against the QP's
optimality conditions inside the same Function (qrqp can report success at a wrong
point after a stale warm start); a failed check is re-solved once, cold, by the other
QP solver, and only then reported as ``ok=False``.

Input bounds (a box on u, from the vehicle):
- a_z <= f T_max / m - g (f = ``max_thrust_fraction``, default 1): up to the thrust at the
  RPYT clamp. The clamp (60000 of 65535) is the firmware's own headroom for the attitude loop,
  and its mixer caps excess so that attitude wins over thrust (thrust/weight is only ~1.5 at
  the clamp, so every bit of it counts after a payload is added).
- a_z >= -(1 - min_thrust_fraction) g: never command (near) free fall; the motors would
  idle and the attitude loop would lose authority. The default keeps 20 % of hover thrust:
  a lighter vehicle than the model's (mass 0.5x, the paper's scenario) hovers only at a
  command of -g/2, so the bound must leave room below that to descend.
- |a_x|, |a_y| <= g tan(max_tilt): the horizontal acceleration a level-ish hover thrust
  can produce at the tilt limit.  Per axis, so the joint tilt may exceed it at a
  corner; the Mellinger layer, which owns the attitude, clamps the final tilt.

With fast adaptation on (``controller.adaptation`` not none) and the rti solver the box becomes the thrust cone the
vehicle really has, as per-stage linear rows whose bounds are parameters (no rebuild when the
mass estimate moves): u_z <= f_max - g, where f_max is the specific thrust at the clamp for the
estimated mass, and an octagon inscribed in the circle |u_xy| <= h_k, h_k = min(tan(tilt)(g + u_z),
sqrt(f_max^2 - (g + u_z)^2)) taken at the previous solution's u_z. Near the clamp the horizontal
room shrinks to nothing before the vertical does: altitude before tilt.
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.flight.solver_stats import SolverStats
from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.flight.mpc_codegen import CompiledFunction, casadi_link_flags, compile_cached

from cfknode.flight.mpc_problem import (  # noqa: F401 (the MPC's public types live there)
    AccelerationBounds,
    MpcParameters,
    MpcSolution,
    NU,
    NX,
    ParameterLayout,
    QpProblem,
    RefLike,
    ResidualLinearisation,
    _BIG,
    _INSCRIBED,
    _KKT_TOL,
    _OCTAGON,
    _STAGE,
    _kkt_residuals,
    _kkt_residuals_rows,
    _qp_options,
    acceleration_bounds,
    build_ipopt_solver,
    build_qp_problem,
    build_rti_step,
    cone_enabled,
    cone_limits,
)


class TranslationalMpc:
    """The translational MPC; see the module docstring.  Build once, ``solve`` every tick."""

    def __init__(
        self,
        ctrl: ControllerConfig,
        vehicle: VehicleConfig,
        cache_dir: str | Path | None = None,
    ) -> None:
        """``cache_dir``: where compiled code is kept (None: ``ctrl.cache_dir``, else the user's cache)."""
        cache_dir = cache_dir if cache_dir is not None else ctrl.cache_dir
        self.ctrl = ctrl
        self.vehicle = vehicle
        self.horizon = ctrl.horizon
        self.dt = ctrl.dt
        self.bounds = acceleration_bounds(ctrl, vehicle)
        self.problem = build_qp_problem(ctrl, vehicle)
        self.compiled: CompiledFunction | None = None
        n = self.horizon
        self.cone = cone_enabled(ctrl)
        nw, ng = _STAGE * n, (NX + (1 + len(_OCTAGON) if self.cone else 0)) * n

        # Preallocated buffers: solve writes into these in place and never builds a DM.
        self._p = np.zeros(self.problem.layout.size)
        views = {k: self._p[s] for k, s in self.problem.layout.slices.items()}
        self._x0 = views["x0"]
        self._ref_p = views["ref_p"].reshape(n + 1, 3)
        self._ref_v = views["ref_v"].reshape(n + 1, 3)
        self._ref_a = views["ref_a"].reshape(n, 3)
        self._res_c = views["c"].reshape(n, 3)
        self._res_jx = views["jx"].reshape(n, 3, NX)
        self._res_ju = views["ju"].reshape(n, 3, NU)
        self._res_start = self.problem.layout.slices["c"].start  # c, jx, ju are the trailing blocks
        if self.cone:
            self._cone_uz, self._cone_h = views["cone_uz"], views["cone_h"]
            # Specific thrust at the clamp for the nominal mass until the adaptation layer says otherwise.
            self.f_max = ctrl.max_thrust_fraction * vehicle.max_thrust / vehicle.mass
        self._residual_set = False
        self.rescues = 0  # solves whose first answer failed its KKT check and were solved again (see solve)
        self.solves = 0
        self.failures = 0
        self._w0 = np.zeros(nw)
        self._lx0 = np.zeros(nw)
        self._la0 = np.zeros(ng)
        self._w = np.zeros(nw)
        self._lx = np.zeros(nw)
        self._la = np.zeros(ng)
        self._kkt = np.zeros(4)
        self._failed_pred = (np.full((n + 1, NX), np.nan), np.full((n, NU), np.nan))

        if ctrl.solver == "rti":
            self.function = build_rti_step(self.problem, ctrl.qp_solver)
            if ctrl.codegen:
                self.compiled = _try_compile(self.function, ctrl.qp_solver, cache_dir)
                if self.compiled is not None:
                    self.function = self.compiled.function
            self.backend = f"rti-{ctrl.qp_solver}-" + ("codegen" if self.compiled is not None else "vm")
            args, results = (self._p, self._w0, self._lx0, self._la0), (self._w, self._lx, self._la, self._kkt)
            self._buf, self._eval = _bind(self.function, args, results)
            # qrqp can stop at a wrong point after a stale warm start or when many bounds switch at
            # once (the KKT check catches it).  The other QP solver, cold and in the VM, re-solves
            # those rare ticks.
            other = "osqp" if ctrl.qp_solver == "qrqp" else "qrqp"
            self._rescue_buf, self._rescue_eval = _bind(build_rti_step(self.problem, other, "rescue"), args, results)
        elif ctrl.solver == "ipopt":
            self.function = build_ipopt_solver(self.problem)
            self.backend = "ipopt"
            self._lbg = np.zeros(ng)
            self._f = np.zeros(1)
            self._g = np.zeros(ng)
            self._lp = np.zeros(self.problem.layout.size)
            self._lbw = np.ascontiguousarray(self.problem.lbw)
            self._ubw = np.ascontiguousarray(self.problem.ubw)
            # nlpsol inputs: x0 p lbx ubx lbg ubg lam_x0 lam_g0; outputs: x f g lam_x lam_g lam_p.
            args = (self._w0, self._p, self._lbw, self._ubw, self._lbg, self._lbg, self._lx0, self._la0)
            results = (self._w, self._f, self._g, self._lx, self._la, self._lp)
            self._buf, self._eval = _bind(self.function, args, results)
        else:
            raise ValueError(f"unknown solver {ctrl.solver!r}")

    def reset(self) -> None:
        """Forget the warm start (e.g. after a fallback period or a jump in the reference)."""
        self._w0.fill(0.0)
        self._lx0.fill(0.0)
        self._la0.fill(0.0)

    def solve(self, x0: np.ndarray, params: MpcParameters | RefLike,
              residual: ResidualLinearisation | None = None) -> MpcSolution:
        """Acceleration command for state ``x0`` = (p, v).  Never raises on bad numbers: ``ok`` says.

        ``params``: what the solve reads besides the state (``MpcParameters``); a reference alone (with
        ``residual``) is the same with the thrust limit unchanged. Wrong array shapes are wiring bugs and
        do raise (``ValueError``).
        """
        if not isinstance(params, MpcParameters):
            params = MpcParameters(params, residual)
        ref, residual = params.ref, params.residual
        if self.cone and math.isfinite(params.thrust_limit):
            # Never below hover: the QP must stay feasible.
            self.f_max = max(params.thrust_limit, self.vehicle.gravity * 1.01)
        t0 = time.perf_counter()
        self.solves += 1
        n = self.horizon
        np.copyto(self._x0, x0)
        np.copyto(self._ref_p, ref.p)
        np.copyto(self._ref_v, ref.v)
        np.copyto(self._ref_a, ref.a[:n])
        if self.cone:
            cone_limits(self._w0.reshape(n, _STAGE)[:, 2], self.f_max, self.ctrl, self.vehicle, self._cone_uz, self._cone_h)
        if residual is not None:
            np.copyto(self._res_c, residual.c)
            np.copyto(self._res_jx, residual.jx)
            np.copyto(self._res_ju, residual.ju)
            self._residual_set = True
        elif self._residual_set:
            self._p[self._res_start :] = 0.0
            self._residual_set = False
        # One reduction instead of an isfinite array: NaN/inf anywhere (or absurd magnitudes) poisons the sum.
        if not math.isfinite(float(self._p.sum())):
            return self._failure("nonfinite_input", t0)

        status = self._run(self._buf, self._eval)
        if status != "ok" and self.backend != "ipopt":
            self.rescues += 1
            self.reset()
            status = self._run(self._rescue_buf, self._rescue_eval)
        if status != "ok":
            self.reset()
            return self._failure(status, t0)

        np.copyto(self._w0, self._w)
        np.copyto(self._lx0, self._lx)
        np.copyto(self._la0, self._la)
        stages = self._w.reshape(n, _STAGE)
        x_pred = np.empty((n + 1, NX))
        x_pred[0] = self._x0
        x_pred[1:] = stages[:, NU:]
        u_pred = stages[:, :NU].copy()
        return MpcSolution(u_pred[0].copy(), True, "ok", time.perf_counter() - t0, x_pred, u_pred)

    def _run(self, buf: Any, evaluate: Any) -> str:
        """Evaluate a solver Function on the buffers; "ok" only for a verified, finite solution."""
        try:
            evaluate()
            ret = buf.ret()
        except RuntimeError:  # defensive: the buffer API reports failures through ret()
            ret = -1
        if ret != 0:
            return "solver_failed"
        if self.backend == "ipopt":
            stats = buf.stats()
            if not stats.get("success", False):
                return str(stats.get("return_status", "solver_failed"))
        elif not (self._kkt <= _KKT_TOL).all():  # NaN compares False: caught here too
            return "not_converged"
        if not math.isfinite(float(self._w.sum())):
            return "nonfinite_solution"
        return "ok"

    def stats(self) -> SolverStats:
        """Solves, failures and rescues since the MPC was built (the ``Solver`` protocol)."""
        return SolverStats(self.solves, self.failures, self.rescues)

    def _failure(self, status: str, t0: float) -> MpcSolution:
        self.failures += 1
        x_pred, u_pred = self._failed_pred
        return MpcSolution(np.zeros(NU), False, status, time.perf_counter() - t0, x_pred.copy(), u_pred.copy())


def _bind(function: Any, args: tuple[np.ndarray, ...], results: tuple[np.ndarray, ...]) -> tuple[Any, Any]:
    """Bind numpy arrays to a Function's inputs/outputs once: each call is then one C call, no DM."""
    buf, evaluate = function.buffer()
    for i, arr in enumerate(args):
        buf.set_arg(i, memoryview(arr))
    for i, arr in enumerate(results):
        buf.set_res(i, memoryview(arr))
    return buf, evaluate


_warned_compile = False


def _try_compile(function: Any, qp_solver: str, cache_dir: str | Path | None) -> CompiledFunction | None:
    """Compiled step, or None (warned once per process) when code generation or gcc fails."""
    global _warned_compile  # warn-once flag: the only module state, for the warning only
    includes, libs = casadi_link_flags((qp_solver,))
    try:
        return compile_cached(function, Path(cache_dir) if cache_dir is not None else None, includes, libs)
    except (RuntimeError, OSError) as exc:
        if not _warned_compile:
            warnings.warn(f"MPC code generation failed, using the CasADi VM: {exc}", RuntimeWarning, stacklevel=3)
            _warned_compile = True
        return None
