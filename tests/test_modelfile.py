"""KNODE model files: round trip, atomic writes, and every kind of bad file -> ModelFileError."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import save

import cfknode
from cfknode.models.modelfile import (
    FORMAT_NAME,
    FORMAT_VERSION,
    ModelFile,
    ModelFileError,
    NetworkWeights,
    Normalisation,
    TrainingInfo,
    load_model,
    model_summary,
    save_model,
)


def make_model(n_nets: int = 3, hidden: tuple[int, ...] = (16, 8), seed: int = 0) -> ModelFile:
    rng = np.random.default_rng(seed)
    sizes = [6, *hidden, 3]
    nets = []
    for _ in range(n_nets):
        layers = tuple((rng.normal(size=(b, a)), rng.normal(size=b)) for a, b in zip(sizes[:-1], sizes[1:]))
        norm = Normalisation(rng.normal(size=6), rng.uniform(0.5, 2.0, 6), rng.uniform(0.5, 2.0, 3))
        nets.append(NetworkWeights(layers, norm))
    info = TrainingInfo(t0=1.5, t1=31.25, sources=("flight_001.mcap", "flight_002.mcap"), loss=0.0123,
                        val_rmse_nominal=0.0042, val_rmse_model=0.0011, epochs=400, wall_time=2.5)
    return ModelFile(hidden=hidden, activation="tanh", queue_size=3, networks=tuple(nets), training=info,
                     extra={"model_version": 7, "window": [2.0, 2.15]})


def raw_parts(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    from safetensors.numpy import load

    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    return load(data), json.loads(header["__metadata__"]["cfknode"])


def write_raw(path: Path, tensors: dict[str, np.ndarray], meta: dict, fmt: str = FORMAT_NAME) -> Path:
    path.write_bytes(save(tensors, metadata={"format": fmt, "cfknode": json.dumps(meta)}))
    return path


def assert_error(path: Path, match: str) -> None:
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg, msg
    assert match in msg, msg


def test_round_trip(tmp_path: Path) -> None:
    model = make_model()
    path = save_model(tmp_path / "sub" / "model.safetensors", model)
    back = load_model(path)
    assert (back.hidden, back.activation, back.queue_size) == (model.hidden, model.activation, model.queue_size)
    assert back.training == model.training
    assert dict(back.extra) == {"model_version": 7, "window": [2.0, 2.15]}
    assert back.software_version == cfknode.__version__
    assert back.created.endswith("+00:00")
    np.testing.assert_array_equal(back.queue_weights, np.exp([-2.0, -1.0, 0.0]))
    for a, b in zip(model.networks, back.networks):
        for (wa, ba), (wb, bb) in zip(a.layers, b.layers):
            np.testing.assert_array_equal(wa, wb)
            np.testing.assert_array_equal(ba, bb)
        for key in ("input_mean", "input_scale", "output_scale"):
            np.testing.assert_array_equal(getattr(a.normalisation, key), getattr(b.normalisation, key))
    assert "3/3 nets" in model_summary(back)


def test_metadata_holds_what_the_design_lists(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    tensors, meta = raw_parts(path)
    assert meta["format_version"] == FORMAT_VERSION
    assert meta["architecture"]["inputs"] == ["vx", "vy", "vz", "ax", "ay", "az"]
    assert meta["architecture"]["outputs"] == ["dvx", "dvy", "dvz"]
    assert meta["architecture"]["hidden"] == [16, 8] and meta["architecture"]["activation"] == "tanh"
    assert len(meta["networks"]) == 3 and set(meta["networks"][0]) == {"input_mean", "input_scale", "output_scale"}
    assert meta["training"]["sources"] == ["flight_001.mcap", "flight_002.mcap"]
    assert {"software_version", "created", "queue_weights"} <= set(meta)
    assert sorted(tensors) == sorted(f"net{j}.layer{i}.{k}" for j in range(3) for i in range(3) for k in ("weight", "bias"))


def test_empty_queue_and_no_training_round_trip(tmp_path: Path) -> None:
    model = ModelFile(hidden=(8,), activation="relu", queue_size=2, networks=())
    back = load_model(save_model(tmp_path / "empty.safetensors", model))
    assert back.networks == () and back.training is None and back.queue_weights.shape == (0,)


def test_save_is_atomic_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "m.safetensors"
    save_model(path, make_model(seed=1))
    save_model(path, make_model(seed=2))
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"]  # no temp file left
    np.testing.assert_array_equal(load_model(path).networks[0].layers[0][0], make_model(seed=2).networks[0].layers[0][0])


def test_save_refuses_bad_models_and_leaves_the_old_file(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model(seed=1))
    good = path.read_bytes()
    model = make_model()
    w, b = model.networks[1].layers[0]
    w = w.copy()
    w[0, 0] = np.nan
    bad_net = NetworkWeights((( w, b), *model.networks[1].layers[1:]), model.networks[1].normalisation)
    bad = ModelFile(model.hidden, model.activation, model.queue_size, (model.networks[0], bad_net, model.networks[2]))
    with pytest.raises(ModelFileError, match="non-finite"):
        save_model(path, bad)
    too_many = ModelFile(model.hidden, model.activation, 2, model.networks)
    with pytest.raises(ModelFileError, match="exceed queue_size"):
        save_model(path, too_many)
    assert path.read_bytes() == good
    assert len(list(tmp_path.iterdir())) == 1


def test_missing_file(tmp_path: Path) -> None:
    assert_error(tmp_path / "nope.safetensors", "not found")


def test_truncated(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    data = path.read_bytes()
    for keep in (len(data) - 7, len(data) // 2, 100):
        path.write_bytes(data[:keep])
        assert_error(path, "truncated")
    path.write_bytes(data[:5])
    assert_error(path, "too short")


def test_corrupt_header_bytes(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    data = bytearray(path.read_bytes())
    data[20:40] = b"\xff" * 20
    path.write_bytes(bytes(data))
    assert_error(path, "not a safetensors file")


def test_corrupt_length_field(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    data = bytearray(path.read_bytes())
    data[0:8] = (10**12).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    assert_error(path, "header length")


def test_tensor_offsets_out_of_range(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    data = path.read_bytes()
    path.write_bytes(data + b"\x00" * 16)  # trailing bytes the header does not cover
    assert_error(path, "corrupt safetensors data")


def test_not_safetensors(tmp_path: Path) -> None:
    path = tmp_path / "notes.safetensors"
    path.write_text("this is a text file, not a model, and it is long enough to have eight bytes\n")
    assert_error(path, "not a safetensors file")


def test_other_safetensors_file(tmp_path: Path) -> None:
    path = tmp_path / "other.safetensors"
    path.write_bytes(save({"w": np.zeros((2, 2))}))
    assert_error(path, "not a cfknode KNODE model")


def test_pickle_is_never_unpickled(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):  # what a malicious pickle would run on load
            return (Path.touch, (marker,))

    path = tmp_path / "model.safetensors"
    path.write_bytes(pickle.dumps(Payload()))
    with pytest.raises(ModelFileError):
        load_model(path)
    assert not marker.exists()


def test_shape_mismatch_with_metadata(tmp_path: Path) -> None:
    good = save_model(tmp_path / "good.safetensors", make_model(hidden=(16, 8)))
    tensors, meta = raw_parts(good)
    meta["architecture"]["hidden"] = [16, 9]
    assert_error(write_raw(tmp_path / "hidden.safetensors", tensors, meta), "the architecture says (9, 16)")
    tensors2 = dict(tensors)
    tensors2["net1.layer2.bias"] = np.zeros(4)
    _, meta2 = raw_parts(good)
    assert_error(write_raw(tmp_path / "bias.safetensors", tensors2, meta2), "net1.layer2.bias")
    tensors3 = dict(tensors)
    del tensors3["net2.layer1.weight"]
    assert_error(write_raw(tmp_path / "missing.safetensors", tensors3, meta2), "'net2.layer1.weight' is missing")
    tensors4 = dict(tensors, **{"net3.layer0.weight": np.zeros((16, 6))})
    assert_error(write_raw(tmp_path / "extra.safetensors", tensors4, meta2), "not in the architecture")
    meta5 = dict(meta2, networks=meta2["networks"][:2], queue_weights=[float(np.exp(-1)), 1.0])
    assert_error(write_raw(tmp_path / "count.safetensors", tensors, meta5), "not in the architecture")


def test_non_finite_weights_and_normalisation(tmp_path: Path) -> None:
    good = save_model(tmp_path / "good.safetensors", make_model())
    tensors, meta = raw_parts(good)
    bad = dict(tensors)
    bad["net0.layer1.weight"] = bad["net0.layer1.weight"].copy()
    bad["net0.layer1.weight"][3, 2] = np.nan
    assert_error(write_raw(tmp_path / "nan.safetensors", bad, meta), "non-finite weights")
    bad["net0.layer1.weight"][3, 2] = np.inf
    assert_error(write_raw(tmp_path / "inf.safetensors", bad, meta), "non-finite weights")
    meta2 = json.loads(json.dumps(meta))
    meta2["networks"][1]["input_scale"][0] = 0.0
    assert_error(write_raw(tmp_path / "scale.safetensors", tensors, meta2), "non-positive scale")
    path = tmp_path / "nanmeta.safetensors"
    text = json.dumps(meta).replace('"loss": 0.0123', '"loss": NaN')
    path.write_bytes(save(tensors, metadata={"format": FORMAT_NAME, "cfknode": text}))
    assert_error(path, "training.loss is not finite")


def test_integer_tensor_is_rejected(tmp_path: Path) -> None:
    tensors, meta = raw_parts(save_model(tmp_path / "good.safetensors", make_model()))
    tensors["net0.layer0.bias"] = np.zeros(16, dtype=np.int64)
    assert_error(write_raw(tmp_path / "int.safetensors", tensors, meta), "expected floating point")


@pytest.mark.parametrize(
    "drop",
    ["format_version", "queue_size", "networks", "queue_weights", "training", "software_version", "created",
     "architecture", "architecture.hidden", "architecture.activation", "networks[0].output_scale", "training.val_rmse_model"],
)
def test_missing_metadata_keys(tmp_path: Path, drop: str) -> None:
    tensors, meta = raw_parts(save_model(tmp_path / "good.safetensors", make_model()))
    if "[0]." in drop:
        del meta["networks"][0][drop.split(".")[1]]
    elif "." in drop:
        outer, inner = drop.split(".")
        del meta[outer][inner]
    else:
        del meta[drop]
    assert_error(write_raw(tmp_path / "bad.safetensors", tensors, meta), f"'{drop}' is missing")


def test_wrong_format_version(tmp_path: Path) -> None:
    tensors, meta = raw_parts(save_model(tmp_path / "good.safetensors", make_model()))
    meta["format_version"] = FORMAT_VERSION + 1
    assert_error(write_raw(tmp_path / "v2.safetensors", tensors, meta), "format version")


def test_wrong_layout_activation_and_weights(tmp_path: Path) -> None:
    tensors, meta = raw_parts(save_model(tmp_path / "good.safetensors", make_model()))
    m1 = json.loads(json.dumps(meta))
    m1["architecture"]["inputs"] = ["px", "py", "pz", "ax", "ay", "az"]
    assert_error(write_raw(tmp_path / "layout.safetensors", tensors, m1), "input/output layout")
    m2 = json.loads(json.dumps(meta))
    m2["architecture"]["activation"] = "sigmoid"
    assert_error(write_raw(tmp_path / "act.safetensors", tensors, m2), "unknown activation")
    m3 = json.loads(json.dumps(meta))
    m3["queue_weights"] = [1.0, 1.0, 1.0]
    assert_error(write_raw(tmp_path / "qw.safetensors", tensors, m3), "queue_weights")
    path = tmp_path / "json.safetensors"
    path.write_bytes(save(tensors, metadata={"format": FORMAT_NAME, "cfknode": "{not json"}))
    assert_error(path, "not valid JSON")


def test_loading_imports_no_torch(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.safetensors", make_model())
    code = (
        "import sys\n"
        "from cfknode.models.modelfile import load_model\n"
        f"m = load_model({str(path)!r})\n"
        "assert len(m.networks) == 3\n"
        "print('TORCH' if any(k == 'torch' or k.startswith('torch.') for k in sys.modules) else 'CLEAN')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "CLEAN"
