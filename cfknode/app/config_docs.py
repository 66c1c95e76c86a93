"""docs/configuration.md, generated from the settings' declarations and the packaged YAML files.

``python -m cfknode.app.config_docs > docs/configuration.md`` rewrites it, and
``python -m cfknode.app.config_docs --yaml`` rewrites the comment on each key's line of the packaged
YAML files from the declared meaning and unit; tests/test_config_declarations.py checks both.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from importlib import resources
from typing import Any

import yaml

from cfknode.app.config import PACKAGED, dotted, load_config, packaged_settings
from cfknode.app.config_bounds import BOUNDS
from cfknode.app.declarations import Declared, declared, yaml_comment

__all__ = ["configuration_doc", "flat_keys", "packaged_keys", "packaged_text", "with_declared_comments"]

_HEAD = """# Configuration

Generated from the settings' declarations by `python -m cfknode.app.config_docs > docs/configuration.md`;
tests/test_config_declarations.py checks that this file is what it prints. Edit the declaration, not this;
`python -m cfknode.app.config_docs --yaml` then rewrites the packaged YAML's comments to match.

Each key is declared once, on its field in the layer's settings module (`setting(...)` from
`cfknode.kernel.setting`: default where the field has one, unit, bounds, one-line meaning). The
packaged values are in two files loaded together: `cfknode/config/default.yaml` holds the keys a
user sets, `cfknode/config/tuning.yaml` the tuning and bench keys. Both take the same dotted keys:
a user's `--config` file or `--set key=value` overrides a key of either. The measurements behind
the values are in [history.md](history.md#defaults-and-the-measurements-behind-them). A third,
`cfknode/config/wake.yaml`, holds the values of a fleet drone that learns a wake (its last table).
"""

_WAKE = """## A fleet drone learning a wake (`cfknode/config/wake.yaml`)

A fleet drone whose networks learn the wake of a drone above (`fleet.wake_only`, or chosen by
`fleet.wake_below`; [fleet.md](fleet.md#wake-only)) takes these values wherever its configuration keeps
the default: a value given in a `--config` file or with `--set` that differs from the default stays its own.
"""

_PARTS = (
    ("config/default.yaml", "Keys a user sets (`cfknode/config/default.yaml`)"),
    ("config/tuning.yaml", "Tuning and bench keys (`cfknode/config/tuning.yaml`)"),
)


def flat_keys(data: Any, prefix: str = "") -> list[str]:
    """The leaf keys of a YAML mapping, dotted (a list is one leaf)."""
    return list(dotted(data, prefix))


def packaged_keys(name: str) -> list[str]:
    """The leaf keys of one packaged file (``config/default.yaml`` or ``config/tuning.yaml``)."""
    return flat_keys(yaml.safe_load(resources.files("cfknode").joinpath(name).read_text()) or {})


def packaged_text(name: str) -> str:
    return resources.files("cfknode").joinpath(name).read_text()


_KEY_LINE = re.compile(r"^(\s*)(\w+):(.*)$")
_COMMENT_COLUMN = 28


def with_declared_comments(text: str) -> str:
    """A packaged YAML text with each declared key's comment made its declared meaning and unit."""
    decls = {d.key: d for d in declared() if not d.record}
    stack: list[tuple[int, str]] = []
    out = []
    for line in text.splitlines():
        m = _KEY_LINE.match(line)
        if m:
            indent, key, rest = len(m.group(1)), m.group(2), m.group(3)
            while stack and stack[-1][0] >= indent:
                stack.pop()
            stack.append((indent, key))
            dotted = ".".join(k for _, k in stack)
            if dotted in decls:
                head = f"{m.group(1)}{key}:{rest.split(' # ', 1)[0].rstrip()}"
                pad = f"{head:<{_COMMENT_COLUMN}}" if len(head) < _COMMENT_COLUMN else f"{head}  "
                line = f"{pad}# {yaml_comment(decls[dotted])}"
        out.append(line)
    return "\n".join(out) + "\n"


def _value(value: Any) -> str:
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_value(v)}" for k, v in value.items()) + "}"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return f'"{value}"' if value == "" else value
    return str(value)


def _get(cfg: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _row(d: Declared, cfg: Any) -> str:
    default = "(per record)" if d.record else _value(_get(cfg, d.key))
    bound = BOUNDS.get(d.key)
    bounds = bound.describe() if bound is not None else ""
    if bound is not None and bound.unit:
        bounds = bounds[: -len(bound.unit) - 1]  # the unit has its own column
    return f"| `{d.key}` | `{_cell(default)}` | {_cell(d.unit)} | {_cell(bounds)} | {_cell(d.doc)} |"


def configuration_doc() -> str:
    """The whole of docs/configuration.md: one table per section, in each packaged file."""
    assert tuple(name for name, _ in _PARTS) == PACKAGED
    cfg = load_config()
    decls = list(declared())
    lines = [_HEAD]
    for name, title in _PARTS:
        keys = set(packaged_keys(name))
        lines.append(f"## {title}\n")
        section = None
        for d in decls:
            owner = d.key.rsplit(".", 1)[0] if d.record else d.key
            if owner not in keys:
                continue
            top = d.key.split(".")[0] if "." in d.key else "(top level)"
            if top != section:
                if section is not None:
                    lines.append("")
                section = top
                lines.append(f"### {top}\n")
                lines.append("| key | default | unit | bounds | meaning |")
                lines.append("|---|---|---|---|---|")
            lines.append(_row(d, cfg))
        lines.append("")
    lines += [_WAKE, "| key | value | default |", "|---|---|---|"]
    lines += [f"| `{k}` | `{_cell(_value(v))}` | `{_cell(_value(_get(cfg, k)))}` |"
              for k, v in packaged_settings("wake").items()]
    return "\n".join(lines).rstrip("\n") + "\n"


if __name__ == "__main__":
    if sys.argv[1:] == ["--yaml"]:
        for name in PACKAGED:
            path = resources.files("cfknode").joinpath(name)
            path.write_text(with_declared_comments(path.read_text()))  # the source tree (an editable install)
    else:
        print(configuration_doc(), end="")
