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
time was measured and gained nothing (at 400 Hz a tick is 5 % of an interval; at 20 Hz
the QP time was the same within noise).  Every RTI answer is checked against the QP's
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

With fast adaptation on (``controller.adaptation`` not none) the box becomes the thrust cone the
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import casadi as ca
import numpy as np

from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.flight.mpc_codegen import CompiledFunction, casadi_link_flags, compile_cached
from cfknode.models.quadrotor import casadi_backend, rk4_step, translational_rhs

NX = 6  # (p, v)
NU = 3  # commanded world acceleration
_STAGE = NU + NX  # decision variables per stage: u_k then x_{k+1} (interleaved, banded KKT)
# Accepted optimality residuals (primal, bounds, stationarity, complementarity); a converged
# qrqp/osqp answer is at 1e-11 here, a wrong one at 1e-1 and more.
_KKT_TOL = np.array([1e-6, 1e-6, 1e-4, 1e-4])


class RefLike(Protocol):
    """What the MPC reads from a reference (``RefSamples``): N+1 nodes at now + k dt."""

    @property
    def p(self) -> np.ndarray: ...  # (N+1, 3)

    @property
    def v(self) -> np.ndarray: ...  # (N+1, 3)

    @property
    def a(self) -> np.ndarray: ...  # (N+1, 3); nodes 0..N-1 are used


@dataclass(frozen=True)
class ResidualLinearisation:
    """Per-stage affine residual on v': r_k(x, u) = c[k] + jx[k] @ x + ju[k] @ u, k = 0..N-1.

    It is held over stage k (all four RK4 evaluations of the interval t_k..t_k+1).
    ``c`` is the affine offset, not the residual's value at the linearisation point;
    ``about`` converts from (value, Jacobians, point).  The natural points are the last
    solution's nodes: ``x_pred[:-1]`` and ``u_pred``.
    """

    c: np.ndarray  # (N, 3)
    jx: np.ndarray  # (N, 3, 6)
    ju: np.ndarray  # (N, 3, 3)

    @classmethod
    def zeros(cls, horizon: int) -> ResidualLinearisation:
        return cls(np.zeros((horizon, 3)), np.zeros((horizon, 3, NX)), np.zeros((horizon, 3, NU)))

    @classmethod
    def about(
        cls, value: np.ndarray, jx: np.ndarray, ju: np.ndarray, x_bar: np.ndarray, u_bar: np.ndarray
    ) -> ResidualLinearisation:
        """First-order expansion of a residual r about (x_bar[k], u_bar[k]) with r(x_bar, u_bar) = value."""
        c = value - np.einsum("kij,kj->ki", jx, x_bar) - np.einsum("kij,kj->ki", ju, u_bar)
        return cls(c, jx, ju)


@dataclass(frozen=True)
class AccelerationBounds:
    lower: np.ndarray  # (3,) m/s^2
    upper: np.ndarray  # (3,)


@dataclass(frozen=True)
class MpcSolution:
    """One solve.  When ``ok`` is False, ``acc`` is zero (hover) and the predictions are NaN."""

    acc: np.ndarray  # (3,) commanded world acceleration for now, m/s^2
    ok: bool
    status: str
    solve_time: float  # s, wall time of the whole ``solve`` call (perf_counter)
    x_pred: np.ndarray  # (N+1, 6)
    u_pred: np.ndarray  # (N, 3)


def acceleration_bounds(ctrl: ControllerConfig, vehicle: VehicleConfig) -> AccelerationBounds:
    """The box on the commanded acceleration (see the module docstring for the reasoning)."""
    g = vehicle.gravity
    f = ctrl.max_thrust_fraction
    az_max = f * vehicle.max_thrust / vehicle.mass - g
    if az_max <= 0.0:
        raise ValueError(f"vehicle cannot hover at controller.max_thrust_fraction {f:g}: f T_max/m - g = {az_max:.3f} m/s^2")
    axy = g * math.tan(math.radians(ctrl.max_tilt_deg))
    az_min = -(1.0 - ctrl.min_thrust_fraction) * g
    return AccelerationBounds(np.array([-axy, -axy, az_min]), np.array([axy, axy, az_max]))


@dataclass(frozen=True)
class ParameterLayout:
    """Where each block lives in the flat parameter vector (numpy row-major blocks)."""

    horizon: int
    cone: bool = False  # per-stage thrust-cone bounds (u_z max, horizontal radius) as parameters

    @property
    def sizes(self) -> dict[str, int]:
        n = self.horizon
        # The residual blocks (c, jx, ju) stay last and contiguous: solve zeroes them in one write.
        blocks = {"x0": NX, "ref_p": 3 * (n + 1), "ref_v": 3 * (n + 1), "ref_a": 3 * n}
        if self.cone:
            blocks.update(cone_uz=n, cone_h=n)
        return {**blocks, "c": 3 * n, "jx": 3 * NX * n, "ju": 3 * NU * n}

    @property
    def slices(self) -> dict[str, slice]:
        out, start = {}, 0
        for name, size in self.sizes.items():
            out[name] = slice(start, start + size)
            start += size
        return out

    @property
    def size(self) -> int:
        return sum(self.sizes.values())


