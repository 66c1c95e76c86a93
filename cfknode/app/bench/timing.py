"""``cfknode bench timing``: medians and p99s of the real-time parts, all measured in one run.

Every number is measured here, now, on this machine, and ratios compare rows of the same
run (never a stored figure), so a busy machine shifts every row alike.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from cfknode.app.config import Config, load_config
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import StateEstimate
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.mpc import TranslationalMpc
from cfknode.flight.trajectory import circle_samples
from cfknode.models.modelfile import ModelFile, NetworkWeights, Normalisation
from cfknode.models.quadrotor import rk4_step
from cfknode.models.residual_np import ResidualQueue


@dataclass(frozen=True)
class Timing:
    name: str
    samples: int
    median_ms: float
    p99_ms: float
    max_ms: float
    note: str = ""

    @classmethod
    def of(cls, name: str, seconds: np.ndarray, note: str = "") -> "Timing":
        ms = np.asarray(seconds) * 1e3
        return cls(name, int(ms.size), float(np.median(ms)), float(np.percentile(ms, 99)), float(ms.max()), note)


def synthetic_queue(hidden: tuple[int, ...], n_networks: int, seed: int = 0) -> ResidualQueue:
    """A queue of ``n_networks`` random networks of the flight architecture (timing needs no training)."""
    rng = np.random.default_rng(seed)
    sizes = [6, *hidden, 3]
    nets = []
    for _ in range(n_networks):
        layers = tuple(
            (rng.normal(0, 0.3 / np.sqrt(i), (o, i)), rng.normal(0, 0.05, o)) for i, o in zip(sizes[:-1], sizes[1:])
        )
        nets.append(NetworkWeights(layers, Normalisation(np.zeros(6), np.full(6, 2.0), np.full(3, 0.3))))
    mf = ModelFile(hidden=hidden, activation="tanh", queue_size=max(n_networks, 1), networks=tuple(nets))
    return ResidualQueue.from_model_file(mf)


def mpc_closed_loop(cfg: Config, mpc: TranslationalMpc, slot: ModelSlot | None, seconds: float) -> tuple[Timing, ...]:
    """Solve time, the control step's time (solve + Mellinger layer: what a pose waits for), and the preparation's
    after the send (the fast layer's update, the next tick's linearisation), of the controller in a 400 Hz
    closed loop on a circle.

    The plant is the double integrator plus the same residual the MPC is given, so the loop
    tracks and the solver works on realistic warm starts.
    """
    ctrl = cfg.controller
    tc = 1.0 / ctrl.rate_hz
    start_ref = circle_samples(np.zeros(1), 0.5, 0.4, 1.0)
    # The floor where the guess would put it (the first state's height): said, not guessed.
    controller = Controller(ctrl, cfg.vehicle, model=slot, solver=mpc, ground_z=float(start_ref.p[0][2]))
    controller.prepares_after_send = True  # as the flight loop: prepare() after each send, timed apart
    # Start on the reference: the bench times tracking, not the recovery from a 0.4 m/s step.
    x = np.concatenate((start_ref.p[0], start_ref.v[0]))
    level = np.array([1.0, 0.0, 0.0, 0.0])
    queue = slot.model if slot is not None else None

    def plant(xs: np.ndarray, us: np.ndarray) -> np.ndarray:
        r = queue.evaluate(xs, us) if queue is not None else 0.0
        return np.concatenate((xs[3:], us + r))

    ticks = int(round(seconds / tc))
    solve, total, prepare = np.empty(ticks), np.empty(ticks), np.empty(ticks)
    for i in range(ticks):
        t = i * tc
        ref = circle_samples(controller.preview_times(t), 0.5, 0.4, 1.0)
        start = time.perf_counter()
        command = controller.step(t, StateEstimate(t, x[:3], x[3:], level, 0.0), ref)
        sent = time.perf_counter()
        controller.prepare()  # as the flight loop does after the send
        total[i], prepare[i] = sent - start, time.perf_counter() - sent
        solve[i] = command.solve_s
        x = rk4_step(plant, x, command.acc, tc)
    label = f"{mpc.backend}{' + KNODE x' + str(queue.n_networks) if queue is not None else ''}"
    return (Timing.of(f"MPC solve, {label}", solve), Timing.of(f"control step, {label}", total),
            Timing.of(f"after the send, {label}", prepare,
                      note="the layer's update, the next tick's linearisation (controller.prepare)"))


class _TimedLayer:
    """A fast layer whose per-tick calls are timed: the controller's slot, delegating to ``inner``."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.seconds: list[float] = []
        self._tick = 0.0

    def __getattr__(self, name: str) -> Any:  # summary, off_air, estimate: not timed
        return getattr(self.inner, name)

    def _timed(self, name: str, *args: Any) -> Any:
        start = time.perf_counter()
        out = getattr(self.inner, name)(*args)
        self._tick += time.perf_counter() - start
        return out

    def before_solve(self, *args: Any) -> Any:
        self._tick = 0.0
        return self._timed("before_solve", *args)

    def f_max(self) -> float:
        return self._timed("f_max")

    def residual(self, *args: Any) -> Any:
        return self._timed("residual", *args)

    def shaping(self) -> Any:
        return self._timed("shaping")

    def after_command(self, *args: Any) -> None:
        self._timed("after_command", *args)

    def log(self) -> Any:
        """The loop asks for the layer's /adaptation message every tick, after the send: timed with the rest."""
        out = self._timed("log")
        self.seconds.append(self._tick)
        return out


