"""Broken, damaged and odd log files through the reader and `cfknode plot`, `replay` and `train`.

Every case ends with one line on stderr naming the file and what is wrong: exit status 2 when
nothing usable is left, else the bad parts are skipped and counted. Never a traceback.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Any, Callable

import pytest
from mcap.writer import CompressionType, Writer

from cfknode.app.cli import main
from cfknode.app.config import load_config
from cfknode.app.logs.format import CHANNELS, MCAP_MAGIC
from cfknode.app.logs.reader import LogData, read_log, replay_mocap
from cfknode.app.mission import run_flight
from fakes import SHORT_FLIGHT
from cfknode.mocap.replay import ReplayError

SHORT = SHORT_FLIGHT


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> LogData:
    d = tmp_path_factory.mktemp("flight")
    cfg = load_config(overrides={**SHORT, "log.dir": str(d), "safety.estop_dir": str(d / "estop")})
    return read_log(run_flight(cfg, name_hint="ok").summary.log_path)


def rewrite(
    src: LogData,
    dst: Path,
    message: Callable[[str, dict], Any] = lambda topic, msg: msg,
    schema: Callable[[str, bytes], bytes] = lambda topic, data: data,
    config_metadata: str | None = None,
) -> Path:
    """``src`` written again by the stock MCAP writer, with what a test breaks: a message
    (``message`` returns the JSON value to write, or None to leave it out), a schema, the metadata."""
    metadata = dict(src.metadata["cfknode"])
    if config_metadata is not None:
        metadata["config"] = config_metadata
    with open(dst, "wb") as f:
        writer = Writer(f, chunk_size=32 * 1024, compression=CompressionType.LZ4)
        writer.start()
        writer.add_metadata("cfknode", metadata)
        ids = {}
        for spec in CHANNELS:
            data = schema(spec.topic, json.dumps(spec.json_schema()).encode())
            ids[spec.topic] = writer.register_channel(
                spec.topic, "json", writer.register_schema(spec.schema_name, "jsonschema", data))
        flat = sorted(((m["t"], topic, m) for topic, ms in src.messages.items() for m in ms), key=lambda x: x[0])
        for t, topic, msg in flat:
            value = message(topic, msg)
            if value is not None:
                ns = round(t * 1e9)
                writer.add_message(ids[topic], ns, json.dumps(value).encode(), ns)
        writer.finish()
    return dst


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return code, out, err


def one_line(err: str, path: Path, *phrases: str) -> str:
    """The one cfknode line on stderr: it names the file and says what is wrong."""
    lines = [line for line in err.splitlines() if line.startswith("cfknode:")]
    assert len(lines) == 1, err
    assert str(path) in lines[0], lines[0]
    for phrase in phrases:
        assert phrase in lines[0], (phrase, lines[0])
    return lines[0]


def commands(path: Path, tmp_path: Path) -> dict[str, list[str]]:
    return {
        "plot": ["plot", str(path), "--out", str(tmp_path / "plots")],
        "replay": ["replay", str(path), "--json"],
        "train": ["train", "--log", str(path), "--out", str(tmp_path / "model.safetensors"), "--epochs", "2"],
    }


def every_fifth_state_without_p(topic: str, msg: dict) -> dict:
    if topic == "/state" and round(msg["t"] * 400) % 5 == 0:
        return {k: v for k, v in msg.items() if k != "p"}
    return msg


# --- Bad contents: refused (status 2) when nothing usable is left, else skipped and counted ------------

REFUSED = {
    # (case, command): phrases of the error line
    ("state_as_lists", "plot"): ("no usable /state messages", "not a JSON object (list)"),
    ("state_as_lists", "replay"): ("no usable /state messages", "not a JSON object (list)"),
    ("state_as_lists", "train"): ("no usable /state messages", "not a JSON object (list)"),
    ("command_without_acc", "replay"): ("no usable /command messages", "missing 'acc'"),
    ("command_without_acc", "train"): ("no usable /command messages", "missing 'acc'"),
    ("no_config_at_all", "replay"): ("holds no configuration", "metadata config is not a JSON object"),
}


def broken(case: str, flight: LogData, tmp_path: Path) -> Path:
    dst = tmp_path / f"{case}.mcap"
    if case == "state_as_lists":
        return rewrite(flight, dst, lambda topic, m: m["p"] if topic == "/state" else m)
    if case == "command_without_acc":
        return rewrite(flight, dst, lambda topic, m: {k: v for k, v in m.items() if k != "acc"}
                       if topic == "/command" else m)
    if case == "no_config_at_all":
        return rewrite(flight, dst, lambda topic, m: None if topic == "/config" else m, config_metadata="{not json")
    if case == "schema_not_json":
        return rewrite(flight, dst, schema=lambda topic, data: b"{not json" if topic == "/state" else data)
    if case == "metadata_not_json":
        return rewrite(flight, dst, config_metadata="{not json")
    if case == "some_states_without_p":
        return rewrite(flight, dst, every_fifth_state_without_p)
    raise AssertionError(case)


@pytest.mark.parametrize("case, command", sorted(REFUSED))
def test_a_log_with_nothing_usable_left_is_one_line_and_status_2(flight, tmp_path, capsys, case, command):
    path = broken(case, flight, tmp_path)
    code, out, err = run(capsys, *commands(path, tmp_path)[command])
    assert code == 2
    assert one_line(err, path, *REFUSED[(case, command)]).startswith("cfknode: error: ")


WARNED = {
    "schema_not_json": "schema cfknode.State of /state is not a JSON object (ignored)",
    "metadata_not_json": "metadata config is not a JSON object (used the /config message)",
    "some_states_without_p": "malformed message(s) skipped (/state: missing 'p' x",
}


@pytest.mark.parametrize("case", sorted(WARNED))
def test_plot_skips_what_is_broken_and_says_so(flight, tmp_path, capsys, case):
    path = broken(case, flight, tmp_path)
    code, out, err = run(capsys, *commands(path, tmp_path)["plot"])
    assert code == 0
    assert one_line(err, path, WARNED[case]).startswith("cfknode: warning: ")
    assert "mpc (rti)" in out  # the config was found: the controller is named


def test_skipped_messages_are_counted_and_the_rest_is_used(flight, tmp_path, capsys):
    path = broken("some_states_without_p", flight, tmp_path)
    data = read_log(path)
    bad = sum(1 for m in flight.topic("/state") if round(m["t"] * 400) % 5 == 0)
    assert bad > 100 and data.damage.bad_messages == {"/state: missing 'p'": bad}
    assert data.count("/state") == flight.count("/state") - bad
    assert f"{bad} malformed message(s) skipped" in data.note
    code, out, err = run(capsys, *commands(path, tmp_path)["replay"])
    assert code == 0
    report = json.loads(out)
    assert report["log_damage"]["malformed_messages"] == {"/state: missing 'p'": bad}
    # Every command is replayed or skipped; the ticks whose state was dropped are among the skipped.
    assert report["ticks"] + sum(report["skipped"].values()) == flight.count("/command")
    assert sum(report["skipped"].values()) >= bad
    one_line(err, path, f"{bad} malformed message(s) skipped")
    code, out, err = run(capsys, *commands(path, tmp_path)["train"])
    assert code == 0
    one_line(err, path, f"{bad} malformed message(s) skipped")


def test_config_from_the_config_message_when_the_metadata_is_broken(flight, tmp_path):
    data = read_log(broken("metadata_not_json", flight, tmp_path))
    assert data.config == flight.config and data.damage.warnings


# --- Files that are not logs: refused before reading ---------------------------------------------------


def test_fifo_device_and_directory_are_refused_without_reading(tmp_path, capsys):
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)  # opening it for reading would block until a writer came
    cases = [(fifo, "a FIFO"), (Path("/dev/zero"), "a character device"), (tmp_path, "a directory")]
    for path, kind in cases:
        for command in ("plot", "replay", "train"):
            code, _, err = run(capsys, *commands(path, tmp_path / "out")[command])
            assert code == 2
            one_line(err, path, kind, "not a regular file")


def test_the_magic_is_checked_first_and_lengths_are_bounded(flight, tmp_path, capsys):
    not_mcap = tmp_path / "zeros.mcap"
    not_mcap.write_bytes(bytes(1 << 16))
    code, _, err = run(capsys, *commands(not_mcap, tmp_path)["plot"])
    assert code == 2
    one_line(err, not_mcap, "not an MCAP flight log (bad magic bytes)")
    # A record header claiming 2^62 bytes: nothing is allocated for it, the file reads as cut there.
    raw = flight.path.read_bytes()
    pos = next(pos for op, pos, _ in records(raw) if op == 0x06)  # the first chunk
    huge = tmp_path / "huge.mcap"
    huge.write_bytes(raw[:pos] + struct.pack("<BQ", 0x06, 1 << 62) + bytes(100))
    data = read_log(huge)
    assert data.truncated and data.damage.tail_bytes == 109 and f"incomplete record at byte {pos}" in data.note
    assert data.config == flight.config  # what came before it is read


# --- Damage inside a log: skipped around, counted, and the missing flight time named -------------------


def records(raw: bytes) -> list[tuple[int, int, int]]:
    """(opcode, offset, total length) of each top-level record of an MCAP file."""
    out, pos = [], len(MCAP_MAGIC)
    while pos + 9 <= len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, pos)
        out.append((opcode, pos, 9 + length))
        if opcode == 0x02:  # footer
            break
        pos += 9 + length
    return out


def _chunk_span(raw: bytes | bytearray, pos: int) -> float:
    """Flight time (s) from a chunk's first message to its last, from the chunk record's header."""
    start, end = struct.unpack_from("<QQ", raw, pos + 9)
    return (end - start) * 1e-9


def test_a_corrupt_chunk_is_skipped_and_the_rest_of_the_flight_still_read(flight, tmp_path, capsys):
    raw = bytearray(flight.path.read_bytes())
    chunks = [(pos, n) for op, pos, n in records(bytes(raw)) if op == 0x06]
    assert len(chunks) > 4
    # Chosen by content: of the chunks after the first, the one spanning the most flight time
    # (its header says so), so it holds many states however the machine's load cut the chunks.
    pos, n = max(chunks[1:], key=lambda c: _chunk_span(raw, c[0]))
    start, end = (x * 1e-9 for x in struct.unpack_from("<QQ", raw, pos + 9))
    assert end - start > 0.1
    for k in range(pos + n - 400, pos + n - 300):  # inside the compressed data
        raw[k] ^= 0x5A
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(raw))
    data = read_log(bad)
    damage = data.damage
    assert damage.skipped_records == 1 and damage.skipped_bytes == n and not damage.truncated
    assert damage.gaps == ((start, end),) and damage.missing_from == start
    t = data.times("/state")
    assert t.max() == flight.times("/state").max()  # read on past the damage
    lost = sorted(set(flight.times("/state")) - set(t))  # exactly the states of the bad chunk
    assert len(lost) == flight.count("/state") - data.count("/state") > 10
    assert start <= lost[0] and lost[-1] <= end
    code, out, err = run(capsys, "replay", str(bad), "--json")
    assert code == 0
    report = json.loads(out)["log_damage"]
    assert report["skipped_records"] == 1 and report["skipped_bytes"] == n
    assert report["missing_from_s"] == pytest.approx(start)
    one_line(err, bad, f"1 unreadable record(s) skipped ({n} bytes): flight time {start:.2f}-{end:.2f} s missing")


def test_a_truncated_log_says_how_much_was_skipped_and_from_when(flight, tmp_path, capsys):
    raw = flight.path.read_bytes()
    chunks = [(pos, n) for op, pos, n in records(raw) if op == 0x06]
    pos, n = chunks[len(chunks) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[:pos + n // 2])  # the process killed while writing this chunk
    data = read_log(cut)
    damage = data.damage
    assert damage.truncated and damage.tail_bytes == n // 2 and damage.skipped_bytes == n // 2
    end = max(m["t"] for ms in data.messages.values() for m in ms)
    assert damage.end_t == damage.missing_from == end
    code, out, err = run(capsys, "plot", str(cut), "--out", str(tmp_path / "plots"))
    assert code == 0
    one_line(err, cut, f"cut short (incomplete record at byte {pos}, {n // 2} bytes skipped): "
                       f"nothing after t = {end:.2f} s")


def test_a_chunk_claiming_a_huge_size_is_skipped_not_allocated(flight, tmp_path):
    raw = bytearray(flight.path.read_bytes())
    pos, n = [(pos, n) for op, pos, n in records(bytes(raw)) if op == 0x06][1]
    struct.pack_into("<Q", raw, pos + 9 + 16, 1 << 40)  # uncompressed size
    bad = tmp_path / "bomb.mcap"
    bad.write_bytes(bytes(raw))
    data = read_log(bad)
    assert data.damage.skipped_records == 1 and len(data.damage.gaps) == 1
    assert data.count("/state") > 0.8 * flight.count("/state")


def test_mocap_replay_of_a_log_whose_mocap_is_all_malformed_names_the_file(flight, tmp_path):
    path = rewrite(flight, tmp_path / "mocap.mcap", lambda topic, m: [m["t"]] if topic == "/mocap" else m)
    with pytest.raises(ReplayError, match=r"mocap\.mcap: no usable /mocap messages: all \d+ are malformed"):
        replay_mocap(path)
    assert len(replay_mocap(flight.path)) > 100
