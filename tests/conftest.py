"""Test speeds and isolation, applied at collection from one table (tests/speeds.py).

Each test gets the marks its file (or the test itself) has in ``speeds.SPEEDS``, so
``python -m pytest -m "not slow"`` is the fast run (docs/testing.md). Each file is one
``xdist_group``, so pytest-xdist keeps a file's module fixtures (one flight, shared by its
tests) on one worker; files that share something outside the process share a group.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from speeds import group_for, marks_for


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        name = getattr(item, "originalname", item.name)
        for mark in marks_for(item.path.name, name):
            item.add_marker(mark)
        item.add_marker(pytest.mark.xdist_group(group_for(item.path.name)))


@pytest.fixture(autouse=True, scope="session")
def _own_runtime_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A runtime directory per test process, so two workers' flights never share an e-stop mailbox.

    The default mailbox is ``$XDG_RUNTIME_DIR/cfknode``; a flight claims its robot's name there, and
    a second flight of the same robot in the same directory is refused. Subprocesses inherit it.
    """
    runtime = tmp_path_factory.mktemp("runtime")
    runtime.chmod(0o700)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("XDG_RUNTIME_DIR", str(runtime))
        yield runtime