def layer_tick(cfg: Config, mpc: TranslationalMpc, seconds: float) -> Timing:
    """The fast layer's own share of a tick (every call the controller makes to it) on a 0.5 m circle: a point
    mass 1.2x heavier than the controller believes, flown on the setpoint's thrust and attitude, so the layer
    estimates and acts."""
    from cfknode.flight.adaptation import LoopAdaptation
    from cfknode.kernel.imu import ImuSample
    from cfknode.kernel.setpoint import read_setpoint

    ctrl, vehicle = dataclasses.replace(cfg.controller, adaptation="dob"), cfg.vehicle
    timed = _TimedLayer(LoopAdaptation(ctrl, vehicle, ground_z=0.0))
    controller = Controller(ctrl, vehicle, solver=mpc, adaptation=timed, ground_z=0.0)  # type: ignore[arg-type]
    tc = 1.0 / ctrl.rate_hz
    start = circle_samples(np.zeros(1), 0.5, 0.4, 1.0)
    p, v, q = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0])
    imu = None
    for i in range(int(round(seconds / tc))):
        t = i * tc
        ref = circle_samples(controller.preview_times(t), 0.5, 0.4, 1.0)
        # As in flight: a mocap frame every tick and an accelerometer sample at 100 Hz, both read by the layer.
        command = controller.step(t, StateEstimate(t, p, v, q, 0.0, frame=(t, p.copy()), imu=imu), ref)
        controller.adaptation.log()  # type: ignore[union-attr] - the loop logs /adaptation every tick
        target = read_setpoint(command.setpoint, vehicle, 0.0, tc)
        if i % 4 == 0:
            imu = ImuSample(t, np.array([0.0, 0.0, target.thrust_n / (1.2 * vehicle.mass)]))
        q = np.array(target.quaternion)
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                           1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        v = v + tc * (target.thrust_n / (1.2 * vehicle.mass) * body_z - [0.0, 0.0, vehicle.gravity])
        p = p + tc * v
    return Timing.of("fast layer (dob), its calls per tick", np.array(timed.seconds),
                     note="before_solve + f_max + residual + shaping + after_command + log (not the log's write)")


