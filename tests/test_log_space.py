"""A take-off whose log cannot be written is refused: too little free space for the flight's
expected log, or a log whose start cannot reach the disk. And chunks end by flight time."""

from __future__ import annotations

import errno
import shutil
from collections import namedtuple
from pathlib import Path
from typing import Any

import pytest

from cfknode.app.cli import main
from cfknode.app.config import ConfigError, load_config
from cfknode.app.flight_checks import expected_log_bytes, log_space_problem, refuse_unflyable
from cfknode.app.logs import writer as flightlog
from cfknode.app.logs.format import LogError
from cfknode.app.logs.writer import FlightLog

Usage = namedtuple("Usage", "total used free")


def _free(monkeypatch: pytest.MonkeyPatch, free: int) -> None:
    real = shutil.disk_usage

    def fake(path: Any) -> Usage:
        real(path)  # the path must exist, as for the real call
        return Usage(1 << 40, (1 << 40) - free, free)

    monkeypatch.setattr(shutil, "disk_usage", fake)


def test_the_expected_size_grows_with_drones_and_duration(tmp_path: Path) -> None:
    one = load_config(overrides={"log.dir": str(tmp_path)})
    three = load_config(overrides={"log.dir": str(tmp_path), "fleet.size": 3})
    longer = load_config(overrides={"log.dir": str(tmp_path), "trajectory.duration": 40.0})
    assert expected_log_bytes(three) - flightlog_fixed() == pytest.approx(3 * (expected_log_bytes(one)
                                                                               - flightlog_fixed()))
    assert expected_log_bytes(longer) > expected_log_bytes(one)


def flightlog_fixed() -> int:
    from cfknode.app.flight_checks import LOG_FIXED_BYTES

    return LOG_FIXED_BYTES


def test_too_little_free_space_refuses_the_take_off_in_one_line(tmp_path: Path, monkeypatch) -> None:
    cfg = load_config(overrides={"log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "estop")})
    need = expected_log_bytes(cfg)
    _free(monkeypatch, need)
    assert log_space_problem(cfg) is None
    refuse_unflyable(cfg)
    _free(monkeypatch, 24_000)  # 24 kB
    with pytest.raises(ConfigError) as err:
        refuse_unflyable(cfg)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"take-off refused: log.dir {tmp_path} has 0.0 MB free")
    assert f"needs about {need / 1e6:.1f} MB" in text


def test_the_cli_refuses_before_anything_is_built_or_logged(tmp_path: Path, monkeypatch, capsys) -> None:
    _free(monkeypatch, 24_000)
    code = main(["fly", "--headless", "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={tmp_path / 'estop'}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "take-off refused: log.dir" in err[0]
    assert not list(tmp_path.glob("*.mcap"))  # no empty log left behind


class _NoSpace:
    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, data: Any) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def test_a_log_whose_start_cannot_be_written_is_refused_and_removed(tmp_path: Path, monkeypatch) -> None:
    real_open = flightlog._open_unique
    monkeypatch.setattr(flightlog, "_open_unique", lambda d, s, h: (lambda p, f: (p, _NoSpace(f)))(*real_open(d, s, h)))
    with pytest.raises(LogError, match="take-off refused: cannot write the flight log .*No space left on device"):
        FlightLog.create(tmp_path, {"a": 1}, "v", "full")
    assert not list(tmp_path.glob("*.mcap"))


def _chunk_times(path: Path) -> list[tuple[int, int]]:
    import struct

    from cfknode.app.logs.format import MCAP_MAGIC

    raw, pos, out = path.read_bytes(), len(MCAP_MAGIC), []
    while pos + 9 <= len(raw):
        op, length = struct.unpack_from("<BQ", raw, pos)
        if op == 0x06:
            out.append(struct.unpack_from("<QQ", raw, pos + 9))
        if op == 0x02:
            break
        pos += 9 + length
    return out


def test_chunks_end_by_flight_time_whatever_the_wall_clock_does(tmp_path: Path, monkeypatch) -> None:
    msg = {"compute_s": 0.0, "solve_s": 0.0, "missed": False, "mpc_ok": True}
    chunks = []
    for run, step in enumerate((0.0, 0.3)):  # wall time frozen, then 0.3 s per message (a loaded machine)
        wall = [0.0]

        def clock() -> float:
            wall[0] += step
            return wall[0]

        monkeypatch.setattr(flightlog.time, "monotonic", clock)
        with FlightLog.create(tmp_path / str(run), {"a": 1}, "v", "chunks", flush_interval=0.5) as log:
            for k in range(800):
                log.write("/tick", k / 400, msg)
        chunks.append(_chunk_times(log.path))
    assert chunks[0] == chunks[1]
    spans = [(b - a) * 1e-9 for a, b in chunks[0][1:-1]]  # the ones between the first and the last
    assert len(spans) >= 3 and all(s == pytest.approx(0.5, abs=0.003) for s in spans)
