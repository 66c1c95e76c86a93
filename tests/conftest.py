"""Test speeds and isolation, applied at collection from one table (tests/speeds.py).

Each test gets the marks its file (or the test itself) has in ``speeds.SPEEDS``, so
``python -m pytest -m "not slow"`` is the fast run (docs/testing.md). Each file is one
``xdist_group``, so pytest-xdist keeps a file's module fixtures (one flight, shared by its
tests) on one worker; files that share something outside the process share a group. The longest
groups start first (``speeds.LONGEST``), so the two workers end together. Each worker has its own
runtime directory; the workers share one cache directory, where each MPC variant compiles once.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from speeds import LONGEST, group_for, marks_for


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        name = getattr(item, "originalname", item.name)
        for mark in marks_for(item.path.name, name):
            item.add_marker(mark)
        item.add_marker(pytest.mark.xdist_group(group_for(item.path.name)))


@pytest.hookimpl(tryfirst=True, optionalhook=True)  # before pytest-xdist's own; absent without it
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """``--dist loadgroup``, but the groups of ``speeds.LONGEST`` are handed out first, longest first.

    pytest-xdist hands out the groups with the most tests first, which leaves a long group of a few
    tests (a benchmark's one run) to start last and run alone while the other worker idles.
    """
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    def rank(group: str) -> int:
        return LONGEST.index(group) if group in LONGEST else len(LONGEST)

    class LongestFirst(LoadGroupScheduling):
        def _assign_work_unit(self, node: object) -> None:
            # The first of the lowest rank; the others keep pytest-xdist's order.
            self.workqueue.move_to_end(min(self.workqueue, key=rank), last=False)
            super()._assign_work_unit(node)

    return LongestFirst(config, log)


@pytest.fixture(autouse=True, scope="session")
def _own_runtime_dir_and_shared_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A runtime directory per test process (each xdist worker), and a cache directory the session's
    workers share, which subprocesses inherit; neither is the user's own.

    Two workers' flights then never share the default e-stop mailbox (``$XDG_RUNTIME_DIR/cfknode``,
    where a flight claims its robot's name). They do share the code-generation cache
    (``$XDG_CACHE_HOME/cfknode``): each MPC variant compiles once a run (seconds of gcc each), not once a
    worker. A library lands there by an atomic rename (flight/mpc_codegen.py), so two workers compiling
    one variant at once each load a complete library.
    """
    root = tmp_path_factory.mktemp("xdg")
    (root / "runtime").mkdir(mode=0o700)
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-cache"
    shared.mkdir(mode=0o700, exist_ok=True)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("XDG_RUNTIME_DIR", str(root / "runtime"))
        patch.setenv("XDG_CACHE_HOME", str(shared))
        yield root
