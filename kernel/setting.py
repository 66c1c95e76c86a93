"""One declaration per setting: a dataclass field carrying its default, unit, bounds and meaning.

Every settings dataclass (``cfknode.flight.settings``, ``cfknode.safety.settings``, ...) declares
its keys with ``setting``. The application reads the metadata back: the bounds check
(``cfknode.app.config_bounds.BOUNDS``), the key table in docs/configuration.md and the comments of
the packaged YAML all come from it. A field without a default takes its value from the packaged
YAML (``cfknode/config/default.yaml`` or ``tuning.yaml``); tests/test_config_declarations.py
checks that the two agree.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["DOC", "BOUNDS", "UNIT", "setting"]

DOC, UNIT, BOUNDS = "doc", "unit", "bounds"


def setting(default: Any = dataclasses.MISSING, *, doc: str, unit: str = "", low: float | None = None,
            high: float | None = None, open_low: bool = False, open_high: bool = False) -> Any:
    """A dataclass field: ``doc`` is its one-line meaning; ``low``..``high`` (an open end excludes itself).

    A bound applies to a number, to every element of a list of numbers and, for a field of a
    record in a list (``sim.mass_changes``), to that field of every record.
    """
    if (low is None) != (high is None):
        raise ValueError("setting: give both low and high, or neither")
    metadata = {DOC: doc, UNIT: unit, BOUNDS: None if low is None else (low, high, open_low, open_high)}
    return dataclasses.field(default=default, metadata=metadata)
