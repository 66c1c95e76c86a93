"""Outputs are written over regular files only: never over a device node, a FIFO or a directory."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from cfknode.kernel.outputs import output_problem
from cfknode.models.modelfile import ModelFileError, load_model, save_model
from test_modelfile import make_model  # pytest puts tests/ on sys.path


def test_new_paths_and_regular_files_may_be_written(tmp_path: Path) -> None:
    assert output_problem(tmp_path / "new.safetensors") is None
    (tmp_path / "old").write_bytes(b"x")
    assert output_problem(tmp_path / "old") is None
    (tmp_path / "link").symlink_to(tmp_path / "old")
    assert output_problem(tmp_path / "link") is None


@pytest.mark.parametrize("kind", ["directory", "fifo", "device", "device link", "dangling link"])
def test_anything_else_is_refused_in_one_line(tmp_path: Path, kind: str) -> None:
    target = tmp_path / "out"
    if kind == "directory":
        target.mkdir()
    elif kind == "fifo":
        os.mkfifo(target)
    elif kind == "device":
        target = Path("/dev/null")
    elif kind == "device link":
        target.symlink_to("/dev/null")
    else:
        target.symlink_to(tmp_path / "nowhere")
    problem = output_problem(target)
    assert problem is not None and "\n" not in problem and str(target) in problem
    word = {"directory": "a directory", "fifo": "a FIFO", "device": "a character device",
            "device link": "a character device", "dangling link": "dangling"}[kind]
    assert word in problem


def test_save_model_leaves_a_fifo_and_a_device_link_alone(tmp_path: Path) -> None:
    fifo = tmp_path / "m.fifo"
    os.mkfifo(fifo)
    link = tmp_path / "m.link"
    link.symlink_to("/dev/null")
    for target in (fifo, link):
        with pytest.raises(ModelFileError, match="not a regular file"):
            save_model(target, make_model())
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.readlink(link) == "/dev/null"
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # no temp file left behind
    good = save_model(tmp_path / "m.safetensors", make_model())
    assert load_model(good).queue_size == make_model().queue_size


def test_train_refuses_a_device_as_out_before_training(tmp_path: Path, capsys) -> None:
    from cfknode.app.cli import main

    code = main(["train", "--log", str(tmp_path / "missing.mcap"), "--out", "/dev/null"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "--out /dev/null is a character device, not a regular file" in err[0]
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
