"""Full-state MPC: x = (p, v, q, w) in R^13, u = (T, Mx, My, Mz), with a learned residual kept
out of the CasADi graph.

Model: x' = f_nom(x, u; m) + E r(x, u), where f_nom is the rigid body of
``cfknode.models.quadrotor`` (the mass m is a solver parameter, so an oracle can be told
the true mass), r is a network residual on the derivative rows E selects, and each
interval of ``dt`` is integrated by RK4 with ``substeps`` steps (the paper's
``integrator('rk', number_of_finite_elements=4)``).

Without a residual the problem is an SX graph solved by IPOPT with its exact Hessian.

With a residual, the network never enters the CasADi graph: a three-network queue inside
it costs about 1.4 s per IPOPT solve (docs/solver-timings.md#full-model-mpc), and linearising it at every
RK4 stage point as solver parameters still leaves a 5e6-instruction Hessian.  Instead
the interval defects x_{k+1} - F(x_k, u_k) are a CasADi ``Callback`` computed in numpy:
RK4 of the true hybrid model for all N intervals at once, with forward-mode sensitivities
(the network's Jacobian from one batched product per stage), so IPOPT sees the exact
constraint values and Jacobian at every iterate.  Its Hessian is a limited-memory
(L-BFGS) approximation by default.  The Hessian only steers the steps; IPOPT's
convergence test uses the exact gradients, so a converged answer is the answer of the
problem with the network inside the graph (the tests compare the two plans).

Decision vector: w = [u_0, x_1, u_1, x_2, ..., u_{N-1}, x_N]; x_0 is the parameter x0.
Cost: sum_k (x_{k+1} - xr_k)' Q (x_{k+1} - xr_k) + (u_k - ur_k)' R (u_k - ur_k), with P in
place of Q on the last node.  Bounds: thrust in [T_min, T_max]; optionally the rotor-force
polytope 0 <= mixer^-1 u <= f_max (what four rotors can produce) on every stage.
"""


from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from cfknode.app.bench.paper.hybrid_rk4 import HybridRk4, rigid_body_rhs_jacobian  # noqa: F401  (re-exported)
from cfknode.app.bench.paper.mpc_defects import Defects
from cfknode.app.bench.paper.mpc_full_spec import NU, NX, STAGE, FullMpcSolution, FullMpcSpec, ResidualModel
from cfknode.models.quadrotor import casadi_backend, rigid_body_rhs


@dataclass(frozen=True)
class _Layout:
    horizon: int

    @property
    def slices(self) -> dict[str, slice]:
        n = self.horizon
        sizes = {"x0": NX, "mass": 1, "x_ref": NX * n, "u_ref": NU * n}
        out, start = {}, 0
        for name, size in sizes.items():
            out[name] = slice(start, start + size)
            start += size
        return out

    @property
    def size(self) -> int:
        return (NX + 1) + (NX + NU) * self.horizon


def _cost_and_bounds(spec: FullMpcSpec, w: Any, p: Any, sym: Any) -> tuple[Any, list[Any], np.ndarray, np.ndarray]:
    n = spec.horizon
    sl = _Layout(n).slices
    x_ref = ca.reshape(p[sl["x_ref"]], NX, n)
    u_ref = ca.reshape(p[sl["u_ref"]], NU, n)
    q, rr, pt = (np.asarray(a, dtype=float) for a in (spec.q, spec.r, spec.p))
    unmix = np.linalg.inv(np.asarray(spec.rotor_mixer, dtype=float)) if spec.rotor_mixer is not None else None
    cost = sym(0)
    poly = []
    for k in range(n):
        u_k = w[STAGE * k : STAGE * k + NU]
        ex = w[STAGE * k + NU : STAGE * (k + 1)] - x_ref[:, k]
        eu = u_k - u_ref[:, k]
        cost = cost + ca.dot(ex, (pt if k == n - 1 else q) * ex) + ca.dot(eu, rr * eu)
        if unmix is not None:
            poly.append(ca.mtimes(ca.DM(unmix), u_k))
    lbw = np.full(STAGE * n, -np.inf)
    ubw = np.full(STAGE * n, np.inf)
    lbw[0::STAGE] = spec.thrust_bounds[0]
    ubw[0::STAGE] = spec.thrust_bounds[1]
    return cost, poly, lbw, ubw


