"""What a solver reports about its solves (the ``Solver`` protocol's ``stats()``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SolverStats:
    """Counts since the solver was built."""

    solves: int  # calls to solve
    failures: int  # answers not ok (the controller flew its fallback)
    rescues: int  # first answers that failed their check and were solved again, from a cold start
