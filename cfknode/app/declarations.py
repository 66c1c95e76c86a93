"""The declared settings read back: every key of ``Config`` with its field, type, unit, bounds and meaning.

Each field is declared once, with ``cfknode.kernel.setting.setting``; the bounds check
(``config_bounds.BOUNDS``), docs/configuration.md (``configuration_doc``) and the tests of the
packaged YAML read the declarations through ``declared``.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any, Iterator

from cfknode.app.settings import Config
from cfknode.kernel.setting import BOUNDS, DOC, UNIT

__all__ = ["Declared", "declared", "leaf_keys", "yaml_comment"]


@dataclass(frozen=True)
class Declared:
    """One declared key: ``record`` is true for a field of the records in a list (``sim.mass_changes.t``)."""

    key: str
    field: dataclasses.Field
    type: Any
    record: bool = False

    @property
    def doc(self) -> str:
        return self.field.metadata.get(DOC, "")

    @property
    def unit(self) -> str:
        return self.field.metadata.get(UNIT, "")

    @property
    def bounds(self) -> tuple[float, float, bool, bool] | None:
        return self.field.metadata.get(BOUNDS)

    @property
    def default(self) -> Any:
        return self.field.default


def declared(cls: type = Config, prefix: str = "", record: bool = False) -> Iterator[Declared]:
    """Every leaf key under ``cls`` in declaration order, then the fields of records in lists."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            yield from declared(tp, f"{prefix}{f.name}.", record)
            continue
        yield Declared(f"{prefix}{f.name}", f, tp, record)
        args = typing.get_args(tp)
        if typing.get_origin(tp) is tuple and args and dataclasses.is_dataclass(args[0]):
            yield from declared(args[0], f"{prefix}{f.name}.", True)


def leaf_keys() -> list[str]:
    """The keys a YAML file sets (fields of records in lists are inside their list's value)."""
    return [d.key for d in declared() if not d.record]


def yaml_comment(d: Declared) -> str:
    """The comment a packaged YAML file carries on the key's line: its meaning, then its unit."""
    return f"{d.doc} [{d.unit}]" if d.unit else d.doc
