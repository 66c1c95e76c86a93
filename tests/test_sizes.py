"""The size rule of the library's code (issue 29): no file over 480 lines, no function over 80
lines, no function over 8 parameters. A seam that grows past these is split or given a parameter
object (a frozen dataclass) before it is merged, so the rule is checked here, not by review."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("cfknode", "kernel", "flight", "models", "mocap", "safety", "sim_backend")
MAX_FILE_LINES = 480
MAX_FUNCTION_LINES = 80
MAX_PARAMETERS = 8  # self and cls not counted; *args and **kwargs count one each


def _parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = node.args
    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
    first = (a.posonlyargs + a.args)[:1]
    return n - 1 if first and first[0].arg in ("self", "cls") else n


def violations(root: Path = ROOT) -> list[str]:
    """One line per file or function over a limit, as ``path[:function]: what``."""
    found = []
    for folder in FOLDERS:
        for path in sorted((root / folder).rglob("*.py")) if (root / folder).is_dir() else ():
            name = path.relative_to(root).as_posix()
            source = path.read_text(encoding="utf-8")
            lines = source.count("\n")
            if lines > MAX_FILE_LINES:
                found.append(f"{name}: {lines} lines (at most {MAX_FILE_LINES})")
            for node in ast.walk(ast.parse(source, filename=name)):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{name}:{node.name}: {length} lines (at most {MAX_FUNCTION_LINES})")
                params = _parameters(node)
                if params > MAX_PARAMETERS:
                    found.append(f"{name}:{node.name}: {params} parameters (at most {MAX_PARAMETERS})")
    return found


def test_the_checker_counts_lines_and_parameters(tmp_path: Path) -> None:
    (tmp_path / "flight").mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(80))
    (tmp_path / "flight" / "m.py").write_text(
        f"def long():\n{body}\n\n"
        "def wide(a, b, c, d, e, f, g, *args, **kwargs):\n    pass\n\n"
        "class C:\n    def ok(self, a, b, c, d, e, f, g, h):\n        pass\n"
    )
    assert violations(tmp_path) == [
        "flight/m.py:long: 81 lines (at most 80)",
        "flight/m.py:wide: 9 parameters (at most 8)",
    ]


def test_no_library_file_or_function_is_over_the_size_limits() -> None:
    found = violations()
    assert not found, "over the size limits (issue 29):\n" + "\n".join(found)