def swap_latency(cfg: Config, repeats: int = 2000) -> Timing:
    """A hot swap is one reference write into the ModelSlot, timed between two ticks' worth of use."""
    slot = ModelSlot(synthetic_queue(cfg.knode.hidden, cfg.knode.queue_size, seed=1), version=1)
    queues = [synthetic_queue(cfg.knode.hidden, cfg.knode.queue_size, seed=s) for s in range(2, 6)]
    for k in range(repeats):
        slot.swap(queues[k % len(queues)], version=k + 2, now=0.0)
    return Timing.of("model swap (ModelSlot.swap)", np.array([s.swap_s for s in slot.swaps]))


def training_round(cfg: Config, t_col: float, epochs: int, rounds: int = 5) -> Timing:
    """Wall time of one online-style round: push a network and train it on a t_col window at 400 Hz."""
    from cfknode.models.training import Segment, make_dataset, train_new_model

    rng = np.random.default_rng(0)
    n = int(round(t_col * cfg.controller.rate_hz)) + 1
    walls = []
    initial = None
    training = dataclasses.replace(cfg.training, epochs=epochs, method=cfg.online.method)  # as online rounds run
    for k in range(rounds):
        t = k * t_col + np.arange(n) / cfg.controller.rate_hz
        u = rng.normal(0, 1.0, (n, 3)) * [0.3, 0.3, 0.5] + [0, 0, 2.0]
        v = np.cumsum(u * 0.77 / cfg.controller.rate_hz, axis=0)  # a heavier vehicle: acceleration 0.77 u
        x = np.concatenate((np.cumsum(v / cfg.controller.rate_hz, axis=0), v), axis=1)
        data = make_dataset([Segment(t, x, u)], cfg.training.velocity_filter_hz, 0.0)
        start = time.perf_counter()
        queue, _ = train_new_model(data, cfg.knode, training, initial=initial)
        walls.append(time.perf_counter() - start)
        from cfknode.models.knode import from_torch_queue

        initial = from_torch_queue(queue)
    return Timing.of(f"training round: {epochs} epochs ({training.method}) on a {t_col:g} s window", np.array(walls),
                     note=f"t_col = {t_col * 1e3:.0f} ms")


def lockstep_flight(cfg: Config, model: ResidualQueue | None, seconds: float, adaptation: str = "none") -> dict[str, Any]:
    """A short lockstep circle through the whole stack: tick compute and the speed factor
    (``adaptation``: the fast layer's mode, to measure its cost)."""
    import tempfile

    from cfknode.app.mission import run_flight

    with tempfile.TemporaryDirectory() as tmp:
        overrides = {"trajectory.duration": seconds, "log.dir": tmp, "controller.adaptation": adaptation}
        flight_cfg = load_config(overrides=overrides)
        if model is not None:
            # A synthetic model file: the flight loads it exactly as `--model` would.
            from cfknode.models.modelfile import save_model

            path = f"{tmp}/bench.ckpt"
            save_model(path, _model_file(cfg))
            flight_cfg = load_config(overrides={**overrides, "controller.model": path})
        s = run_flight(flight_cfg, name_hint="bench").summary
        by_kind = ticks_by_sample(s.log_path, s.window)
    return {
        "tick_median_ms": s.compute_median_ms,
        "tick_p99_ms": s.compute_p99_ms,
        "missed": s.missed_deadlines,
        "ticks": s.ticks,
        "speed_factor": s.speed_factor,
        **by_kind,
    }