def _nominal_nlp(spec: FullMpcSpec) -> dict[str, Any]:
    """The SX problem with the nominal model inside the graph."""
    n, ns = spec.horizon, spec.substeps
    h = spec.dt / ns
    layout = _Layout(n)
    sl = layout.slices
    p = ca.SX.sym("p", layout.size)
    ws = ca.SX.sym("w", STAGE * n)
    w = ws * ca.DM(spec.variable_scale)
    be = casadi_backend()
    x0, mass = p[sl["x0"]], p[sl["mass"]]
    cost, poly, _, _ = _cost_and_bounds(spec, w, p, ca.SX)
    dyn = []
    x = x0
    for k in range(n):
        u_k = w[STAGE * k : STAGE * k + NU]
        x_next = w[STAGE * k + NU : STAGE * (k + 1)]
        y = x
        for _ in range(ns):
            k1 = rigid_body_rhs(y, u_k, mass, spec.inertia, spec.gravity, be)
            k2 = rigid_body_rhs(y + 0.5 * h * k1, u_k, mass, spec.inertia, spec.gravity, be)
            k3 = rigid_body_rhs(y + 0.5 * h * k2, u_k, mass, spec.inertia, spec.gravity, be)
            k4 = rigid_body_rhs(y + h * k3, u_k, mass, spec.inertia, spec.gravity, be)
            y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        dyn.append(x_next - y)
        x = x_next
    return {"x": ws, "p": p, "f": cost, "g": ca.vertcat(*dyn, *poly)}


def _ipopt_options(spec: FullMpcSpec) -> dict[str, Any]:
    return {
        "print_time": False,
        "ipopt": {
            "print_level": 0,
            "sb": "yes",
            "tol": spec.ipopt_tol,
            "warm_start_init_point": "yes",
            "max_iter": spec.ipopt_max_iter,
        },
    }


