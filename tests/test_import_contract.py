"""The import graph: pyproject.toml's contracts hold, no module import circle, the flight package without torch.

An editable install maps the top-level folders into ``cfknode`` with an import hook that
import-linter and grimp cannot walk, so the graph checks build a plain install of the checkout first.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Every module's direct imports within cfknode, as JSON; annotation-only imports count too.
_EDGES = """
import json, grimp
graph = grimp.build_graph("cfknode", cache_dir=None)
print(json.dumps({m: sorted(graph.find_modules_directly_imported_by(m)) for m in graph.modules}))
"""


@pytest.fixture(scope="module")
def plain_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A site directory holding a plain (non-editable) install of this checkout."""
    work = tmp_path_factory.mktemp("install")
    target = work / "site"
    import setuptools

    # Build with this interpreter's setuptools when it is new enough for pyproject.toml (no download).
    isolation = [] if int(setuptools.__version__.split(".")[0]) < 68 else ["--no-build-isolation"]
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", *isolation,
                    "--target", str(target), str(ROOT)], check=True, capture_output=True, text=True, timeout=600,
                   cwd=work)
    shutil.rmtree(work / "build", ignore_errors=True)
    return target


def _run_on(site: Path, code: str, *args: str) -> subprocess.CompletedProcess[str]:
    # The plain install comes first on the path, so the checkout's editable hook is not consulted.
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300,
                          cwd=site.parent, env={"PYTHONPATH": str(site), "PATH": str(Path(sys.executable).parent)})


def import_cycles(edges: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """Every group of two or more modules that import each other, directly or around a loop (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(edges.get(root, ())))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, targets = work[-1]
            target = next(targets, None)
            if target is not None:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(edges.get(target, ()))))
                elif target in on_stack:
                    low[node] = min(low[node], index[target])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1:
                    groups.append(sorted(group))
    return sorted(groups)


def test_the_cycle_finder_finds_loops_and_only_loops() -> None:
    edges = {"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": ["e"], "e": ["d"], "f": ["a"], "g": []}
    assert import_cycles(edges) == [["a", "b", "c"], ["d", "e"]]
    assert import_cycles({"a": ["b"], "b": ["c"], "c": []}) == []


def test_the_import_contracts_hold(plain_install: Path) -> None:
    # import-linter's own command, run by this interpreter (no console-script shim on PATH needed).
    lint = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    out = _run_on(plain_install, lint, str(ROOT / "pyproject.toml"))
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout


def test_no_module_of_cfknode_takes_part_in_an_import_circle(plain_install: Path) -> None:
    out = _run_on(plain_install, _EDGES)
    assert out.returncode == 0, out.stderr[-2000:]
    edges = json.loads(out.stdout)
    assert "cfknode.app.mission" in edges and "cfknode.flight.loop" in edges  # the graph is the real one
    assert import_cycles(edges) == []


def test_loading_every_flight_module_leaves_torch_unloaded() -> None:
    # The contract forbids direct imports; this catches an eager one through cfknode.models.
    code = ("import importlib, pkgutil, sys, cfknode.flight as f\n"
            "names = [m.name for m in pkgutil.walk_packages(f.__path__, 'cfknode.flight.')]\n"
            "[importlib.import_module(n) for n in names]\n"
            "print(len(names), 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    count, loaded = out.stdout.split()
    assert int(count) > 10
    assert loaded == "False"
