"""RK4 of the hybrid model x' = f_nom + E r over a whole plan, with forward sensitivities, in numpy.

The network never enters the CasADi graph (see mpc_full.py): the interval defects and their
Jacobian come from here.
"""

from __future__ import annotations

import numpy as np

from cfknode.app.bench.paper.mpc_full_spec import NU, NX, NZ, STAGE, FullMpcSpec, ResidualModel
from cfknode.models.quadrotor import NUMPY, rigid_body_rhs

_RK_A = (0.5, 0.5, 1.0)  # RK4: stage j + 1 evaluates at y + _RK_A[j] h k_j
_RK_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)




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
        stages = w.reshape(n, STAGE)
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