class FullStateMpc:
    """Build once, ``solve`` every control tick; see the module docstring."""

    def __init__(self, spec: FullMpcSpec) -> None:
        self.spec = spec
        self.horizon = n = spec.horizon
        self.layout = _Layout(n)
        nominal = _nominal_nlp(spec)
        self._scale = spec.variable_scale
        _, _, lbw, ubw = _cost_and_bounds(spec, nominal["x"], nominal["p"], ca.SX)
        self._lbw, self._ubw = lbw / self._scale, ubw / self._scale
        self._dyn: HybridRk4 | None = None
        if spec.residual_rows:
            self._dyn = HybridRk4(spec)
            self._defects = Defects("hybrid_defects", self._dyn)
            ws = ca.MX.sym("w", STAGE * n)
            w = ws * ca.DM(self._scale)
            p = ca.MX.sym("p", self.layout.size)
            sl = self.layout.slices
            cost, poly, _, _ = _cost_and_bounds(spec, w, p, ca.MX)
            g = ca.vertcat(self._defects(w, p[sl["x0"]], p[sl["mass"]]), *poly)
            opts = _ipopt_options(spec)
            if spec.hessian == "nominal":
                # Same variables, parameters and constraint order: the nominal Lagrangian's Hessian.
                helper = ca.nlpsol("full_mpc_nominal_hessian", "ipopt", nominal, _ipopt_options(spec))
                opts["hess_lag"] = helper.get_function("nlp_hess_l")
            else:
                opts["ipopt"]["hessian_approximation"] = "limited-memory"
            self.solver = ca.nlpsol("full_mpc_hybrid", "ipopt", {"x": ws, "p": p, "f": cost, "g": g}, opts)
        else:
            self.solver = ca.nlpsol("full_mpc", "ipopt", nominal, _ipopt_options(spec))
        ng = int(self.solver.size1_out("g"))
        self._lbg = np.zeros(ng)
        self._ubg = np.zeros(ng)
        if spec.rotor_mixer is not None:
            self._ubg[NX * n :] = spec.rotor_force_max
        self._p = np.zeros(self.layout.size)
        views = {k: self._p[s] for k, s in self.layout.slices.items()}
        self._x0 = views["x0"]
        self._mass = views["mass"]
        self._x_ref = views["x_ref"].reshape(n, NX)
        self._u_ref = views["u_ref"].reshape(n, NU)
        nw = STAGE * n
        self._w0 = np.zeros(nw)
        self._lx0 = np.zeros(nw)
        self._lg0 = np.zeros(ng)
        self.failures = 0

    def reset(self) -> None:
        """Forget the warm start (the next solve starts from zeros, as the paper's first call)."""
        self._w0.fill(0.0)
        self._lx0.fill(0.0)
        self._lg0.fill(0.0)

    def solve(
        self,
        x0: np.ndarray,
        x_ref: np.ndarray,
        u_ref: np.ndarray,
        mass: float,
        residual: ResidualModel | None = None,
    ) -> FullMpcSolution:
        """First input for state ``x0``; x_ref (N, 13) targets nodes 1..N, u_ref (N, 4) inputs 0..N-1.

        ``residual`` needs an MPC built with the same ``residual_rows``; None there means
        r = 0.  A problem built without residual rows accepts only None.
        """
        t0 = time.perf_counter()
        n = self.horizon
        if residual is not None:
            if self._dyn is None:
                raise ValueError("this MPC was built without residual rows; build one with residual_rows set")
            if tuple(residual.rows) != self.spec.residual_rows:
                raise ValueError(f"residual acts on rows {tuple(residual.rows)}, the MPC on {self.spec.residual_rows}")
        if self._dyn is not None:
            self._dyn.set_residual(residual)
        np.copyto(self._x0, x0)
        self._mass[0] = mass
        np.copyto(self._x_ref, x_ref)
        np.copyto(self._u_ref, u_ref)
        sol = self.solver(
            x0=self._w0, p=self._p, lbx=self._lbw, ubx=self._ubw, lbg=self._lbg, ubg=self._ubg,
            lam_x0=self._lx0, lam_g0=self._lg0,
        )
        stats = self.solver.stats()
        iterations = int(stats.get("iter_count", 0))
        ws = np.asarray(sol["x"]).ravel()
        w = ws * self._scale
        if not stats.get("success", False) or not np.all(np.isfinite(w)):
            self.failures += 1
            self.reset()
            status = str(stats.get("return_status", "solver_failed"))
            nan_x, nan_u = np.full((n + 1, NX), np.nan), np.full((n, NU), np.nan)
            return FullMpcSolution(np.zeros(NU), False, status, time.perf_counter() - t0, nan_x, nan_u, iterations)
        np.copyto(self._w0, ws)
        np.copyto(self._lx0, np.asarray(sol["lam_x"]).ravel())
        np.copyto(self._lg0, np.asarray(sol["lam_g"]).ravel())
        stages = w.reshape(n, STAGE)
        x_pred = np.empty((n + 1, NX))
        x_pred[0] = x0
        x_pred[1:] = stages[:, NU:]
        u_pred = stages[:, :NU].copy()
        return FullMpcSolution(u_pred[0].copy(), True, "ok", time.perf_counter() - t0, x_pred, u_pred, iterations)


__all__ = [
    "FullMpcSolution",
    "FullMpcSpec",
    "FullStateMpc",
    "HybridRk4",
    "ResidualModel",
    "rigid_body_rhs_jacobian",
]
