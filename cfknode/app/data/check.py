"""``cfknode model check``'s analysis: what a model can add to the fast layer, judged on held-out manoeuvres.

The data is split by manoeuvre (or by file): a model is fitted on some manoeuvres (or a given
model file is used) and judged on the others, never on the tail of a run it was fitted on, where
horizontal drag-like slopes look like gains and do not transfer. The scores are the per-axis
shares of ``cfknode.models.residual_check``; see docs/data.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from cfknode.kernel.errors import ConfigError
from cfknode.models import residual_check as rc
from cfknode.models.training import Dataset, Pairs, Segment, make_dataset

HORIZONS_S = (0.1, 0.25, 0.5)


def group_of(segment: Segment) -> str:
    """A segment's manoeuvre (``file:manoeuvre``), or its file when the table had no manoeuvre column."""
    return segment.source


def split_by_group(segments: Sequence[Segment], held_out: float = 0.25) -> tuple[list[Segment], list[Segment]]:
    """Training and held-out segments, whole groups on each side (every ``1/held_out``-th group held out)."""
    groups = list(dict.fromkeys(group_of(s) for s in segments))
    if len(groups) < 2:
        raise ConfigError("a held-out check needs at least two manoeuvres or files: add a manoeuvre column "
                          "or give more files (docs/data.md)")
    n_out = max(1, round(held_out * len(groups)))
    step = len(groups) / n_out
    out = {groups[min(len(groups) - 1, int(step * (k + 1)) - 1)] for k in range(n_out)}
    return ([s for s in segments if group_of(s) not in out], [s for s in segments if group_of(s) in out])


def split_dataset(train: Sequence[Segment], held: Sequence[Segment], filter_hz: float) -> Dataset:
    """A dataset whose validation pairs are the held-out manoeuvres' (not the tails of the training runs)."""
    fitted = make_dataset(train, filter_hz, 0.0)
    return dataclasses.replace(fitted, val=make_dataset(held, filter_hz, 0.0).train)


def queue_residual(queue: Any, beside_layer: bool = True) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The model's residual as a numpy function of (x (k, 6), u (k, 3)); ``beside_layer``: as it flies beside
    the fast layer, vertically without its slope in the vertical command u_z, which the layer's thrust scale
    owns there (docs/architecture.md, the model and the layer as one estimator): the score is then the score of
    what flies."""
    def raw(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = queue(torch.as_tensor(x, dtype=queue.dtype), torch.as_tensor(u, dtype=queue.dtype))
        return out.numpy().astype(np.float64)

    def flown(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        r = raw(x, u)
        step = np.zeros(3)
        step[2] = SLOPE_STEP
        slope = (raw(x, u + step)[:, 2] - raw(x, u - step)[:, 2]) / (2.0 * SLOPE_STEP)
        r[:, 2] -= slope * u[:, 2]
        return r
    return flown if beside_layer else raw


SLOPE_STEP = 1e-2  # m/s^2: the central difference's half step for the slope in u_z (the network is smooth)


@dataclass(frozen=True)
class CheckReport:
    shares: rc.AxisShares
    open_loop: dict[str, dict[float, tuple[float, float]]]  # "nominal" / "+ layer" / "+ layer + model"
    verdict: str
    pairs: int  # held-out pairs judged on
    held_out: tuple[str, ...]


def check(held: Pairs, model: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
          bandwidth_hz: tuple[float, float], output_hz: tuple[float, float], held_out: Sequence[str] = ()) -> CheckReport:
    """Score ``model`` (None: no model) on held-out pairs beside the layer at its bandwidths ((xy, z) Hz)."""
    if len(held) < 10:
        raise ConfigError("the held-out manoeuvres hold fewer than 10 usable samples")
    r = rc.pair_residual(held)
    m = model(held.x0, held.u) if model is not None else np.zeros_like(r)
    shares = rc.shares(held.t0, r, m, bandwidth_hz, output_hz)
    layer = rc.layer_estimate(held.t0, r, bandwidth_hz, output_hz)
    layer_with_model = rc.layer_estimate(held.t0, r - m, bandwidth_hz, output_hz)
    ol = {
        "nominal": rc.open_loop_errors(held.t0, held.x0, held.u, HORIZONS_S),
        "+ layer": rc.open_loop_errors(held.t0, held.x0, held.u, HORIZONS_S, offset=layer),
    }
    if model is not None:
        ol["+ layer + model"] = rc.open_loop_errors(held.t0, held.x0, held.u, HORIZONS_S, offset=layer_with_model,
                                                    model=model)
    return CheckReport(shares, ol, rc.verdict(shares.beyond_layer), len(held), tuple(held_out))


def render(report: CheckReport, console: Any) -> None:
    from rich.table import Table

    s = report.shares
    table = Table(title=f"residual per axis, {report.pairs} held-out samples ({', '.join(report.held_out)})")
    for col in ("axis", "RMS m/s^2", "a constant removes", "the layer removes", "the model removes",
                "model beyond layer"):
        table.add_column(col, justify="right")
    for k, axis in enumerate("xyz"):
        table.add_row(axis, f"{s.rms[k]:.3f}", f"{s.constant[k]:.0%}", f"{s.layer[k]:.0%}", f"{s.model[k]:.0%}",
                      f"{s.beyond_layer[k]:.0%}")
    console.print(table)
    ol = Table(title="open-loop prediction error on held-out manoeuvres (position m / velocity m/s)")
    ol.add_column("prediction")
    for h in HORIZONS_S:
        ol.add_column(f"{h:g} s", justify="right")
    for name, row in report.open_loop.items():
        ol.add_row(name, *(f"{row[h][0]:.3f} / {row[h][1]:.3f}" for h in HORIZONS_S))
    console.print(ol)
    console.print(report.verdict)
