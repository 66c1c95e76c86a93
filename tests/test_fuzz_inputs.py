"""Property-based fuzzing of every reader of a given file: the config loader, the model-file
reader, the log reader and the mailbox parser. No input may give anything but the reader's
one-line error type (or a valid result).

The default profile runs a few dozen examples per reader (seconds). ``CFKNODE_FUZZ=long``
selects a long run (20,000 examples per reader, or ``CFKNODE_FUZZ_EXAMPLES``, with a 5 s
deadline per example so a hang fails).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cfknode.app.config import ConfigError, default_dict, load_config, parse_override
from cfknode.app.logs.format import LogError
from cfknode.app.logs.reader import read_log
from cfknode.models.modelfile import ModelFileError, load_model, save_model
from cfknode.safety.estop_mailbox import ACTIONS, EstopMailbox, scan_flights
from synthetic_log import write_synthetic_flight
from test_modelfile import make_model

_QUIET = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture]
_PROFILES = {
    "ci": settings(max_examples=25, deadline=None, database=None, suppress_health_check=_QUIET),
    "long": settings(max_examples=int(os.environ.get("CFKNODE_FUZZ_EXAMPLES", "20000")), deadline=5000, database=None,
                     suppress_health_check=_QUIET),
}
FUZZ = _PROFILES["long" if os.environ.get("CFKNODE_FUZZ") == "long" else "ci"]

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
YAML_TEXT = st.text(alphabet=st.sampled_from(list("abz019.:-[]{},&*!|>#'\"\n ?%@`~")), max_size=200)


def _mutations(base: bytes) -> st.SearchStrategy[bytes]:
    """``base`` with a few bytes changed, cut short, or a slice repeated: damage near the real format."""
    n = len(base)
    flips = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8).map(
        lambda changes: _flip(base, changes))
    cuts = st.integers(0, n).map(lambda k: base[:k])
    header = st.tuples(st.integers(0, min(n - 1, 64)), st.binary(min_size=1, max_size=8)).map(
        lambda c: base[:c[0]] + c[1] + base[c[0] + len(c[1]):])
    return st.one_of(flips, cuts, header, st.binary(max_size=256))


def _flip(base: bytes, changes: list[tuple[int, int]]) -> bytes:
    out = bytearray(base)
    for at, value in changes:
        out[at] = value
    return bytes(out)


def _read_or_one_line(read, path: Path, error: type[Exception]) -> None:
    """``read(path)`` gives a result or ``error`` with a one-line message; anything else fails."""
    try:
        read(path)
    except error as exc:
        assert "\n" not in str(exc)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# --- config -----------------------------------------------------------------------------------

def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


KEYS = sorted(_flat(default_dict()))


@FUZZ
@given(text=YAML_TEXT | st.text(max_size=200))
def test_config_files_give_a_config_or_one_config_error(work, text):
    path = work / "config.yaml"
    path.write_text(text, errors="surrogateescape")
    _read_or_one_line(load_config, path, ConfigError)


@FUZZ
@given(key=st.sampled_from(KEYS), value=JSON | YAML_TEXT)
def test_overrides_give_a_config_or_one_config_error(key, value):
    try:
        if isinstance(value, str):
            key, value = parse_override(f"{key}={value}")
        load_config(overrides={key: value})
    except ConfigError as exc:
        assert "\n" not in str(exc) and len(str(exc)) < 600


# --- model files and logs ------------------------------------------------------------------


@pytest.fixture(scope="module")
def model_bytes(work) -> bytes:
    return save_model(work / "base.safetensors", make_model(n_nets=2, hidden=(4,))).read_bytes()


@FUZZ
@given(meta=JSON, key=st.sampled_from(["queue_weights", "networks", "architecture", "training", "queue_size", "extra"]))
def test_model_metadata_gives_a_model_or_one_model_file_error(work, model_bytes, meta, key):
    from safetensors.numpy import load, save

    n = int.from_bytes(model_bytes[:8], "little")
    header = json.loads(model_bytes[8:8 + n])
    cfknode_meta = json.loads(header["__metadata__"]["cfknode"])
    cfknode_meta[key] = meta
    path = work / "meta.safetensors"
    path.write_bytes(save(load(model_bytes), metadata={**header["__metadata__"], "cfknode": json.dumps(cfknode_meta)}))
    _read_or_one_line(load_model, path, ModelFileError)


@pytest.fixture(scope="module")
def log_bytes(work) -> bytes:
    return write_synthetic_flight(work / "logs", 0.1).read_bytes()


@FUZZ
@given(data=st.data())
def test_damaged_models_and_logs_give_a_result_or_one_error(work, model_bytes, log_bytes, data):
    for base, name, read, error in ((model_bytes, "model.safetensors", load_model, ModelFileError),
                                    (log_bytes, "log.mcap", read_log, LogError)):
        path = work / name
        path.write_bytes(data.draw(_mutations(base)))
        _read_or_one_line(read, path, error)


# --- the e-stop mailbox -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def mailbox(work):
    box = EstopMailbox(work / "estop", "sim-cf1")
    box.open()
    yield box
    box.close()


@FUZZ
@given(body=JSON.map(json.dumps).map(str.encode) | st.binary(max_size=300))
def test_presence_files_are_flights_or_skipped_never_an_error(mailbox, body):
    planted = mailbox.directory / f"flight-sim-cf2-{os.getpid()}-0badf00d.json"
    planted.write_bytes(body)
    scan = scan_flights(mailbox.directory)
    assert mailbox.id in [f.id for f in scan.flights]
    assert all("\n" not in line for line in scan.skipped)


@FUZZ
@given(body=JSON.map(json.dumps).map(str.encode) | st.binary(max_size=300))
def test_requests_are_an_action_whatever_they_hold(mailbox, body):
    mailbox.request_path.write_bytes(body)
    got = mailbox.poll()
    assert got is not None and got.action in ACTIONS and not mailbox.request_path.exists()
