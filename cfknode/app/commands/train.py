"""``cfknode train``: fit a KNODE residual to one or more flight logs and write a model file."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from cfknode.app.errors import UsageError
from cfknode.app.commands.fly import add_config_arguments, config_from_args

HELP = "train a KNODE model from flight logs (offline KNODE-MPC)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    p.add_argument("--log", action="append", required=True, metavar="FLIGHT_LOG", help="flight log (repeatable)")
    p.add_argument("--out", required=True, help="model file to write (safetensors)")
    p.add_argument("--init", help="start from this model file's queue (a new network is pushed onto it)")
    p.add_argument("--epochs", type=int, help="override training.epochs")


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args, flags={"epochs": "training.epochs"})
    out = Path(args.out)
    if out.exists() and out.is_dir():
        raise UsageError(f"--out {out} is a directory; give a file name")
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from cfknode.app.config import ConfigError
    from cfknode.app.logs.training_data import segments_from_logs
    from cfknode.models.knode import from_torch_queue
    from cfknode.models.modelfile import ModelFileError, load_model, model_summary, save_model
    from cfknode.models.training import make_dataset, train_new_model

    console = Console()
    segments = segments_from_logs(args.log, lambda line: print(f"cfknode: warning: {line}", file=sys.stderr))
    try:
        initial = load_model(args.init) if args.init else None
    except ModelFileError as exc:
        raise ConfigError(str(exc)) from None
    try:
        dataset = make_dataset(segments, cfg.training.velocity_filter_hz, cfg.training.validation_fraction)
    except ValueError as exc:
        raise ConfigError(f"cannot train on {', '.join(args.log)}: {exc}") from None
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
    model = from_torch_queue(queue, training=result.training_info(dataset), extra={"config_knode": cfg.to_dict()["knode"]})
    path = save_model(out, model)
    console.print(model_summary(load_model(path)))
    console.print(
        f"held-out one-step velocity RMSE: nominal {result.val_rmse_nominal:.4g} m/s -> model "
        f"{result.val_rmse_model:.4g} m/s; wrote {path}"
    )
    return 0
