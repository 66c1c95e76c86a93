"""``cfknode model check``: before flying a model, what can one learn of this vehicle, and on which axes?

Per axis it reports the residual's size; how much of it a constant and the fast layer (at its
configured bandwidths) remove; how much a model removes beyond the layer on held-out manoeuvres
(a given ``--model``, or one fitted now on the other manoeuvres); the open-loop prediction error
at 0.1, 0.25 and 0.5 s; and one sentence on whether learning is worth it (docs/data.md).
"""

from __future__ import annotations

import argparse

from cfknode.app.commands.data_args import add_data_arguments, dataset_for, read_segments
from cfknode.app.commands.fly import add_config_arguments, config_from_args

HELP = "check a model, or what a model could learn, on flight data (model check)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True)
    check = sub.add_parser("check", help="what a model adds beside the fast layer, on held-out manoeuvres",
                           description=__doc__)
    add_config_arguments(check)
    add_data_arguments(check)
    check.add_argument("--model", help="the model file to judge (default: fit one now on the other manoeuvres)")
    check.add_argument("--epochs", type=int, help="override training.epochs for the fit")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from cfknode.app.config import ConfigError
    from cfknode.app.data.check import check, queue_residual, render
    from cfknode.models.knode import to_torch_queue
    from cfknode.models.modelfile import ModelFileError, load_model
    from cfknode.models.training import train_new_model

    cfg = config_from_args(args, flags={"epochs": "training.epochs"})
    console = Console()
    segments, _ = read_segments(args, cfg, lambda line: console.print(f"[dim]{line}[/]"))
    dataset, held_out = dataset_for(segments, cfg, "group" if args.split == "auto" else args.split)
    if args.model:
        try:
            queue = to_torch_queue(load_model(args.model))
        except ModelFileError as exc:
            raise ConfigError(str(exc)) from None
    else:
        console.print(f"fitting a model on {len(dataset.train)} samples ({cfg.training.epochs} steps) ...")
        queue, _ = train_new_model(dataset, cfg.knode, cfg.training)
    a = cfg.controller.adaptation_settings
    report = check(dataset.val, queue_residual(queue), (a.bandwidth_xy_hz, a.bandwidth_hz),
                   (a.output_bandwidth_xy_hz, a.output_bandwidth_hz), held_out or ("the last part of each run",))
    render(report, console)
    return 0
