"""What the Foxglove view costs a tick: ``/state`` log writes with and without it, in one run."""

from __future__ import annotations

import tempfile
import time
from typing import Any

import numpy as np

from cfknode.app.foxglove.live import LiveServer
from cfknode.app.foxglove.view import Drawing, FoxgloveView, McapSink
from cfknode.app.logs.writer import FlightLog


def _writes(ticks: int, live: Any) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per ``/state`` write, straight to the log and through the view, interleaved tick by tick."""
    with tempfile.TemporaryDirectory() as d, FlightLog.create(d, {}, "bench", "foxglove") as log:
        path = np.column_stack([np.cos(np.linspace(0, 6.3, 700)), np.sin(np.linspace(0, 6.3, 700)), np.ones(700)])
        view = FoxgloveView(log, [McapSink(log), *([live] if live is not None else [])],
                            {"cf": Drawing(path, ([-2, -2, 0], [2, 2, 2]))})
        plan = np.zeros((21, 3))
        view.follow_plan("cf", lambda: plan)
        msg = {"p": np.zeros(3), "v": np.zeros(3), "q": np.array([1.0, 0, 0, 0]), "fresh": True, "phase": "pattern"}
        plain, tapped = np.empty(ticks), np.empty(ticks)
        for k in range(ticks):
            t = k / 400.0
            t0 = time.perf_counter()
            log.write("/state", t, msg)
            t1 = time.perf_counter()
            view.write("/state", t, msg)
            plain[k], tapped[k] = t1 - t0, time.perf_counter() - t1
    return plain, tapped


def foxglove_samples(ticks: int = 8000) -> list[tuple[str, np.ndarray, str]]:
    """``bench timing``'s rows (name, seconds, note): a plain ``/state`` write, the same through the
    view, and with the live server up."""
    plain, tapped = _writes(ticks, None)
    with LiveServer(port=0) as live:
        _, served = _writes(ticks, live)
    return [("/state write, log only", plain, ""),
            ("/state write + Foxglove channels in the log", tapped, "50 Hz pose, 10 Hz horizon"),
            ("/state write + Foxglove log and live server", served, "no client connected")]