def ticks_by_sample(log_path: str, window: tuple[float, float]) -> dict[str, float]:
    """Tick compute medians (ms) and counts over the pattern ``window`` from a flight's log, for the ticks with a
    new accelerometer sample and those without: where the fast layer learns depends on them
    (docs/design.md#the-tick-in-two-phases)."""
    from cfknode.app.logs.reader import read_log

    log = read_log(log_path)
    seen = {m["t"]: m.get("imu_t") for m in log.topic("/state")}
    newest = -math.inf
    kinds: dict[bool, list[float]] = {True: [], False: []}
    for m in log.topic("/tick"):
        imu_t = seen.get(m["t"])
        fresh = imu_t is not None and imu_t > newest
        newest = imu_t if fresh else newest
        if window[0] <= m["t"] <= window[1]:
            kinds[fresh].append(m["compute_s"] * 1e3)
    return {"sample_tick_median_ms": _median(kinds[True]), "other_tick_median_ms": _median(kinds[False]),
            "sample_ticks": len(kinds[True]), "other_ticks": len(kinds[False])}


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else math.nan


def _model_file(cfg: Config) -> ModelFile:
    rng = np.random.default_rng(3)
    sizes = [6, *cfg.knode.hidden, 3]
    nets = tuple(
        NetworkWeights(
            tuple((rng.normal(0, 0.05 / np.sqrt(i), (o, i)), np.zeros(o)) for i, o in zip(sizes[:-1], sizes[1:])),
            Normalisation(np.zeros(6), np.full(6, 2.0), np.full(3, 0.3)),
        )
        for _ in range(cfg.knode.queue_size)
    )
    return ModelFile(hidden=cfg.knode.hidden, activation=cfg.knode.activation, queue_size=cfg.knode.queue_size,
                     networks=nets)


