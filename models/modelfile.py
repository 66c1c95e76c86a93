"""KNODE model files: one safetensors file, weights as tensors, everything else as JSON metadata.

Loading uses numpy only (``safetensors.numpy``): no torch import and no unpickling, so the
flight process can read a model the trainer wrote.  Every problem with a file (corrupt,
truncated, not safetensors, shapes that disagree with the metadata, non-finite numbers,
missing keys, another format version) raises ``ModelFileError`` with a one-line message
naming the file.

Layout (format version 1):
- tensors ``net{j}.layer{i}.weight`` (out, in) and ``net{j}.layer{i}.bias`` (out,), float64,
  for network j = 0 (oldest) .. n-1 (newest) and layer i = 0 .. len(hidden);
- header metadata ``{"format": "cfknode.knode", "cfknode": <JSON>}``; the JSON holds the
  format version, architecture, per-network normalisation, queue weights, training
  provenance and metrics, software version, creation time and free-form ``extra``.

A network maps the raw input z = (vx, vy, vz, ax, ay, az) to a residual on v' (m/s^2), or in a fleet with
``fleet.neighbour_input`` z = (v, a, nbx, nby, nbz), the last three the relative position of the nearest
drone above (``NEIGHBOUR_INPUT_NAMES``; ``architecture.inputs`` records which, docs/fleet.md#neighbour-input), or
for a wake network (``fleet.wake_only``) z = (v, a, nbr, nb0, nbz), its horizontal distance, 0 and its height:
r = output_scale * MLP((z - input_mean) / input_scale); the queue's residual is
sum_j w_j r_j with w_j = e^(j + 1 - n) (newest 1, then e^-1, e^-2, ...).
"""

from __future__ import annotations

import json
import math
import os
import struct
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from cfknode.kernel.bounded_input import describe_os_error, load_json, open_regular
from cfknode.kernel.outputs import output_problem
from cfknode.models.input_bounds import BOUNDS_KEY, bounds_problem
from cfknode.models.input_layouts import (  # noqa: F401 (re-exported: readers name the layouts here)
    INPUT_LAYOUTS, INPUT_NAMES, N_IN, NEIGHBOUR_INPUT_NAMES, NEIGHBOUR_NAMES, WAKE_INPUT_NAMES, WAKE_NAMES,
)
from cfknode.models.residual_check import SCORE_KEY, score_problem

FORMAT_NAME = "cfknode.knode"
FORMAT_VERSION = 1
OUTPUT_NAMES = ("dvx", "dvy", "dvz")
ACTIVATIONS = ("tanh", "softplus", "relu")
# An input scale this large switches the input off ((z - m) / s ~ 1e-9), its inverse as an output scale the output.
MASKED_INPUT_SCALE = 1e9
N_OUT = len(OUTPUT_NAMES)

# A header larger than this is not one of ours (ours are a few kB): refuse before parsing it.
_MAX_HEADER_BYTES = 16 * 1024 * 1024
# A queue of 10 networks with two 1024-wide hidden layers is about 90 MB; the cap leaves room.
MAX_MODEL_BYTES = 512 << 20


class ModelFileError(ValueError):
    """A model file that cannot be used, with a one-line message naming the file."""


@dataclass(frozen=True)
class Normalisation:
    """Affine maps around one network: z_n = (z - input_mean) / input_scale, r = output_scale * y."""

    input_mean: np.ndarray  # (6,)
    input_scale: np.ndarray  # (6,), > 0
    output_scale: np.ndarray  # (3,), > 0

    @classmethod
    def identity(cls, n_in: int = N_IN) -> Normalisation:
        return cls(np.zeros(n_in), np.ones(n_in), np.ones(N_OUT))

    def to_json(self) -> dict[str, list[float]]:
        return {k: [float(v) for v in getattr(self, k)] for k in ("input_mean", "input_scale", "output_scale")}

    @property
    def wake_only(self) -> bool:
        """The drone's own inputs switched off: a network of the neighbour's position alone (``fleet.wake_only``)."""
        return len(self.input_scale) > N_IN and bool(np.all(self.input_scale[:N_IN] >= MASKED_INPUT_SCALE))


@dataclass(frozen=True)
class NetworkWeights:
    """One residual MLP: ``layers[i] = (W (out, in), b (out,))``, hidden layers first, then the output layer."""

    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    normalisation: Normalisation


