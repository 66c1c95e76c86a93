"""CasADi callbacks that hand IPOPT the hybrid model's interval defects and their sparse Jacobian."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from cfknode.app.bench.paper.hybrid_rk4 import HybridRk4
from cfknode.app.bench.paper.mpc_full_spec import NU, NX, NZ, STAGE


def _defect_jacobian_pattern(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of d(defects)/dw in the order ``_DefectsJacobian`` fills the values."""
    rows, cols = [], []
    for k in range(n):
        base_r = NX * k
        for r in range(NX):  # + I on x_{k+1}
            rows.append(base_r + r)
            cols.append(STAGE * k + NU + r)
        for r in range(NX):  # - dF/du_k
            for c in range(NU):
                rows.append(base_r + r)
                cols.append(STAGE * k + c)
        if k > 0:  # - dF/dx_k (x_0 is a parameter)
            for r in range(NX):
                for c in range(NX):
                    rows.append(base_r + r)
                    cols.append(STAGE * (k - 1) + NU + c)
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
            w=ca.Sparsity.triplet(NX * n, STAGE * n, rows.tolist(), cols.tolist()),
            perm_w=np.lexsort((rows, cols)),  # CasADi stores nonzeros column by column
            x0=ca.Sparsity.triplet(NX * n, NX, r0.tolist(), c0.tolist()),
            perm_x0=np.lexsort((r0, c0)),
            mass=ca.Sparsity.dense(NX * n, 1),
        )


class _DefectsJacobian(ca.Callback):
    """Jacobian of ``Defects``: inputs (w, x0, mass, defects) -> blocks w.r.t. w, x0, mass."""

    def __init__(self, name: str, dyn: HybridRk4, pattern: _JacobianPattern) -> None:
        ca.Callback.__init__(self)
        self.dyn = dyn
        self.pattern = pattern
        n = dyn.spec.horizon
        self.nw, self.nd = STAGE * n, NX * n
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


class Defects(ca.Callback):
    """(w, x0, mass) -> x_{k+1} - F(x_k, u_k) for k = 0..N-1, computed by ``HybridRk4``.

    It declares its Jacobian's sparsity: without it CasADi assumes a dense Jacobian, and the
    KKT factorisation was measured 20x slower.
    """

    def __init__(self, name: str, dyn: HybridRk4) -> None:
        ca.Callback.__init__(self)
        self.dyn = dyn
        self.nw, self.nd = STAGE * dyn.spec.horizon, NX * dyn.spec.horizon
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