@dataclass(frozen=True)
class QpProblem:
    """The MPC as a parametric QP: min 1/2 w'Hw + q(p)'w  s.t.  A(p) w = b(p),  lbw <= w <= ubw."""

    layout: ParameterLayout
    p: Any  # SX parameter vector
    w: Any  # SX decision vector
    cost: Any  # SX scalar
    dynamics: Any  # SX (N*6,) equality residual, zero when satisfied
    hessian: Any  # DM, constant
    gradient: Any  # SX q(p) = gradient of the cost at w = 0
    lbw: np.ndarray
    ubw: np.ndarray
    # Linear inequality rows lower(p) <= rows(w) <= upper(p) (the thrust cone); None without it.
    rows: Any = None
    rows_lower: Any = None
    rows_upper: Any = None


# Octagon directions for the horizontal cone, and the factor that puts it inside the circle.
_OCTAGON = tuple((math.cos(a), math.sin(a)) for a in (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4))
_INSCRIBED = math.cos(math.pi / 8)
_BIG = 1e3  # m/s^2: an inactive bound that stays finite (the KKT check multiplies by it)


def cone_enabled(ctrl: ControllerConfig) -> bool:
    return getattr(ctrl, "adaptation", "none") != "none"


def build_qp_problem(ctrl: ControllerConfig, vehicle: VehicleConfig) -> QpProblem:
    """Symbolic MPC problem; decision vector w = [u_0, x_1, u_1, x_2, ..., u_{N-1}, x_N]."""
    n, h = ctrl.horizon, ctrl.dt
    cone = cone_enabled(ctrl)
    layout = ParameterLayout(n, cone)
    sl = layout.slices
    p = ca.SX.sym("p", layout.size)
    w = ca.SX.sym("w", _STAGE * n)
    be = casadi_backend()

    x0 = p[sl["x0"]]
    # numpy (n, 3) row-major == CasADi (3, n) column-major: column k is node k.
    ref_p = ca.reshape(p[sl["ref_p"]], 3, n + 1)
    ref_v = ca.reshape(p[sl["ref_v"]], 3, n + 1)
    ref_a = ca.reshape(p[sl["ref_a"]], 3, n)
    c = ca.reshape(p[sl["c"]], 3, n)
    jx = p[sl["jx"]]
    ju = p[sl["ju"]]

    qx = np.concatenate((ctrl.q_position, ctrl.q_velocity))
    r = np.asarray(ctrl.r_acceleration, dtype=float)
    weights = np.zeros(_STAGE * n)
    dyn = []
    target = []
    x = x0
    for k in range(n):
        u_k = w[_STAGE * k : _STAGE * k + NU]
        x_next = w[_STAGE * k + NU : _STAGE * (k + 1)]
        # Row-major (3, 6) from a flat block: CasADi reshape is column-major, hence the transpose.
        jx_k = ca.reshape(jx[3 * NX * k : 3 * NX * (k + 1)], NX, 3).T
        ju_k = ca.reshape(ju[3 * NU * k : 3 * NU * (k + 1)], NU, 3).T
        c_k = c[:, k]

        def rhs(xs: Any, us: Any, c_k: Any = c_k, jx_k: Any = jx_k, ju_k: Any = ju_k) -> Any:
            residual = c_k + ca.mtimes(jx_k, xs) + ca.mtimes(ju_k, us)
            return translational_rhs(xs, us, be) + ca.vertcat(ca.SX.zeros(3), residual)

        dyn.append(x_next - rk4_step(rhs, x, u_k, h))
        target += [ref_a[:, k], ref_p[:, k + 1], ref_v[:, k + 1]]
        scale = ctrl.terminal_scale if k == n - 1 else 1.0
        weights[_STAGE * k : _STAGE * (k + 1)] = np.concatenate((r, scale * qx))
        x = x_next

    t = ca.vertcat(*target)
    err = w - t
    cost = ca.dot(err, weights * err)
    bounds = acceleration_bounds(ctrl, vehicle)
    lower, upper = bounds.lower, bounds.upper
    rows = rows_lower = rows_upper = None
    if cone:
        # The cone rows replace the horizontal box and the vertical maximum; the box stays as a loose guard.
        lower = np.array([-_BIG, -_BIG, bounds.lower[2]])
        upper = np.array([_BIG, _BIG, _BIG])
        uz_max, h_max = p[sl["cone_uz"]], p[sl["cone_h"]]
        r, lo, hi = [], [], []
        for k in range(n):
            u_k = w[_STAGE * k : _STAGE * k + NU]
            r.append(u_k[2])
            lo.append(-_BIG)
            hi.append(uz_max[k])
            for cx, cy in _OCTAGON:
                r.append(cx * u_k[0] + cy * u_k[1])
                lo.append(-_INSCRIBED * h_max[k])
                hi.append(_INSCRIBED * h_max[k])
        rows, rows_lower, rows_upper = ca.vertcat(*r), ca.vertcat(*lo), ca.vertcat(*hi)
    lbw = np.tile(np.concatenate((lower, np.full(NX, -np.inf))), n)
    ubw = np.tile(np.concatenate((upper, np.full(NX, np.inf))), n)
    return QpProblem(
        layout=layout,
        p=p,
        w=w,
        cost=cost,
        dynamics=ca.vertcat(*dyn),
        hessian=ca.DM(ca.Sparsity.diag(w.numel()), 2.0 * weights),
        gradient=-2.0 * weights * t,
        lbw=lbw,
        ubw=ubw,
        rows=rows,
        rows_lower=rows_lower,
        rows_upper=rows_upper,
    )


