"""The translational MPC's problem: data types, parameter layout, the QP over the horizon, the thrust cone,
the RTI step and the IPOPT reference solver, built with CasADi (the solver object is ``mpc.TranslationalMpc``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import casadi as ca
import numpy as np

from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig
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
class MpcParameters:
    """Everything one solve reads besides the state: the one channel into the MPC's parameter vector
    (``ParameterLayout`` says where each part lives in it)."""

    ref: Any  # the reference on the horizon's nodes (p, v over N+1, a over N): ``RefSamples``
    residual: ResidualLinearisation | None = None  # the model's (and the layer's) linearised residual; None: zero
    thrust_limit: float = math.inf  # m/s^2, specific thrust at the clamp for the estimated mass (the cone); inf: unchanged


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
    """The thrust cone is part of the real-time (rti) problem; the converged ipopt reference keeps the box (the
    Mellinger layer still puts altitude before tilt when a command exceeds the thrust left)."""
    return getattr(ctrl, "adaptation", "none") != "none" and getattr(ctrl, "solver", "rti") == "rti"


def _cone_rows(w: Any, uz_max: Any, h_max: Any, n: int) -> tuple[Any, Any, Any]:
    """The thrust cone as rows of the QP: per stage, the vertical maximum and an octagon inscribed in the
    horizontal room (both parameters, set every tick from the layer's thrust limit)."""
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
    return ca.vertcat(*r), ca.vertcat(*lo), ca.vertcat(*hi)


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
        rows, rows_lower, rows_upper = _cone_rows(w, p[sl["cone_uz"]], p[sl["cone_h"]], n)
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
    """Per-stage cone bounds (written into ``out_uz``, ``out_h``): the vertical max, and the horizontal radius at
    the planned vertical ``uz_plan`` (clipped to what can be flown) within thrust and tilt.

    Horizontal tracking keeps a reserve at the clamp: the thrust may lean ``controller.cone_reserve_deg`` from
    vertical whatever the plan. Without it a plan at the top of the cone got no room the next tick, so it stayed
    at the top with no tilt while the horizontal error grew (a fixed point); the reserve costs the vertical
    1 - cos(reserve) of the thrust (0.4 % at 5 deg)."""
    g = vehicle.gravity
    reserve = f_max * math.sin(math.radians(ctrl.cone_reserve_deg))
    out_uz[:] = math.sqrt(f_max * f_max - reserve * reserve) - g
    lift = np.clip(uz_plan + g, ctrl.min_thrust_fraction * g, f_max)
    np.minimum(math.tan(math.radians(ctrl.max_tilt_deg)) * lift, np.sqrt(np.maximum(f_max * f_max - lift * lift, 0.0)),
               out=out_h)
    # At least the reserve, and a sliver of room: rows with equal bounds are degenerate for the active-set QP.
    np.maximum(out_h, max(reserve, 0.05), out=out_h)


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
