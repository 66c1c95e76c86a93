"""``cfknode train``: fit a KNODE residual to flight logs or flight tables and write a model file.

After training, the model is judged on held-out data (whole manoeuvres or files where there are
two or more) beside the fast layer, with the same score as ``cfknode model check``."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from cfknode.app.commands.data_args import add_data_arguments, dataset_for, read_segments
from cfknode.app.errors import UsageError
from cfknode.kernel.outputs import output_problem
from cfknode.app.commands.fly import add_config_arguments, config_from_args

HELP = "train a KNODE model from flight logs or CSV/Parquet flight tables (offline KNODE-MPC)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    add_data_arguments(p)
    p.add_argument("--out", required=True, help="model file to write (safetensors)")
    p.add_argument("--init", help="start from this model file's queue (a new network is pushed onto it)")
    p.add_argument("--epochs", type=int, help="override training.epochs")


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args, flags={"epochs": "training.epochs"})
    out = Path(args.out)
    problem = output_problem(out)  # before training: the model is written over regular files only
    if problem is not None:
        raise UsageError(f"--out {problem}")
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from cfknode.app.config import ConfigError
    from cfknode.models.knode import from_torch_queue
    from cfknode.models.modelfile import ModelFileError, load_model, model_summary, save_model
    from cfknode.models.residual_check import SCORE_KEY
    from cfknode.models.training import train_new_model

    console = Console()
    segments, _ = read_segments(args, cfg)
    try:
        initial = load_model(args.init) if args.init else None
    except ModelFileError as exc:
        raise ConfigError(str(exc)) from None
    if initial is not None and initial.takes_neighbour:  # logs do not pair a drone with its neighbour's positions
        raise ConfigError(f"--init {args.init} takes the neighbour input (docs/fleet.md#neighbour-input), which "
                          "cfknode train does not record from logs")
    dataset, held_out = dataset_for(segments, cfg, args.split)
    console.print(
        f"training on {len(dataset.train)} pairs ({len(dataset.val)} held out) from {len(segments)} segment(s), "
        f"{cfg.training.epochs} epochs, {cfg.training.method}"
    )
    with Progress(TextColumn("[bold]training"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TextColumn("loss {task.fields[loss]:.4g}"), TimeRemainingColumn(), console=console) as bar:
        task = bar.add_task("train", total=cfg.training.epochs, loss=math.nan)
        queue, result = train_new_model(
            dataset, cfg.knode, cfg.training, initial=initial,
            progress=lambda epoch, loss: bar.update(task, completed=epoch, loss=loss),
        )
    report = None
    if len(dataset.val) >= 10:  # judged before it is written: the file keeps the score (the flight reads it)
        from cfknode.app.data.check import check, queue_residual

        a = cfg.controller.adaptation_settings
        report = check(dataset.val, queue_residual(queue), (a.bandwidth_xy_hz, a.bandwidth_hz),
                       (a.output_bandwidth_xy_hz, a.output_bandwidth_hz), held_out or ("the last part of each run",))
    extra: dict[str, object] = {"config_knode": cfg.to_dict()["knode"]}
    if report is not None:
        extra[SCORE_KEY] = [float(v) for v in report.shares.beyond_layer]
    model = from_torch_queue(queue, training=result.training_info(dataset), extra=extra)
    path = save_model(out, model)
    console.print(model_summary(load_model(path)))
    console.print(
        f"held-out one-step velocity RMSE: nominal {result.val_rmse_nominal:.4g} m/s -> model "
        f"{result.val_rmse_model:.4g} m/s; wrote {path}"
    )
    if report is not None:
        from cfknode.app.data.check import render

        render(report, console)
        console.print("stored score beyond the layer (x, y, z): "
                      + ", ".join(f"{v:+.4f}" for v in report.shares.beyond_layer))
    return 0
