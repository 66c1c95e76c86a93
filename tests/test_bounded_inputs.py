"""Bounded inputs: every file cfknode reads (config, robots, model, log) is a regular file under a
size cap, read header first, parsed within bounds, and quoted short; each hostile case is one line."""

from __future__ import annotations

import dataclasses
import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.opcode import Opcode

from cfknode.app.cli import main
from cfknode.app.config import ConfigError, load_config, parse_override
from cfknode.app.backends.robots import load_robots
from cfknode.app.logs.reader import read_log
from cfknode.app.mission import build_model_slot, run_flight
from cfknode.kernel.bounded_input import MAX_DEPTH, MAX_INT_DIGITS, QUOTE_CHARS, load_json, quote
from cfknode.models.modelfile import FORMAT_NAME, MAX_MODEL_BYTES, ModelFileError, NetworkWeights, load_model, save_model
from fakes import SHORT_FLIGHT
from test_modelfile import make_model, raw_parts, write_raw

BOMB = "\n".join(
    ["vehicle:", "  mass:", '    a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    + [f"    {c}: &{c} [{','.join(['*' + p] * 9)}]" for p, c in zip("abcdefgh", "bcdefghi")]
) + "\n"


def one_line(text: str) -> str:
    assert "\n" not in text.strip() and "Traceback" not in text, text
    return text


# --- quoting and parsing bounds -------------------------------------------------------------------


def test_a_quoted_value_is_cut_short_whatever_it_is():
    deep: list = []
    for _ in range(10_000):
        deep = [deep]
    shared = ["lol"] * 9
    for _ in range(12):  # 9^12 leaves if walked: only the quote's own bounds keep it cheap
        shared = [shared] * 9
    for value in (10**5000, "x" * 100_000, deep, shared, {str(i): i for i in range(10_000)}):
        assert len(quote(value)) <= QUOTE_CHARS + 10
    assert quote(10**4999) == "<an integer of about 4999 digits>"  # counted from its bits: never its repr


def test_json_is_bounded_in_depth_and_integer_size():
    assert load_json('{"a": [1, 2.5, "x"]}', ValueError, "t") == {"a": [1, 2.5, "x"]}
    with pytest.raises(ValueError, match=f"nested deeper than {MAX_DEPTH} levels"):
        load_json("[" * 100_000 + "]" * 100_000, ValueError, "t")
    with pytest.raises(ValueError, match=f"integer of 400 digits \\(at most {MAX_INT_DIGITS}\\)"):
        load_json("9" * 400, ValueError, "t")
    assert load_json('"[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["', ValueError, "t").startswith("[")  # inside a string


# --- config and robots files ------------------------------------------------------------------


def test_a_yaml_alias_bomb_is_one_line(tmp_path):
    path = tmp_path / "bomb.yaml"
    path.write_text(BOMB)
    assert len(BOMB) < 600
    with pytest.raises(ConfigError, match="bomb.yaml is not valid YAML .*aliases are expanded") as err:
        load_config(path)
    one_line(str(err.value))


@pytest.mark.parametrize("digits", [400, 5000])
def test_a_huge_integer_on_the_command_line_is_one_line(tmp_path, capsys, digits):
    code = main(["fly", "--headless", "--log-dir", str(tmp_path), "--set", f"vehicle.mass={'9' * digits}"])
    err = capsys.readouterr().err
    assert code == 2
    line = one_line(err).strip()
    assert line.startswith("cfknode: error: --set vehicle.mass: cannot parse value")
    assert f"an integer of {digits} digits" in line and len(line) < 300


def test_a_value_in_a_config_message_is_quoted_short(tmp_path):
    path = tmp_path / "long.yaml"
    path.write_text("vehicle:\n  mass: " + json.dumps(["x" * 500] * 50) + "\n")
    with pytest.raises(ConfigError, match="vehicle.mass' must be a number") as err:
        load_config(path)
    assert len(one_line(str(err.value))) < 200
    with pytest.raises(ConfigError, match="cannot parse value"):
        parse_override("a=[" * 50 + "]" * 50)


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "oversized"])
def test_config_and_robots_files_must_be_small_regular_files(tmp_path, kind):
    path = tmp_path / "in.yaml"
    if kind == "fifo":
        os.mkfifo(path)  # reading would block until a writer came
    elif kind == "dev_zero":
        path.symlink_to("/dev/zero")  # reading would never end
    else:
        path.write_text("vehicle:\n  mass: 0.03\n" + "#" * (2 << 20))
    expected = {"fifo": "a FIFO, not a regular file", "dev_zero": "a character device, not a regular file",
                "oversized": "is larger than the cap of 1 MiB"}[kind]
    for read in (load_config, load_robots):
        with pytest.raises(ConfigError, match=expected) as err:
            read(path)
        one_line(str(err.value))


# --- model files ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["fifo", "dev_zero"])
def test_a_model_that_is_not_a_regular_file_is_refused_unread(tmp_path, kind):
    path = tmp_path / "m.ckpt"
    os.mkfifo(path) if kind == "fifo" else path.symlink_to("/dev/zero")
    with pytest.raises(ModelFileError, match="a FIFO|a character device") as err:
        load_model(path)
    one_line(str(err.value))