@dataclass(frozen=True)
class TrainingInfo:
    """Where the newest network's training data came from and how well it fits."""

    t0: float  # s, first sample used (flight clock of the source)
    t1: float  # s, last sample used
    sources: tuple[str, ...]  # log files (or window ids) the data came from
    loss: float  # final data loss of the newest network, (m/s^2)^2
    val_rmse_nominal: float  # held-out one-step velocity RMSE of the nominal model, m/s
    val_rmse_model: float  # the same for the nominal + residual queue, m/s
    epochs: int
    wall_time: float  # s spent training

    def to_json(self) -> dict[str, Any]:
        return {
            "t0": float(self.t0),
            "t1": float(self.t1),
            "sources": list(self.sources),
            "loss": float(self.loss),
            "val_rmse_nominal": float(self.val_rmse_nominal),
            "val_rmse_model": float(self.val_rmse_model),
            "epochs": int(self.epochs),
            "wall_time": float(self.wall_time),
        }


@dataclass(frozen=True)
class ModelFile:
    """A network queue with its metadata, as numpy arrays (oldest network first)."""

    hidden: tuple[int, ...]
    activation: str
    queue_size: int
    networks: tuple[NetworkWeights, ...]
    training: TrainingInfo | None = None
    software_version: str = ""
    created: str = ""  # ISO 8601 UTC; filled by save_model when empty
    extra: Mapping[str, Any] = field(default_factory=dict)  # JSON-serialisable, e.g. the online model version
    inputs: tuple[str, ...] = INPUT_NAMES  # or NEIGHBOUR_INPUT_NAMES, WAKE_INPUT_NAMES: the networks' input layout

    @property
    def takes_neighbour(self) -> bool:
        """Whether the networks take the neighbour's relative position (a fleet's ``fleet.neighbour_input``)."""
        return len(self.inputs) > N_IN

    @property
    def queue_weights(self) -> np.ndarray:
        return queue_weights(len(self.networks))


def queue_weights(n: int) -> np.ndarray:
    """Forgetting weights w_k = e^(k - n), k = 1..n, newest (last) = 1 (the paper's recursion)."""
    return np.exp(np.arange(1, n + 1, dtype=np.float64) - n)


def save_model(path: str | Path, model: ModelFile) -> Path:
    """Write ``model`` to ``path`` atomically: temp file in the same directory, fsync, ``os.replace``."""
    path = Path(path)
    problem = output_problem(path)
    if problem is not None:
        raise ModelFileError(f"model file {problem}")
    _check_model(model, str(path))
    tensors: dict[str, np.ndarray] = {}
    for j, net in enumerate(model.networks):
        for i, (w, b) in enumerate(net.layers):
            tensors[f"net{j}.layer{i}.weight"] = np.ascontiguousarray(w, dtype=np.float64)
            tensors[f"net{j}.layer{i}.bias"] = np.ascontiguousarray(b, dtype=np.float64)
    created = model.created or datetime.now(timezone.utc).isoformat(timespec="seconds")
    meta = {
        "format_version": FORMAT_VERSION,
        "architecture": {
            "hidden": list(model.hidden),
            "activation": model.activation,
            "inputs": list(model.inputs),
            "outputs": list(OUTPUT_NAMES),
        },
        "queue_size": model.queue_size,
        "networks": [net.normalisation.to_json() for net in model.networks],
        "queue_weights": [float(w) for w in model.queue_weights],
        "training": None if model.training is None else model.training.to_json(),
        "software_version": model.software_version or _software_version(),
        "created": created,
        "extra": dict(model.extra),
    }
    from safetensors.numpy import save

    # allow_nan=False: metrics must be finite; a NaN here is a bug upstream, not a file to write.
    blob = save(tensors, metadata={"format": FORMAT_NAME, "cfknode": json.dumps(meta, allow_nan=False)})
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        problem = output_problem(path)  # again: the target may have changed while the blob was written
        if problem is not None:
            raise ModelFileError(f"model file {problem}")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def load_model(path: str | Path) -> ModelFile:
    """Read and validate a model file (numpy only, never unpickles); raises ``ModelFileError``.

    The 8-byte header length and the header are read and checked before the tensors, so a
    file that is not one of ours is refused without reading its body."""
    path = Path(path)
    name = str(path)
    f, size = open_regular(path, MAX_MODEL_BYTES, ModelFileError, "model file")
    with f:
        try:
            head = f.read(8)
            n = _header_length(head, size, name)
            header_bytes = f.read(n)
            header = _read_header(header_bytes, n, size, name)
            meta = _metadata(header, name)
            body = f.read(size - 8 - n)
        except OSError as exc:
            raise ModelFileError(f"model file {name}: cannot read ({describe_os_error(exc)})") from None
    from safetensors.numpy import load

    try:
        tensors = load(head + header_bytes + body)
    except Exception as exc:  # safetensors raises its own error type for malformed buffers
        raise ModelFileError(f"model file {name}: corrupt safetensors data ({_one_line(exc)[:120]})") from None
    try:
        model = _model_from(meta, tensors, name)
    except ModelFileError:
        raise
    except (TypeError, ValueError, OverflowError, AttributeError, KeyError, IndexError):
        raise ModelFileError(f"model file {name}: metadata has a value of the wrong type") from None
    _check_model(model, name)
    return model