def cone_limits(uz_plan: np.ndarray, f_max: float, ctrl: ControllerConfig, vehicle: VehicleConfig,
                out_uz: np.ndarray, out_h: np.ndarray) -> None:
    """Per-stage cone bounds (written into ``out_uz``, ``out_h``): vertical max f_max - g, and the horizontal
    radius at the planned vertical ``uz_plan`` (clipped to what can be flown) within thrust and tilt."""
    g = vehicle.gravity
    out_uz[:] = f_max - g
    lift = np.clip(uz_plan + g, ctrl.min_thrust_fraction * g, f_max)
    np.minimum(math.tan(math.radians(ctrl.max_tilt_deg)) * lift, np.sqrt(np.maximum(f_max * f_max - lift * lift, 0.0)),
               out=out_h)
    # A sliver of room: rows with equal bounds are degenerate for the active-set QP (the Mellinger layer cuts the rest).
    np.maximum(out_h, 0.05, out=out_h)


def _qp_options(qp_solver: str) -> dict[str, Any]:
    if qp_solver == "qrqp":
        quiet = {"print_iter": False, "print_header": False, "print_info": False}
        return {**quiet, "max_iter": 200, "error_on_fail": True}
    if qp_solver == "osqp":
        # Tight tolerances and polishing: the default 1e-3 is far from the converged answer.
        settings = {"eps_abs": 1e-7, "eps_rel": 1e-7, "max_iter": 4000, "polish": True, "verbose": False}
        return {"osqp": settings, "warm_start_primal": True, "warm_start_dual": True, "error_on_fail": True}
    raise ValueError(f"unknown qp_solver {qp_solver!r}")


def build_rti_step(problem: QpProblem, qp_solver: str, name: str = "cfknode_mpc_rti") -> Any:
    """ONE Function (p, w0, lam_x0, lam_a0) -> (w, lam_x, lam_a, kkt) containing the QP.

    The equality constraints are affine in w, so A = d(dyn)/dw and b = -dyn(w=0) are exact
    and one QP is the exact solution.  ``kkt`` holds the optimality residuals of the answer.
    """
    w, p = problem.w, problem.p
    b_expr = -ca.substitute(problem.dynamics, w, ca.SX.zeros(w.sparsity()))
    if problem.rows is not None:
        a_expr = ca.jacobian(ca.vertcat(problem.dynamics, problem.rows), w)
        lba_expr = ca.vertcat(b_expr, problem.rows_lower)
        uba_expr = ca.vertcat(b_expr, problem.rows_upper)
    else:
        a_expr = ca.jacobian(problem.dynamics, w)
        lba_expr = uba_expr = b_expr
    data = ca.Function(f"{name}_data", [p], [problem.gradient, a_expr, lba_expr, uba_expr])
    structure = {"h": problem.hessian.sparsity(), "a": a_expr.sparsity()}
    qp = ca.conic(f"{name}_qp", qp_solver, structure, _qp_options(qp_solver))

    P = ca.MX.sym("p", p.numel())
    W0 = ca.MX.sym("w0", w.numel())
    LX0 = ca.MX.sym("lam_x0", w.numel())
    LA0 = ca.MX.sym("lam_a0", a_expr.size1())
    q, a, lba, uba = data(P)
    sol = qp(
        h=problem.hessian, g=q, a=a, lba=lba, uba=uba, lbx=problem.lbw, ubx=problem.ubw, x0=W0, lam_x0=LX0, lam_a0=LA0
    )
    if problem.rows is None:
        kkt = _kkt_residuals(problem, q, a, lba, sol["x"], sol["lam_x"], sol["lam_a"])
    else:
        kkt = _kkt_residuals_rows(problem, q, a, lba, uba, sol["x"], sol["lam_x"], sol["lam_a"])
    return ca.Function(
        name,
        [P, W0, LX0, LA0],
        [sol["x"], sol["lam_x"], sol["lam_a"], kkt],
        ["p", "w0", "lam_x0", "lam_a0"],
        ["w", "lam_x", "lam_a", "kkt"],
    )


