"""The full-state MPC's problem statement: dimensions, the residual interface, settings and result."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

NX = 13
NU = 4
NZ = NX + NU  # residual input z = (x, u)
STAGE = NU + NX  # decision variables per stage: u_k, x_{k+1}


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
