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

import math
import time
from dataclasses import dataclass
from typing import Any, Protocol

import casadi as ca
import numpy as np

from cfknode.models.quadrotor import NUMPY, casadi_backend, rigid_body_rhs

NX = 13
NU = 4
NZ = NX + NU  # residual input z = (x, u)
_STAGE = NU + NX
_RK_A = (0.5, 0.5, 1.0)  # RK4: stage j + 1 evaluates at y + _RK_A[j] h k_j
_RK_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)


class ResidualModel(Protocol):
    """A residual on some derivative rows, evaluated with its Jacobian in numpy (no torch)."""

    @property
    def rows(self) -> tuple[int, ...]: ...  # indices into the 13 derivative rows

    def value(self, z: np.ndarray) -> np.ndarray:
        """z (n, 17) = (x, u) -> r (n, len(rows))."""
        ...

    def value_and_jacobian(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (n, 17) -> r (n, len(rows)), dr/dz (n, len(rows), 17)."""
        ...


@dataclass(frozen=True)
class FullMpcSpec:
    """The full-state MPC problem.  Weights are diagonals in SI units of (x - x_ref), (u - u_ref)."""

    horizon: int = 20
    dt: float = 0.05
    substeps: int = 4
    inertia: tuple[float, float, float] = (1.43e-5, 1.43e-5, 2.89e-5)
    gravity: float = 9.81
    q: tuple[float, ...] = (1.0,) * NX
    r: tuple[float, ...] = (1.0,) * NU
    p: tuple[float, ...] = (1.0,) * NX  # terminal node
    thrust_bounds: tuple[float, float] = (0.0, 0.575)
    # 4x4 (T, M) = mixer @ rotor forces; when set, every stage keeps 0 <= forces <= rotor_force_max.
    rotor_mixer: tuple[tuple[float, ...], ...] | None = None
    rotor_force_max: float = math.inf
    residual_rows: tuple[int, ...] = ()  # () builds the nominal problem (exact Hessian, SX)
    ipopt_tol: float = 1e-8  # IPOPT's default, as in the paper
    ipopt_max_iter: int = 500
    # With a residual: "limited-memory" (L-BFGS) or "nominal" (exact Hessian of the residual-free
    # Lagrangian; measured to need about twice the iterations of L-BFGS on the paper's networks).
    hessian: str = "limited-memory"
    # IPOPT's variables are u / input_scale: with weights that span 1e-1..1e6 (moments in N m)
    # an unscaled problem took L-BFGS hundreds of iterations.
    input_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        for name, n in (("q", NX), ("r", NU), ("p", NX)):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} needs {n} weights, got {len(getattr(self, name))}")
        if any(not 0 <= r < NX for r in self.residual_rows) or len(set(self.residual_rows)) != len(self.residual_rows):
            raise ValueError(f"residual_rows must be distinct indices in 0..12, got {self.residual_rows}")
        if len(self.input_scale) != NU or min(self.input_scale) <= 0:
            raise ValueError(f"input_scale needs {NU} positive values, got {self.input_scale}")
        if self.hessian not in ("limited-memory", "nominal"):
            raise ValueError(f"hessian must be 'limited-memory' or 'nominal', got {self.hessian!r}")

    @property
    def variable_scale(self) -> np.ndarray:
        """w = variable_scale * (IPOPT's variables), stage by stage."""
        return np.tile(np.concatenate((np.asarray(self.input_scale, dtype=float), np.ones(NX))), self.horizon)


@dataclass(frozen=True)
class FullMpcSolution:
    """One solve.  When ``ok`` is False, ``u`` is zero and the predictions are NaN."""

    u: np.ndarray  # (4,) first input (T, Mx, My, Mz)
    ok: bool
    status: str
    solve_time: float  # s, wall time of the whole ``solve`` call
    x_pred: np.ndarray  # (N+1, 13)
    u_pred: np.ndarray  # (N, 4)
    iterations: int  # IPOPT iterations


# --- numpy rigid body and RK4 with sensitivities -------------------------------------------


def rigid_body_rhs_jacobian(
    x: np.ndarray, u: np.ndarray, mass: float, inertia: tuple[float, float, float], gravity: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched f_nom, df/d(x, u) and df/dm for x (n, 13), u (n, 4): (n, 13), (n, 13, 17), (n, 13).

    The same equations as ``rigid_body_rhs``, differentiated by hand (checked against CasADi
    in the tests): one pass of array arithmetic instead of a CasADi call per RK4 stage.
    """
    n = x.shape[0]
    vx, vy, vz = x[:, 3], x[:, 4], x[:, 5]
    qw, qx, qy, qz = x[:, 6], x[:, 7], x[:, 8], x[:, 9]
    wx, wy, wz = x[:, 10], x[:, 11], x[:, 12]
    thrust = u[:, 0]
    jx, jy, jz = inertia
    s = thrust / mass
    bx = 2.0 * (qx * qz + qw * qy)
    by = 2.0 * (qy * qz - qw * qx)
    bz = 1.0 - 2.0 * (qx * qx + qy * qy)
    f = np.empty((n, NX))
    f[:, 0], f[:, 1], f[:, 2] = vx, vy, vz
    f[:, 3], f[:, 4], f[:, 5] = s * bx, s * by, s * bz - gravity
    f[:, 6] = -0.5 * (qx * wx + qy * wy + qz * wz)
    f[:, 7] = 0.5 * (qw * wx + qy * wz - qz * wy)
    f[:, 8] = 0.5 * (qw * wy + qz * wx - qx * wz)
    f[:, 9] = 0.5 * (qw * wz + qx * wy - qy * wx)
    f[:, 10] = (u[:, 1] - (jz - jy) * wy * wz) / jx
    f[:, 11] = (u[:, 2] - (jx - jz) * wz * wx) / jy
    f[:, 12] = (u[:, 3] - (jy - jx) * wx * wy) / jz

    jac = np.zeros((n, NX, NZ))
    jac[:, 0, 3] = jac[:, 1, 4] = jac[:, 2, 5] = 1.0
    s2 = 2.0 * s
    # v' = s b(q): rows 3..5, columns q (6..9) and T (13)
    jac[:, 3, 6], jac[:, 3, 7], jac[:, 3, 8], jac[:, 3, 9] = s2 * qy, s2 * qz, s2 * qw, s2 * qx
    jac[:, 4, 6], jac[:, 4, 7], jac[:, 4, 8], jac[:, 4, 9] = -s2 * qx, -s2 * qw, s2 * qz, s2 * qy
    jac[:, 5, 7], jac[:, 5, 8] = -2.0 * s2 * qx, -2.0 * s2 * qy
    jac[:, 3, 13], jac[:, 4, 13], jac[:, 5, 13] = bx / mass, by / mass, bz / mass
    # q' = q (x) (0, w) / 2: rows 6..9, columns q and w (10..12)
    h = 0.5
    jac[:, 6, 7], jac[:, 6, 8], jac[:, 6, 9] = -h * wx, -h * wy, -h * wz
    jac[:, 6, 10], jac[:, 6, 11], jac[:, 6, 12] = -h * qx, -h * qy, -h * qz
    jac[:, 7, 6], jac[:, 7, 8], jac[:, 7, 9] = h * wx, h * wz, -h * wy
    jac[:, 7, 10], jac[:, 7, 11], jac[:, 7, 12] = h * qw, -h * qz, h * qy
    jac[:, 8, 6], jac[:, 8, 7], jac[:, 8, 9] = h * wy, -h * wz, h * wx
    jac[:, 8, 10], jac[:, 8, 11], jac[:, 8, 12] = h * qz, h * qw, -h * qx
    jac[:, 9, 6], jac[:, 9, 7], jac[:, 9, 8] = h * wz, h * wy, -h * wx
    jac[:, 9, 10], jac[:, 9, 11], jac[:, 9, 12] = -h * qy, h * qx, h * qw
    # Euler's equations: rows 10..12, columns w and M (14..16)
    jac[:, 10, 11], jac[:, 10, 12] = -(jz - jy) * wz / jx, -(jz - jy) * wy / jx
    jac[:, 11, 10], jac[:, 11, 12] = -(jx - jz) * wz / jy, -(jx - jz) * wx / jy
    jac[:, 12, 10], jac[:, 12, 11] = -(jy - jx) * wy / jz, -(jy - jx) * wx / jz
    jac[:, 10, 14], jac[:, 11, 15], jac[:, 12, 16] = 1.0 / jx, 1.0 / jy, 1.0 / jz

    dm = np.zeros((n, NX))
    dm[:, 3:6] = -f[:, 3:6] / mass
    dm[:, 5] -= gravity / mass
    return f, jac, dm


class HybridRk4:
    """RK4 of x' = f_nom + E r over every interval of a plan at once, with sensitivities.

    ``run(w, x0, mass, jacobian)`` returns the defects x_{k+1} - F(x_k, u_k) (N, 13) and, on
    request, dF/d(x_k, u_k, m) (N, 13, 18).  The last result is cached: IPOPT asks for the
    Jacobian of the same point through several CasADi entry points.
    """

    def __init__(self, spec: FullMpcSpec) -> None:
        self.spec = spec
        self.residual: ResidualModel | None = None
        self._rows = list(spec.residual_rows)
        self._key: tuple[bytes, bool] | None = None
        self._out: tuple[np.ndarray, np.ndarray | None] = (np.zeros(0), None)

    def set_residual(self, residual: ResidualModel | None) -> None:
        self.residual = residual
        self._key = None

    def run(self, w: np.ndarray, x0: np.ndarray, mass: float, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        key = (w.tobytes() + x0.tobytes() + np.float64(mass).tobytes(), jacobian)
        if self._key is not None and (self._key == key or (self._key[0] == key[0] and self._key[1])):
            return self._out
        self._out = self._integrate(w, x0, mass, jacobian)
        self._key = key
        return self._out

    def _integrate(self, w: np.ndarray, x0: np.ndarray, mass: float, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        spec = self.spec
        n, h = spec.horizon, spec.dt / spec.substeps
        stages = w.reshape(n, _STAGE)
        u = stages[:, :NU]
        x_next = stages[:, NU:]
        y = np.concatenate((x0[None, :], x_next[:-1]), axis=0)
        sens = None
        if jacobian:
            sens = np.zeros((n, NX, NZ + 1))
            sens[:, :, :NX] = np.eye(NX)
        res, rows = self.residual, self._rows
        for _ in range(spec.substeps):
            k_sum = np.zeros((n, NX))
            dk_sum = np.zeros((n, NX, NZ + 1)) if jacobian else None
            k_prev = dk_prev = None
            for j in range(4):
                yj = y if j == 0 else y + (_RK_A[j - 1] * h) * k_prev
                if jacobian:
                    f, jac, dm = rigid_body_rhs_jacobian(yj, u, mass, spec.inertia, spec.gravity)
                    if res is not None:
                        r, dr = res.value_and_jacobian(np.concatenate((yj, u), axis=1))
                        f[:, rows] += r
                        jac[:, rows, :] += dr
                    sj = sens if j == 0 else sens + (_RK_A[j - 1] * h) * dk_prev
                    dk = np.matmul(jac[:, :, :NX], sj)
                    dk[:, :, NX:NZ] += jac[:, :, NX:]
                    dk[:, :, NZ] += dm
                    dk_sum += _RK_B[j] * dk
                    dk_prev = dk
                else:
                    f = rigid_body_rhs(yj, u, mass, spec.inertia, spec.gravity, NUMPY)
                    if res is not None:
                        f[:, rows] += res.value(np.concatenate((yj, u), axis=1))
                k_sum += _RK_B[j] * f
                k_prev = f
            y = y + h * k_sum
            if jacobian:
                sens = sens + h * dk_sum
        return x_next - y, sens


# --- CasADi glue --------------------------------------------------------------------------


def _defect_jacobian_pattern(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of d(defects)/dw in the order ``_DefectsJacobian`` fills the values."""
    rows, cols = [], []
    for k in range(n):
        base_r = NX * k
        for r in range(NX):  # + I on x_{k+1}
            rows.append(base_r + r)
            cols.append(_STAGE * k + NU + r)
        for r in range(NX):  # - dF/du_k
            for c in range(NU):
                rows.append(base_r + r)
                cols.append(_STAGE * k + c)
        if k > 0:  # - dF/dx_k (x_0 is a parameter)
            for r in range(NX):
                for c in range(NX):
                    rows.append(base_r + r)
                    cols.append(_STAGE * (k - 1) + NU + c)
    return np.asarray(rows), np.asarray(cols)


@dataclass(frozen=True)
class _JacobianPattern:
    """Sparsity of d(defects)/d(w, x0, mass) and the permutations from our fill order to CasADi's."""

    w: Any
    perm_w: np.ndarray
    x0: Any
    perm_x0: np.ndarray
    mass: Any

    @classmethod
    def build(cls, n: int) -> _JacobianPattern:
        rows, cols = _defect_jacobian_pattern(n)
        r0, c0 = np.divmod(np.arange(NX * NX), NX)
        return cls(
            w=ca.Sparsity.triplet(NX * n, _STAGE * n, rows.tolist(), cols.tolist()),
            perm_w=np.lexsort((rows, cols)),  # CasADi stores nonzeros column by column
            x0=ca.Sparsity.triplet(NX * n, NX, r0.tolist(), c0.tolist()),
            perm_x0=np.lexsort((r0, c0)),
            mass=ca.Sparsity.dense(NX * n, 1),
        )


class _DefectsJacobian(ca.Callback):
    """Jacobian of ``_Defects``: inputs (w, x0, mass, defects) -> blocks w.r.t. w, x0, mass."""

    def __init__(self, name: str, dyn: HybridRk4, pattern: _JacobianPattern) -> None:
        ca.Callback.__init__(self)
        self.dyn = dyn
        self.pattern = pattern
        n = dyn.spec.horizon
        self.nw, self.nd = _STAGE * n, NX * n
        self.construct(name, {})

    def get_n_in(self) -> int:
        return 4

    def get_n_out(self) -> int:
        return 3

    def get_sparsity_in(self, i: int) -> Any:
        return ca.Sparsity.dense((self.nw, NX, 1, self.nd)[i], 1)

    def get_sparsity_out(self, i: int) -> Any:
        return (self.pattern.w, self.pattern.x0, self.pattern.mass)[i]

    def eval(self, args: list[Any]) -> list[Any]:
        w = np.asarray(args[0]).ravel()
        x0 = np.asarray(args[1]).ravel()
        _, sens = self.dyn.run(w, x0, float(args[2]), True)
        assert sens is not None
        n = self.dyn.spec.horizon
        parts = []
        for k in range(n):
            parts.append(np.ones(NX))
            parts.append(-sens[k, :, NX:NZ].ravel())
            if k > 0:
                parts.append(-sens[k, :, :NX].ravel())
        pat = self.pattern
        return [
            ca.DM(pat.w, np.concatenate(parts)[pat.perm_w]),
            ca.DM(pat.x0, (-sens[0, :, :NX]).ravel()[pat.perm_x0]),
            ca.DM(-sens[:, :, NZ].ravel()),
        ]


class _Defects(ca.Callback):
    """(w, x0, mass) -> x_{k+1} - F(x_k, u_k) for k = 0..N-1, computed by ``HybridRk4``.

    It declares its Jacobian's sparsity: without it CasADi assumes a dense Jacobian, and the
    KKT factorisation was measured 20x slower.
    """

    def __init__(self, name: str, dyn: HybridRk4) -> None:
        ca.Callback.__init__(self)
        self.dyn = dyn
        self.nw, self.nd = _STAGE * dyn.spec.horizon, NX * dyn.spec.horizon
        self.pattern = _JacobianPattern.build(dyn.spec.horizon)
        self._jacobians: list[_DefectsJacobian] = []  # CasADi keeps no Python reference: we must
        self.construct(name, {})

    def get_n_in(self) -> int:
        return 3

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> Any:
        return ca.Sparsity.dense((self.nw, NX, 1)[i], 1)

    def get_sparsity_out(self, i: int) -> Any:
        return ca.Sparsity.dense(self.nd, 1)

    def has_jac_sparsity(self, oind: int, iind: int) -> bool:
        return True

    def get_jac_sparsity(self, oind: int, iind: int, symmetric: bool) -> Any:
        return (self.pattern.w, self.pattern.x0, self.pattern.mass)[iind]

    def eval(self, args: list[Any]) -> list[Any]:
        defects, _ = self.dyn.run(np.asarray(args[0]).ravel(), np.asarray(args[1]).ravel(), float(args[2]), False)
        return [ca.DM(defects.ravel())]

    def has_jacobian(self) -> bool:
        return True

    def get_jacobian(self, name: str, inames: list[str], onames: list[str], opts: dict[str, Any]) -> Any:
        jac = _DefectsJacobian(name, self.dyn, self.pattern)
        self._jacobians.append(jac)
        return jac


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
        u_k = w[_STAGE * k : _STAGE * k + NU]
        ex = w[_STAGE * k + NU : _STAGE * (k + 1)] - x_ref[:, k]
        eu = u_k - u_ref[:, k]
        cost = cost + ca.dot(ex, (pt if k == n - 1 else q) * ex) + ca.dot(eu, rr * eu)
        if unmix is not None:
            poly.append(ca.mtimes(ca.DM(unmix), u_k))
    lbw = np.full(_STAGE * n, -np.inf)
    ubw = np.full(_STAGE * n, np.inf)
    lbw[0::_STAGE] = spec.thrust_bounds[0]
    ubw[0::_STAGE] = spec.thrust_bounds[1]
    return cost, poly, lbw, ubw


def _nominal_nlp(spec: FullMpcSpec) -> dict[str, Any]:
    """The SX problem with the nominal model inside the graph."""
    n, ns = spec.horizon, spec.substeps
    h = spec.dt / ns
    layout = _Layout(n)
    sl = layout.slices
    p = ca.SX.sym("p", layout.size)
    ws = ca.SX.sym("w", _STAGE * n)
    w = ws * ca.DM(spec.variable_scale)
    be = casadi_backend()
    x0, mass = p[sl["x0"]], p[sl["mass"]]
    cost, poly, _, _ = _cost_and_bounds(spec, w, p, ca.SX)
    dyn = []
    x = x0
    for k in range(n):
        u_k = w[_STAGE * k : _STAGE * k + NU]
        x_next = w[_STAGE * k + NU : _STAGE * (k + 1)]
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
            self._defects = _Defects("hybrid_defects", self._dyn)
            ws = ca.MX.sym("w", _STAGE * n)
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
        nw = _STAGE * n
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
        stages = w.reshape(n, _STAGE)
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