def test_a_sparse_model_is_refused_by_its_size_or_its_header(tmp_path):
    huge = tmp_path / "huge.ckpt"
    with open(huge, "wb") as f:
        f.truncate(2 << 30)  # sparse: 2 GiB of zeros, no disk used
    with pytest.raises(ModelFileError, match="2 GiB is larger than the cap of 512 MiB"):
        load_model(huge)
    below = tmp_path / "below.ckpt"
    with open(below, "wb") as f:
        f.truncate(MAX_MODEL_BYTES - 1)
    # Under the cap, its 8-byte header (length 0) refuses it; the body is never read.
    with pytest.raises(ModelFileError, match="header length 0"):
        load_model(below)


def _with_meta(tmp_path: Path, change) -> Path:
    good = save_model(tmp_path / "good.safetensors", make_model())
    tensors, meta = raw_parts(good)
    change(meta)
    return write_raw(tmp_path / "bad.safetensors", tensors, meta)


def _nest(meta: dict) -> None:
    deep: object = 1
    for _ in range(500):
        deep = {"k": deep}
    meta["extra"] = deep


@pytest.mark.parametrize("change", [
    lambda m: m.update(queue_weights=[{"a": 1}] * len(m["queue_weights"])),
    lambda m: m.update(queue_weights=[10**39] * len(m["queue_weights"])),
    lambda m: m.update(queue_size=int("9" * 400)),
    lambda m: m["architecture"].update(hidden=["16", 8]),
    lambda m: m["networks"][0].update(input_mean=[[1, 2]] * 6),
    lambda m: m["training"].update(epochs={"a": 1}),
    _nest,
], ids=["queue_weights_objects", "queue_weights_huge", "queue_size_400_digits", "hidden_strings",
        "input_mean_nested", "epochs_object", "extra_500_deep"])
def test_model_metadata_of_wrong_types_or_bounds_is_one_line(tmp_path, change):
    path = _with_meta(tmp_path, change)
    with pytest.raises(ModelFileError, match="bad.safetensors") as err:
        load_model(path)
    one_line(str(err.value))


def test_a_finite_but_absurd_model_is_refused_before_take_off(tmp_path):
    model = make_model(n_nets=1)
    good = save_model(tmp_path / "good.safetensors", model)
    net = model.networks[0]
    w, b = net.layers[-1]
    absurd = dataclasses.replace(model, networks=(NetworkWeights((*net.layers[:-1], (w * 1e300, b * 1e300)),
                                                                 net.normalisation),))
    bad = save_model(tmp_path / "absurd.safetensors", absurd)
    assert np.all(np.isfinite(load_model(bad).networks[0].layers[-1][0]))  # finite, so the file itself is valid
    over = {"controller.kind": "knode-mpc", "log.dir": str(tmp_path)}
    assert build_model_slot(load_config(overrides={**over, "controller.model": str(good)})) is not None
    cfg = load_config(overrides={**over, "controller.model": str(bad)})
    with pytest.raises(ConfigError, match=r"absurd.safetensors: implausible .*exceeds knode.max_residual") as err:
        run_flight(cfg)
    one_line(str(err.value))
    assert not list(tmp_path.glob("*.mcap")), "no flight log: the flight never started"


def test_a_model_without_the_format_tag_is_still_named(tmp_path):
    tensors, meta = raw_parts(save_model(tmp_path / "g.safetensors", make_model()))
    path = write_raw(tmp_path / "other.safetensors", tensors, meta, fmt=FORMAT_NAME + "x")
    with pytest.raises(ModelFileError, match="other.safetensors: not a cfknode KNODE model"):
        load_model(path)


# --- flight logs ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("flight")
    cfg = load_config(overrides={**SHORT_FLIGHT, "log.dir": str(d), "safety.estop_dir": str(d / "estop")})
    return Path(run_flight(cfg, name_hint="ok").summary.log_path)


def _first_metadata(raw: bytes) -> int:
    pos = 8
    while True:
        op, length = struct.unpack_from("<BQ", raw, pos)
        if op == Opcode.METADATA:
            return pos
        pos += 9 + length


@pytest.mark.parametrize("where", ["map_length", "record_length"])
def test_a_damaged_first_metadata_record_is_one_line_or_read_around(flight_log, tmp_path, capsys, where):
    raw = bytearray(flight_log.read_bytes())
    pos = _first_metadata(raw)
    if where == "map_length":  # the metadata map's byte length, after the name
        (name_len,) = struct.unpack_from("<I", raw, pos + 9)
        struct.pack_into("<I", raw, pos + 9 + 4 + name_len, 0xFFFFFFF0)
    else:  # the record's own length: the records after it are out of step
        struct.pack_into("<Q", raw, pos + 1, 5)
    path = tmp_path / f"{where}.mcap"
    path.write_bytes(bytes(raw))
    if where == "map_length":
        data = read_log(path)
        assert data.config is not None and any("unreadable record" in w for w in data.damage.warnings)
    argvs = [["plot", str(path), "--out", str(tmp_path / "plots")], ["replay", str(path), "--json"],
             ["train", "--log", str(path), "--out", str(tmp_path / "m.safetensors"), "--epochs", "2"]]
    for argv in argvs:
        code = main(argv)
        out, err = capsys.readouterr()
        assert "Traceback" not in out + err, (argv, err)
        errors = [line for line in err.splitlines() if line.startswith("cfknode: error")]
        assert (code, len(errors)) in ((0, 0), (2, 1)), (argv, code, err)


def test_a_log_that_is_a_link_to_a_device_is_refused(tmp_path):
    path = tmp_path / "zero.mcap"
    path.symlink_to("/dev/zero")
    with pytest.raises(Exception, match="a character device, not a regular file") as err:
        read_log(path)
    one_line(str(err.value))
