"""Every test file has a speed class (tests/speeds.py), so a slow new file cannot join the fast run unseen."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

from speeds import FAST, GROUPS, LONGEST, MARKS, SLOW, SPEEDS, group_for, marks_for

TESTS = Path(__file__).resolve().parent


def _test_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {node.name for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name.startswith("test_")}


def test_every_test_file_is_classified_and_every_entry_is_a_test_file() -> None:
    files = {p.name for p in TESTS.glob("test_*.py")}
    assert sorted(files - set(SPEEDS)) == [], "add these files to tests/speeds.py"
    assert sorted(set(SPEEDS) - files) == [], "these entries of tests/speeds.py name no test file"
    assert set(GROUPS) <= files


def test_every_named_test_exists_and_every_mark_is_known() -> None:
    for file, speed in SPEEDS.items():
        per_test = speed if isinstance(speed, dict) else {"*": speed}
        stale = set(per_test) - {"*"} - _test_names(TESTS / file)
        assert not stale, f"{file}: tests/speeds.py names tests that do not exist: {sorted(stale)}"
        for marks in per_test.values():
            assert set(marks) <= set(MARKS), (file, marks)


def test_the_marks_are_the_ones_pytest_registers() -> None:
    config = tomllib.loads((TESTS.parent / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["pytest"]
    registered = {line.split(":")[0] for line in config["ini_options"]["markers"]}
    assert set(MARKS) <= registered
    assert "--strict-markers" in config["ini_options"]["addopts"]


def test_a_file_entry_marks_all_its_tests_and_a_mapping_each_test() -> None:
    table = {"test_a.py": (SLOW,), "test_b.py": {"test_one": (SLOW,), "*": FAST}}
    assert marks_for("test_a.py", "test_x", table) == (SLOW,)
    assert marks_for("test_b.py", "test_one", table) == (SLOW,)
    assert marks_for("test_b.py", "test_two", table) == FAST
    assert marks_for("test_c.py", "test_x", table) == FAST


def test_the_fast_run_keeps_unit_tests_of_files_that_also_fly() -> None:
    mixed = [file for file, speed in SPEEDS.items() if isinstance(speed, dict) and speed.get("*") == FAST]
    assert mixed, "files with both flights and unit tests keep the unit tests in the fast run"


def test_collection_gives_each_test_its_files_group(request: pytest.FixtureRequest) -> None:
    marker = request.node.get_closest_marker("xdist_group")
    assert marker is not None and marker.args[0] == group_for("test_speeds.py") == "test_speeds.py"


def test_the_longest_groups_are_groups_of_test_files() -> None:
    groups = {group_for(file) for file in SPEEDS}
    assert set(LONGEST) <= groups, sorted(set(LONGEST) - groups)
    assert len(set(LONGEST)) == len(LONGEST)


def test_the_workers_take_the_longest_groups_first_then_pytest_xdists_order() -> None:
    from types import SimpleNamespace

    import conftest

    class TwoWorkers:  # the options of `-n 2 --dist loadgroup`, as the scheduler reads them
        option = SimpleNamespace(loadscopereorder=True)

        def getvalue(self, name: str) -> object:
            return {"dist": "loadgroup", "tx": ["2*popen"]}[name]

    scheduler = conftest.pytest_xdist_make_scheduler(TwoWorkers(), None)
    queue = ["test_many.py", LONGEST[1], "test_few.py", LONGEST[0]]  # as pytest-xdist orders them
    scheduler.workqueue.update((group, {f"{group}::t": False}) for group in queue)
    sent: list[list[int]] = []

    class Node:  # a worker: what it was sent to run
        def send_runtest_some(self, indices: list[int]) -> None:
            sent.append(indices)

    node = Node()
    scheduler.registered_collections[node] = [f"{group}::t" for group in queue]
    for _ in queue:
        scheduler._assign_work_unit(node)
    assert [queue[i] for (i,) in sent] == [LONGEST[0], LONGEST[1], "test_many.py", "test_few.py"]