def _kkt_residuals(problem: QpProblem, q: Any, a: Any, b: Any, w: Any, lam_x: Any, lam_a: Any) -> Any:
    """(primal, bounds, stationarity, complementarity) infinity norms of the QP's optimality conditions.

    Solver-independent proof of the answer: qrqp can report success from a stale warm start
    (about 1 in 4 unrelated problems, measured), so the step checks its own result.
    """
    bounded = np.flatnonzero(np.isfinite(problem.lbw)).tolist()
    free = np.flatnonzero(~np.isfinite(problem.lbw)).tolist()
    lb, ub = problem.lbw[bounded], problem.ubw[bounded]
    wb, lb_lam = w[bounded], lam_x[bounded]
    primal = ca.norm_inf(ca.mtimes(a, w) - b)
    bounds = ca.fmax(ca.mmax(lb - wb), ca.mmax(wb - ub))
    # CasADi sign convention: H w + q + A' lam_a + lam_x = 0, lam_x > 0 at an upper bound.
    stationarity = ca.norm_inf(ca.mtimes(problem.hessian, w) + q + ca.mtimes(a.T, lam_a) + lam_x)
    complementarity = ca.fmax(
        ca.mmax(ca.fmax(lb_lam, 0) * (ub - wb) + ca.fmax(-lb_lam, 0) * (wb - lb)), ca.norm_inf(lam_x[free])
    )
    return ca.vertcat(primal, bounds, stationarity, complementarity)


def _kkt_residuals_rows(problem: QpProblem, q: Any, a: Any, lba: Any, uba: Any, w: Any, lam_x: Any, lam_a: Any) -> Any:
    """``_kkt_residuals`` with inequality rows (the thrust cone): row feasibility and row complementarity added."""
    base = _kkt_residuals(problem, q, a, lba, w, lam_x, lam_a)
    g = ca.mtimes(a, w)
    primal = ca.fmax(ca.mmax(lba - g), ca.mmax(g - uba))
    rows_comp = ca.mmax(ca.fmax(lam_a, 0) * (uba - g) + ca.fmax(-lam_a, 0) * (g - lba))
    return ca.vertcat(primal, base[1], base[2], ca.fmax(base[3], rows_comp))


def build_ipopt_solver(problem: QpProblem, name: str = "cfknode_mpc_ipopt") -> Any:
    """IPOPT on the same problem, quiet and warm-started: the converged reference."""
    opts = {
        "print_time": False,
        "ipopt": {
            "print_level": 0,
            "sb": "yes",
            "tol": 1e-10,
            "warm_start_init_point": "yes",
            "mu_init": 1e-3,
            # The Lagrangian Hessian is the constant cost Hessian (the constraints are affine).
            "hessian_constant": "yes",
            "max_iter": 200,
        },
    }
    nlp = {"x": problem.w, "p": problem.p, "f": problem.cost, "g": problem.dynamics}
    return ca.nlpsol(name, "ipopt", nlp, opts)


class TranslationalMpc:
    """The translational MPC; see the module docstring.  Build once, ``solve`` every tick."""

    def __init__(
        self,
        ctrl: ControllerConfig,
        vehicle: VehicleConfig,
        cache_dir: str | Path | None = None,
    ) -> None:
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
            if self.cone:
                raise ValueError("the thrust cone (controller.adaptation) needs controller.solver rti")
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

    def set_thrust_limit(self, f_max: float) -> None:
        """Specific collective thrust at the clamp [m/s^2] for the estimated mass (cone only; a parameter)."""
        if self.cone and math.isfinite(f_max):
            self.f_max = max(f_max, self.vehicle.gravity * 1.01)  # never below hover: the QP must stay feasible

    def reset(self) -> None:
        """Forget the warm start (e.g. after a fallback period or a jump in the reference)."""
        self._w0.fill(0.0)
        self._lx0.fill(0.0)
        self._la0.fill(0.0)

    def solve(self, x0: np.ndarray, ref: RefLike, residual: ResidualLinearisation | None = None) -> MpcSolution:
        """Acceleration command for state ``x0`` = (p, v).  Never raises on bad numbers: ``ok`` says.

        Wrong array shapes are wiring bugs and do raise (``ValueError``).
        """
        t0 = time.perf_counter()
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

    def _failure(self, status: str, t0: float) -> MpcSolution:
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