def _header_length(head: bytes, size: int, name: str) -> int:
    if len(head) < 8:
        raise ModelFileError(f"model file {name}: too short to be a safetensors file ({size} bytes)")
    (n,) = struct.unpack("<Q", head)
    if n == 0 or n > _MAX_HEADER_BYTES or 8 + n > size:
        raise ModelFileError(f"model file {name}: not a safetensors file or truncated (header length {n}, file {size} bytes)")
    return n


def _read_header(raw: bytes, n: int, size: int, name: str) -> dict[str, Any]:
    # Parse the header ourselves so a wrong file gets a precise message before any tensor is read.
    if len(raw) < n:
        raise ModelFileError(f"model file {name}: truncated while reading its header")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ModelFileError(f"model file {name}: not a safetensors file (header is not JSON)") from None
    header = load_json(text, ModelFileError, f"model file {name}: not a safetensors file (header)")
    if not isinstance(header, dict):
        raise ModelFileError(f"model file {name}: not a safetensors file (header is not a JSON object)")
    ends = [
        entry["data_offsets"][1]
        for key, entry in header.items()
        if key != "__metadata__" and isinstance(entry, dict) and isinstance(entry.get("data_offsets"), list)
        and len(entry["data_offsets"]) == 2 and isinstance(entry["data_offsets"][1], int)
    ]
    expected = 8 + n + max(ends, default=0)
    if expected > size:
        raise ModelFileError(f"model file {name}: truncated ({size} bytes, the header describes {expected})")
    return header


def _metadata(header: Mapping[str, Any], name: str) -> dict[str, Any]:
    raw_meta = header.get("__metadata__")
    if not isinstance(raw_meta, dict) or raw_meta.get("format") != FORMAT_NAME:
        raise ModelFileError(f"model file {name}: not a cfknode KNODE model (no '{FORMAT_NAME}' format tag)")
    text = raw_meta.get("cfknode", "")
    if not isinstance(text, str):
        raise ModelFileError(f"model file {name}: metadata is not valid JSON")
    meta = load_json(text, ModelFileError, f"model file {name}: metadata")
    if not isinstance(meta, dict):
        raise ModelFileError(f"model file {name}: metadata must be a JSON object")
    return meta


