"""A flight whose log stops writing mid-flight (full disk): it lands, and says its log is incomplete."""

from __future__ import annotations

import errno
import json
from pathlib import Path
from typing import Any, BinaryIO

import pytest

from cfknode.app.cli import main
from cfknode.app.logs import writer as flightlog
from cfknode.app.logs.reader import read_log

SHORT = [
    "--set", "trajectory.duration=1.5", "--set", "trajectory.takeoff_duration=1.0",
    "--set", "trajectory.settle_duration=0.2", "--set", "trajectory.land_duration=1.0",
    "--set", "trajectory.ramp_duration=0.4",
]


class FullDisk:
    """A log file whose writes fail with ENOSPC from the ``fail_after``-th write on."""

    def __init__(self, stream: BinaryIO, fail_after: int) -> None:
        self._stream, self._left = stream, fail_after

    def write(self, data: Any) -> int:
        if self._left <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        self._left -= 1
        return self._stream.write(data)

    def __getattr__(self, name: str) -> Any:  # tell, flush, close: the real file's
        return getattr(self._stream, name)


def fly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        fail_after: int | None) -> tuple[int, dict, str, Path]:
    real_open = flightlog._open_unique
    if fail_after is not None:
        def failing_open(directory: Path, stamp: str, hint: str) -> tuple[Path, Any]:
            path, stream = real_open(directory, stamp, hint)
            return path, FullDisk(stream, fail_after)

        monkeypatch.setattr(flightlog, "_open_unique", failing_open)
    code = main(["fly", "--headless", "--json", "--log-dir", str(tmp_path), "--set",
                 f"safety.estop_dir={tmp_path / 'estop'}", *SHORT])
    out, err = capsys.readouterr()
    (path,) = tmp_path.glob("*.mcap")
    return code, json.loads(out), err, path


def test_a_log_that_stops_writing_makes_the_flight_say_so_and_fail(tmp_path, monkeypatch, capsys):
    code, summary, err, path = fly(tmp_path, monkeypatch, capsys, fail_after=40)
    note = summary["extra"]["flight_log"]
    assert note.startswith("incomplete from t = ") and "No space left on device" in note, note
    lost_from = float(note.split("t = ")[1].split(" s")[0])
    assert 0.0 < lost_from < summary["duration_s"]
    assert code == 1  # the flight landed, but its record is lost from lost_from on
    outcome = [line for line in err.splitlines() if line.startswith("cfknode: flight complete")]
    assert outcome == [f"cfknode: flight complete: landed; but the flight log is {note}"]
    # What reached the disk reads back: everything before lost_from, nothing written after the failure.
    data = read_log(path)
    assert data.truncated and not data.topic("/summary")
    t_state = data.times("/state")
    assert lost_from - 0.01 <= t_state.max() < lost_from + 0.5  # at most the failed chunk past it
    assert len(t_state) < summary["ticks"]


def test_a_fully_written_log_keeps_exit_status_0(tmp_path, monkeypatch, capsys):
    code, summary, err, path = fly(tmp_path, monkeypatch, capsys, fail_after=None)
    assert code == 0 and "flight_log" not in summary["extra"]
    assert "cfknode: flight complete: landed" in err.splitlines()
    assert not read_log(path).truncated