def run_timing_bench(quick: bool = False, progress: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    cfg = load_config()
    seconds = 2.0 if quick else 8.0
    rows: list[Timing] = []
    variants = [
        ("rti", "qrqp", True),
        ("rti", "qrqp", False),
        ("rti", "osqp", False),
        ("ipopt", "qrqp", False),
    ]
    for solver, qp, codegen in variants:
        ctrl = dataclasses.replace(cfg.controller, solver=solver, qp_solver=qp, codegen=codegen)
        c = dataclasses.replace(cfg, controller=ctrl)
        mpc = TranslationalMpc(ctrl, cfg.vehicle)
        for n_nets in (0, cfg.knode.queue_size):
            progress(f"MPC {mpc.backend}, {n_nets} networks")
            slot = ModelSlot(synthetic_queue(cfg.knode.hidden, n_nets), version=1) if n_nets else None
            mpc.reset()
            rows.extend(mpc_closed_loop(c, mpc, slot, seconds / (4 if solver == "ipopt" else 1)))
    progress("fast layer")
    rows.append(layer_tick(cfg, TranslationalMpc(cfg.controller, cfg.vehicle), seconds))
    progress("model swap")
    rows.append(swap_latency(cfg))
    progress("training rounds")
    rows.append(training_round(cfg, t_col=0.5, epochs=60, rounds=3 if quick else 6))
    rows.append(training_round(cfg, t_col=0.15, epochs=80, rounds=3 if quick else 6))
    progress("Foxglove view")
    from cfknode.app.bench.foxglove_cost import foxglove_samples

    rows.extend(Timing.of(*row) for row in foxglove_samples(2000 if quick else 8000))
    progress("lockstep flights")
    flights = {
        "nominal": lockstep_flight(cfg, None, 4.0 if quick else 20.0),
        "knode": lockstep_flight(cfg, synthetic_queue(cfg.knode.hidden, cfg.knode.queue_size), 4.0 if quick else 20.0),
        "nominal + adaptation (dob)": lockstep_flight(cfg, None, 4.0 if quick else 20.0, "dob"),
        "knode + adaptation (dob)": lockstep_flight(cfg, synthetic_queue(cfg.knode.hidden, cfg.knode.queue_size),
                                                    4.0 if quick else 20.0, "dob"),
    }
    by_name = {r.name: r for r in rows}
    ratios = _ratios(by_name)
    with_layer, without = flights["nominal + adaptation (dob)"], flights["nominal"]
    ratios["fast layer: lockstep tick median with / without"] = with_layer["tick_median_ms"] / without["tick_median_ms"]
    return {"timings": [dataclasses.asdict(r) for r in rows], "flights": flights, "ratios": ratios,
            "over_nominal_ms": over_nominal(flights)}


def over_nominal(flights: dict[str, dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Each flight's tick medians less the nominal flight's (ms), overall and by kind of tick: the fast layer's
    budget is stated as a time over plain MPC, not a ratio."""
    base = flights["nominal"]
    keys = ("tick_median_ms", "sample_tick_median_ms", "other_tick_median_ms")
    return {name: {k: f[k] - base[k] for k in keys} for name, f in flights.items() if name != "nominal"}


def _ratios(rows: dict[str, Timing]) -> dict[str, float]:
    """Speed-ups between rows of this run (median over median)."""
    out = {}
    rti = next((r for n, r in rows.items() if n.startswith("control step, rti-qrqp-codegen + KNODE")), None)
    ipopt = next((r for n, r in rows.items() if n.startswith("control step, ipopt + KNODE")), None)
    rti_nom = next((r for n, r in rows.items() if n == "MPC solve, rti-qrqp-codegen"), None)
    ipopt_nom = next((r for n, r in rows.items() if n == "MPC solve, ipopt"), None)
    if rti and ipopt:
        out["ipopt / rti-codegen, with KNODE (median)"] = ipopt.median_ms / rti.median_ms
    if rti_nom and ipopt_nom:
        out["ipopt / rti-codegen, nominal (median)"] = ipopt_nom.median_ms / rti_nom.median_ms
    if rti and rti_nom:
        out["KNODE cost: rti-codegen with / without (median)"] = rti.median_ms / rti_nom.median_ms
    return out


def render_timing(result: dict[str, Any], console: Any) -> None:
    from rich.table import Table

    table = Table(title="cfknode bench timing (this machine, this run)")
    for col in ("what", "n", "median ms", "p99 ms", "max ms", "note"):
        table.add_column(col, justify="left" if col in ("what", "note") else "right")
    for r in result["timings"]:
        table.add_row(r["name"], str(r["samples"]), f"{r['median_ms']:.3f}", f"{r['p99_ms']:.3f}",
                      f"{r['max_ms']:.3f}", r["note"])
    console.print(table)
    flights = Table(title="400 Hz lockstep flights (whole stack)")
    for col in ("model", "tick median ms", "tick p99 ms", "with a sample", "without", "missed / ticks",
                "speed x real time"):
        flights.add_column(col, justify="right")
    over = result.get("over_nominal_ms", {})
    for name, f in result["flights"].items():
        d = over.get(name)
        kinds = [f"{f[k]:.3f}" + (f" ({d[k]:+.3f})" if d else "") for k in ("sample_tick_median_ms", "other_tick_median_ms")]
        flights.add_row(name, f"{f['tick_median_ms']:.3f}" + (f" ({d['tick_median_ms']:+.3f})" if d else ""),
                        f"{f['tick_p99_ms']:.3f}", *kinds, f"{f['missed']} / {f['ticks']}", f"{f['speed_factor']:.1f}")
    console.print(flights)
    console.print("tick medians over the pattern; in brackets, over the nominal flight's (ms). \"with a sample\": "
                  "the ticks with a new accelerometer sample")
    for name, value in result["ratios"].items():
        console.print(f"ratio {name}: {value:.1f}x")


def add_timing_arguments(p: Any) -> None:
    p.add_argument("--quick", action="store_true", help="shorter runs (a smoke test, about 15 s)")
    p.add_argument("--json", dest="json_out", metavar="FILE", help="also write the results as JSON")


def run_timing(args: Any) -> int:
    """``cfknode bench timing``: print the table (and optionally write JSON)."""
    import json

    from rich.console import Console

    console = Console()
    result = run_timing_bench(quick=args.quick, progress=lambda what: console.print(f"[dim]timing {what}...[/]"))
    render_timing(result, console)
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(result, f, indent=1)
    return 0