def _model_from(meta: Mapping[str, Any], tensors: Mapping[str, np.ndarray], name: str) -> ModelFile:
    def need(obj: Mapping[str, Any], key: str, where: str = "") -> Any:
        if not isinstance(obj, Mapping) or key not in obj:
            raise ModelFileError(f"model file {name}: metadata key '{where}{key}' is missing")
        return obj[key]

    version = need(meta, "format_version")
    if version != FORMAT_VERSION:
        raise ModelFileError(f"model file {name}: format version {version!r} is not supported (this build reads {FORMAT_VERSION})")
    arch = need(meta, "architecture")
    hidden = need(arch, "hidden", "architecture.")
    activation = need(arch, "activation", "architecture.")
    if not isinstance(hidden, list) or not hidden or not all(isinstance(h, int) and h > 0 for h in hidden):
        raise ModelFileError(f"model file {name}: architecture.hidden must be a non-empty list of positive integers")
    if activation not in ACTIVATIONS:
        raise ModelFileError(f"model file {name}: unknown activation {activation!r}")
    inputs, outputs = need(arch, "inputs", "architecture."), need(arch, "outputs", "architecture.")
    if not isinstance(inputs, list) or not isinstance(outputs, list) or tuple(inputs) not in INPUT_LAYOUTS \
            or tuple(outputs) != OUTPUT_NAMES:
        raise ModelFileError(f"model file {name}: input/output layout differs from {INPUT_NAMES} (or with "
                             f"{NEIGHBOUR_NAMES} or {WAKE_NAMES}) -> {OUTPUT_NAMES}")
    n_in = len(inputs)
    queue_size = need(meta, "queue_size")
    nets_meta = need(meta, "networks")
    if not isinstance(queue_size, int) or queue_size < 1:
        raise ModelFileError(f"model file {name}: queue_size must be a positive integer")
    if not isinstance(nets_meta, list):
        raise ModelFileError(f"model file {name}: 'networks' must be a list")
    stored_w = need(meta, "queue_weights")
    expected_w = queue_weights(len(nets_meta))
    if not isinstance(stored_w, list) or len(stored_w) != len(nets_meta) or not all(
        isinstance(w, (int, float)) and not isinstance(w, bool) for w in stored_w
    ) or not np.allclose(
        np.asarray(stored_w, dtype=np.float64), expected_w, rtol=1e-12, atol=0.0
    ):
        raise ModelFileError(f"model file {name}: queue_weights disagree with e^(k-n) for {len(nets_meta)} networks")

    sizes = [n_in, *hidden, N_OUT]
    expected_names: set[str] = set()
    networks = []
    for j, nm in enumerate(nets_meta):
        norm = Normalisation(
            _vector(need(nm, "input_mean", f"networks[{j}]."), n_in, f"networks[{j}].input_mean", name),
            _vector(need(nm, "input_scale", f"networks[{j}]."), n_in, f"networks[{j}].input_scale", name),
            _vector(need(nm, "output_scale", f"networks[{j}]."), N_OUT, f"networks[{j}].output_scale", name),
        )
        layers = []
        for i in range(len(sizes) - 1):
            wname, bname = f"net{j}.layer{i}.weight", f"net{j}.layer{i}.bias"
            expected_names.update((wname, bname))
            w = _tensor(tensors, wname, (sizes[i + 1], sizes[i]), name)
            b = _tensor(tensors, bname, (sizes[i + 1],), name)
            layers.append((w, b))
        networks.append(NetworkWeights(tuple(layers), norm))
    extra_names = sorted(set(tensors) - expected_names)
    if extra_names:
        raise ModelFileError(f"model file {name}: tensor '{extra_names[0]}' is not in the architecture ({len(nets_meta)} networks, hidden {hidden})")

    training = need(meta, "training")
    info = None if training is None else _training_from(training, name)
    extra = meta.get("extra", {})
    problem = score_problem(extra.get(SCORE_KEY)) if isinstance(extra, Mapping) else None
    if not problem and isinstance(extra, Mapping):
        problem = bounds_problem(extra.get(BOUNDS_KEY), len(networks))
    if problem:
        raise ModelFileError(f"model file {name}: {problem}")
    return ModelFile(
        hidden=tuple(hidden),
        activation=activation,
        queue_size=queue_size,
        networks=tuple(networks),
        training=info,
        software_version=str(need(meta, "software_version")),
        created=str(need(meta, "created")),
        extra=extra if isinstance(extra, dict) else {},
        inputs=tuple(inputs),
    )


def _training_from(obj: Any, name: str) -> TrainingInfo:
    keys = ("t0", "t1", "sources", "loss", "val_rmse_nominal", "val_rmse_model", "epochs", "wall_time")
    for key in keys:
        if not isinstance(obj, Mapping) or key not in obj:
            raise ModelFileError(f"model file {name}: metadata key 'training.{key}' is missing")
    try:
        return TrainingInfo(
            t0=float(obj["t0"]),
            t1=float(obj["t1"]),
            sources=tuple(str(s) for s in obj["sources"]),
            loss=float(obj["loss"]),
            val_rmse_nominal=float(obj["val_rmse_nominal"]),
            val_rmse_model=float(obj["val_rmse_model"]),
            epochs=int(obj["epochs"]),
            wall_time=float(obj["wall_time"]),
        )
    except (TypeError, ValueError):
        raise ModelFileError(f"model file {name}: metadata 'training' has a value of the wrong type") from None


