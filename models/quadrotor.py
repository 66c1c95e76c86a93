"""The nominal quadrotor model, written once and rendered in numpy, CasADi and torch.

Two models share one set of conventions (world frame z up, body FLU, quaternion
scalar-first ``(w, x, y, z)`` rotating body to world):

- translational: x = (p, v) in R^6, u = commanded acceleration a in R^3;
  p' = v, v' = a.  The hierarchical hardware path predicts with it.
- rigid body: x = (p, v, q, w) in R^13, u = (T, Mx, My, Mz) collective thrust [N]
  and body moments [N m]; m v' = T R e3 - m g e3 + f_ext, q' = q (x) (0, w) / 2,
  J w' = M - w x J w.  The paper's simulation setting and the simulator's plant.

Each equation is written against a tiny array "backend" (unpack a vector into its
components, stack components back), so numpy (batched over leading axes), CasADi
(SX/MX column vectors) and torch (batched, differentiable) share the same lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

TRANSLATIONAL_STATES = ("px", "py", "pz", "vx", "vy", "vz")
TRANSLATIONAL_INPUTS = ("ax", "ay", "az")
RIGID_BODY_STATES = ("px", "py", "pz", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "wx", "wy", "wz")
RIGID_BODY_INPUTS = ("T", "Mx", "My", "Mz")


@dataclass(frozen=True)
class Backend:
    """How to split a vector into components and stack components into a vector."""

    unpack: Callable[[Any, int], list[Any]]
    stack: Callable[[Sequence[Any]], Any]


def _np_unpack(x: Any, n: int) -> list[Any]:
    return [x[..., i] for i in range(n)]


NUMPY = Backend(unpack=_np_unpack, stack=lambda xs: np.stack(np.broadcast_arrays(*xs), axis=-1))


def casadi_backend() -> Backend:
    import casadi as ca

    return Backend(unpack=lambda x, n: [x[i] for i in range(n)], stack=lambda xs: ca.vertcat(*xs))


def torch_backend() -> Backend:
    import torch

    return Backend(unpack=_np_unpack, stack=lambda xs: torch.stack(list(torch.broadcast_tensors(*xs)), dim=-1))


def translational_rhs(x: Any, u: Any, be: Backend = NUMPY) -> Any:
    """p' = v, v' = a_cmd."""
    _, _, _, vx, vy, vz = be.unpack(x, 6)
    ax, ay, az = be.unpack(u, 3)
    return be.stack([vx, vy, vz, ax, ay, az])


def thrust_direction(qw: Any, qx: Any, qy: Any, qz: Any) -> tuple[Any, Any, Any]:
    """Third column of R(q): the body z axis in the world frame."""
    return (
        2.0 * (qx * qz + qw * qy),
        2.0 * (qy * qz - qw * qx),
        1.0 - 2.0 * (qx * qx + qy * qy),
    )


def rigid_body_rhs(
    x: Any,
    u: Any,
    mass: float | Any,
    inertia: Sequence[float],
    gravity: float,
    be: Backend = NUMPY,
    force: Any | None = None,
) -> Any:
    """Rigid-body derivative; ``force`` is an optional external world force [N] (3-vector)."""
    _, _, _, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = be.unpack(x, 13)
    thrust, mx, my, mz = be.unpack(u, 4)
    jx, jy, jz = inertia
    bx, by, bz = thrust_direction(qw, qx, qy, qz)
    fx, fy, fz = (0.0, 0.0, 0.0) if force is None else be.unpack(force, 3)
    ax = (thrust * bx + fx) / mass
    ay = (thrust * by + fy) / mass
    az = (thrust * bz + fz) / mass - gravity
    dqw = -0.5 * (qx * wx + qy * wy + qz * wz)
    dqx = 0.5 * (qw * wx + qy * wz - qz * wy)
    dqy = 0.5 * (qw * wy + qz * wx - qx * wz)
    dqz = 0.5 * (qw * wz + qx * wy - qy * wx)
    # Euler's equations for a diagonal inertia: J w' = M - w x (J w).
    dwx = (mx - (jz - jy) * wy * wz) / jx
    dwy = (my - (jx - jz) * wz * wx) / jy
    dwz = (mz - (jy - jx) * wx * wy) / jz
    return be.stack([vx, vy, vz, ax, ay, az, dqw, dqx, dqy, dqz, dwx, dwy, dwz])


def hover_input(mass: float, gravity: float) -> np.ndarray:
    """Rigid-body input that holds a level hover: T = m g, no moments."""
    return np.array([mass * gravity, 0.0, 0.0, 0.0])


def casadi_translational() -> Any:
    """CasADi Function f(x[6], u[3]) -> x'[6]."""
    import casadi as ca

    x = ca.SX.sym("x", 6)
    u = ca.SX.sym("u", 3)
    return ca.Function("translational", [x, u], [translational_rhs(x, u, casadi_backend())], ["x", "u"], ["xdot"])


def casadi_rigid_body(inertia: Sequence[float], gravity: float) -> Any:
    """CasADi Function f(x[13], u[4], mass) -> x'[13] (mass is an input so events can change it)."""
    import casadi as ca

    x = ca.SX.sym("x", 13)
    u = ca.SX.sym("u", 4)
    m = ca.SX.sym("m")
    rhs = rigid_body_rhs(x, u, m, inertia, gravity, casadi_backend())
    return ca.Function("rigid_body", [x, u, m], [rhs], ["x", "u", "mass"], ["xdot"])


def rk4_step(f: Callable[[Any, Any], Any], x: Any, u: Any, h: float) -> Any:
    """One classical Runge-Kutta step of x' = f(x, u) with u held; backend-agnostic."""
    k1 = f(x, u)
    k2 = f(x + 0.5 * h * k1, u)
    k3 = f(x + 0.5 * h * k2, u)
    k4 = f(x + h * k3, u)
    return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (body to world) from a scalar-first unit quaternion."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_to_euler_zyx(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad, ZYX convention, from a scalar-first quaternion."""
    w, x, y, z = q
    roll = float(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = float(np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)))
    yaw = float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    return roll, pitch, yaw


def euler_zyx_to_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Scalar-first quaternion from ZYX (yaw, then pitch, then roll) Euler angles in rad."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )
