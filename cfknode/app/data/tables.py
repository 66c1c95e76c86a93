"""Reading a CSV or Parquet flight table into named float columns, with the documented schema.

The schema (docs/data.md): ``t`` (s), ``px py pz`` (m), optional ``vx vy vz`` (m/s), ``qw qx qy qz``,
and one input: ``m1 m2 m3 m4`` (motor speeds, rad/s), or ``thrust`` (N), or ``roll_deg pitch_deg
thrust_cmd`` (the RPYT command); an optional ``manoeuvre`` column groups samples for the split.
``--columns name=their_name,...`` maps a dataset's own names onto these.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO, TextIO

import numpy as np

from cfknode.kernel.bounded_input import open_regular
from cfknode.kernel.errors import ConfigError

MAX_BYTES = 2 * 1024**3  # a table larger than this is refused before it is read
MAX_ROWS = 20_000_000
REQUIRED = ("t", "px", "py", "pz")
OPTIONAL = ("vx", "vy", "vz", "qw", "qx", "qy", "qz", "m1", "m2", "m3", "m4", "thrust", "roll_deg", "pitch_deg",
            "thrust_cmd", "manoeuvre")


def _short(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[:n] + "..."


def parse_column_map(spec: str | None) -> dict[str, str]:
    """``"t=time,px=x"`` -> {"t": "time", "px": "x"}; a wrong entry is a one-line ConfigError."""
    if not spec:
        return {}
    out: dict[str, str] = {}
    for item in spec.split(","):
        ours, sep, theirs = item.partition("=")
        ours, theirs = ours.strip(), theirs.strip()
        if not sep or not theirs or ours not in (*REQUIRED, *OPTIONAL):
            raise ConfigError(f"--columns entry {_short(item)!r}: expected NAME=COLUMN with NAME one of "
                              f"{', '.join((*REQUIRED, *OPTIONAL))}")
        out[ours] = theirs
    return out


def read_table(path: str | Path, columns: Mapping[str, str] | None = None) -> dict[str, np.ndarray]:
    """The schema's columns present in ``path`` (.csv or .parquet) as float arrays (``manoeuvre`` as str)."""
    path = Path(path)
    names = {ours: (columns or {}).get(ours, ours) for ours in (*REQUIRED, *OPTIONAL)}
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet", ".pq"):
        raise ConfigError(f"{path}: a flight table is .csv or .parquet (or give a cfknode .mcap log with --log)")
    # A regular file under the cap, opened once: no FIFO, device or /dev/zero link is read.
    fh, _ = open_regular(path, MAX_BYTES, ConfigError, "flight table")
    with fh:
        raw = (_read_csv(io.TextIOWrapper(fh, newline=""), path, set(names.values())) if suffix == ".csv"
               else _read_parquet(fh, path, set(names.values())))
    missing = [ours for ours in REQUIRED if names[ours] not in raw]
    if missing:
        raise ConfigError(f"{path}: no column {', '.join(names[m] for m in missing)} (map yours with --columns)")
    table: dict[str, np.ndarray] = {}
    for ours, theirs in names.items():
        if theirs not in raw:
            continue
        if ours == "manoeuvre":
            table[ours] = np.asarray(raw[theirs]).astype(str)
            continue
        try:
            table[ours] = np.asarray(raw[theirs], dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(f"{path}: column {_short(theirs)!r} is not numeric") from None
    if table["t"].size < 2:
        raise ConfigError(f"{path}: fewer than two rows")
    return table


def _read_csv(fh: TextIO, path: Path, wanted: set[str]) -> dict[str, list[str] | np.ndarray]:
    reader = csv.reader(fh)
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise ConfigError(f"{path}: empty file") from None
    except (csv.Error, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a CSV table ({_short(str(exc))})") from None
    keep = [(i, h) for i, h in enumerate(header) if h in wanted]
    cols: dict[str, list[str]] = {h: [] for _, h in keep}
    try:
        for n, row in enumerate(reader, start=2):
            if n > MAX_ROWS:
                raise ConfigError(f"{path}: over {MAX_ROWS} rows")
            if len(row) != len(header):
                raise ConfigError(f"{path}: line {n} has {len(row)} fields, the header {len(header)}")
            for i, h in keep:
                cols[h].append(row[i])
    except (csv.Error, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: line {reader.line_num}: {_short(str(exc))}") from None
    out: dict[str, list[str] | np.ndarray] = {}
    for h, values in cols.items():
        try:
            out[h] = np.array([float(v) if v.strip() else math.nan for v in values])
        except ValueError:
            out[h] = values  # text (a manoeuvre name): read_table decides whether that is allowed
    return out


def _read_parquet(fh: BinaryIO, path: Path, wanted: set[str]) -> dict[str, list[str] | np.ndarray]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise ConfigError("reading Parquet needs pyarrow: pip install 'cfknode[data]'") from None
    try:
        pf = pq.ParquetFile(fh)
        if pf.metadata.num_rows > MAX_ROWS:
            raise ConfigError(f"{path}: {pf.metadata.num_rows} rows, over the {MAX_ROWS} row limit")
        present = [c for c in pf.schema_arrow.names if c in wanted]
        table = pf.read(columns=present)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for a damaged file
        raise ConfigError(f"{path}: not a readable Parquet file ({_short(str(exc))})") from None
    out: dict[str, list[str] | np.ndarray] = {}
    for name in present:
        col = table.column(name)
        out[name] = col.to_numpy(zero_copy_only=False) if not str(col.type).startswith("string") else col.to_pylist()
    return out