def _vector(value: Any, n: int, key: str, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelFileError(f"model file {name}: metadata '{key}' must be a list of {n} numbers") from None
    if arr.shape != (n,):
        raise ModelFileError(f"model file {name}: metadata '{key}' must be a list of {n} numbers")
    return arr


def _tensor(tensors: Mapping[str, np.ndarray], key: str, shape: tuple[int, ...], name: str) -> np.ndarray:
    if key not in tensors:
        raise ModelFileError(f"model file {name}: tensor '{key}' is missing")
    arr = tensors[key]
    if arr.dtype.kind != "f":
        raise ModelFileError(f"model file {name}: tensor '{key}' has dtype {arr.dtype}, expected floating point")
    if arr.shape != shape:
        raise ModelFileError(f"model file {name}: tensor '{key}' has shape {arr.shape}, the architecture says {shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _check_model(model: ModelFile, name: str) -> None:
    """Consistency and finiteness; shared by save (refuse to write) and load (refuse to use)."""
    if model.activation not in ACTIVATIONS:
        raise ModelFileError(f"model file {name}: unknown activation {model.activation!r}")
    if len(model.networks) > model.queue_size:
        raise ModelFileError(f"model file {name}: {len(model.networks)} networks exceed queue_size {model.queue_size}")
    if tuple(model.inputs) not in INPUT_LAYOUTS:
        raise ModelFileError(f"model file {name}: unknown input layout {tuple(model.inputs)}")
    sizes = [len(model.inputs), *model.hidden, N_OUT]
    for j, net in enumerate(model.networks):
        if len(net.layers) != len(sizes) - 1:
            raise ModelFileError(f"model file {name}: network {j} has {len(net.layers)} layers, the architecture says {len(sizes) - 1}")
        for i, (w, b) in enumerate(net.layers):
            if np.shape(w) != (sizes[i + 1], sizes[i]) or np.shape(b) != (sizes[i + 1],):
                raise ModelFileError(f"model file {name}: network {j} layer {i} has shapes {np.shape(w)}/{np.shape(b)}, expected {(sizes[i + 1], sizes[i])}")
            if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
                raise ModelFileError(f"model file {name}: network {j} layer {i} has non-finite weights")
        norm = net.normalisation
        for key, arr in (("input_mean", norm.input_mean), ("input_scale", norm.input_scale), ("output_scale", norm.output_scale)):
            if not np.all(np.isfinite(arr)):
                raise ModelFileError(f"model file {name}: network {j} {key} is not finite")
        if np.any(norm.input_scale <= 0) or np.any(norm.output_scale <= 0):
            raise ModelFileError(f"model file {name}: network {j} has a non-positive scale")
    if model.training is not None:
        t = model.training
        for key in ("t0", "t1", "loss", "val_rmse_nominal", "val_rmse_model", "wall_time"):
            if not math.isfinite(getattr(t, key)):
                raise ModelFileError(f"model file {name}: training.{key} is not finite")


def _software_version() -> str:
    from cfknode.kernel.version import __version__

    return __version__


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not every platform can open a directory, so best effort.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def model_summary(model: ModelFile) -> str:
    """One line for logs and the CLI."""
    parts = [f"{len(model.networks)}/{model.queue_size} nets", f"hidden {list(model.hidden)} {model.activation}"]
    if model.training is not None:
        t = model.training
        parts.append(f"val RMSE {t.val_rmse_model:.4g} m/s (nominal {t.val_rmse_nominal:.4g})")
    return ", ".join(parts)


__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "INPUT_LAYOUTS",
    "INPUT_NAMES",
    "MASKED_INPUT_SCALE",
    "NEIGHBOUR_INPUT_NAMES",
    "NEIGHBOUR_NAMES",
    "OUTPUT_NAMES",
    "WAKE_INPUT_NAMES",
    "ModelFile",
    "ModelFileError",
    "NetworkWeights",
    "Normalisation",
    "TrainingInfo",
    "load_model",
    "model_summary",
    "queue_weights",
    "save_model",
]
