"""Simulated motion capture: samples the simulator's true state at the mocap frame rate.

Frames are due at multiples of ``1 / rate_hz``; each is taken from the first plant step
at or after its due time (the simulator reports every step through its step observer).
A frame gets Gaussian position noise and a small random rotation, may be dropped, and
becomes visible to ``latest(now)`` only once ``now >= sample_time + latency``. ``outages``
(fault injection) are time windows ``(t0, duration)`` in which no frame is sampled at all,
as when the rigid body is occluded; their frames count as dropouts.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from cfknode.mocap.source import MocapStats, Pose, RateMeter

# Float slack when comparing plant times (sums of 2 ms steps) against frame times.
_TIME_EPS = 1e-9
# Mixed into the seed so this noise stream differs from the simulator's own, which
# is seeded from the same ``sim.seed``.
_STREAM_KEY = 0x6D6F636170  # "mocap"


class _SteppedSim(Protocol):
    def add_step_observer(self, cb: Callable[[float, np.ndarray], None]) -> None: ...


class SimulatedMocap:
    """A ``PoseSource`` fed by the simulator's plant steps."""

    def __init__(
        self,
        sim: _SteppedSim,
        rate_hz: float,
        position_noise: float,
        attitude_noise: float,
        latency: float,
        dropout_prob: float,
        seed: int,
        outages: Sequence[tuple[float, float]] = (),
    ) -> None:
        if rate_hz <= 0:
            raise ValueError("rate_hz must be > 0")
        if not 0.0 <= dropout_prob < 1.0:
            raise ValueError("dropout_prob must be in [0, 1)")
        if position_noise < 0 or attitude_noise < 0 or latency < 0:
            raise ValueError("noise levels and latency must be >= 0")
        self._sim = sim
        self._rate = float(rate_hz)
        self._pos_noise = float(position_noise)
        self._att_noise = float(attitude_noise)
        self._latency = float(latency)
        self._dropout = float(dropout_prob)
        self._outages = tuple((float(t0), float(t0) + float(d)) for t0, d in outages)
        self._rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_STREAM_KEY,)))
        # The step observer cannot see the state at the current time, so the first
        # frame is the next frame time strictly after it.
        t0 = float(getattr(sim, "t", 0.0))
        self._next_k = math.floor(t0 * self._rate + _TIME_EPS) + 1
        self._next_t = self._next_k / self._rate
        self._pending: deque[Pose] = deque()  # sampled, not yet visible (latency)
        self._latest: Pose | None = None
        self._frames = 0
        self._dropouts = 0
        self._last_step_t = t0
        self._meter = RateMeter(window=1.0)
        # The simulator may step in another thread (--realtime) than the loop reads in.
        self._lock = threading.Lock()
        self._closed = False
        sim.add_step_observer(self._on_step)

    @classmethod
    def from_config(
        cls, sim: _SteppedSim, sim_cfg: Any, outages: Sequence[tuple[float, float]] = ()
    ) -> "SimulatedMocap":
        """Build from ``cfg.sim`` (a ``cfknode.app.config.SimConfig``), with optional outage windows."""
        return cls(
            sim,
            rate_hz=sim_cfg.mocap_rate_hz,
            position_noise=sim_cfg.mocap_position_noise,
            attitude_noise=sim_cfg.mocap_attitude_noise,
            latency=sim_cfg.mocap_latency,
            dropout_prob=sim_cfg.mocap_dropout_prob,
            seed=sim_cfg.seed,
            outages=outages,
        )

    def _on_step(self, t: float, state: np.ndarray) -> None:
        # Runs after every 2 ms plant step: keep the no-frame path to one comparison.
        if t < self._next_t - _TIME_EPS or self._closed:
            self._last_step_t = t
            return
        # Skip frame times already passed (only when the frame rate exceeds the step rate).
        self._next_k = max(self._next_k + 1, math.floor(t * self._rate + _TIME_EPS) + 1)
        self._next_t = self._next_k / self._rate
        rng = self._rng
        if self._outages and any(t0 - _TIME_EPS <= t < t1 - _TIME_EPS for t0, t1 in self._outages):
            with self._lock:
                self._dropouts += 1
                self._last_step_t = t
            return
        if self._dropout > 0.0 and rng.random() < self._dropout:
            with self._lock:
                self._dropouts += 1
                self._last_step_t = t
            return
        position = state[0:3] + self._pos_noise * rng.standard_normal(3)
        quaternion = _perturb(state[6:10], self._att_noise * rng.standard_normal(3))
        pose = Pose(t=t, position=position, quaternion=quaternion)
        with self._lock:
            self._pending.append(pose)
            self._frames += 1
            self._last_step_t = t
            self._meter.add(t)

    def latest(self, now: float) -> Pose | None:
        deadline = now - self._latency + _TIME_EPS
        with self._lock:
            pending = self._pending
            while pending and pending[0].t <= deadline:
                self._latest = pending.popleft()
            return self._latest

    def stats(self) -> MocapStats:
        with self._lock:
            return MocapStats(
                frames=self._frames,
                dropouts=self._dropouts,
                rate_hz=self._meter.rate(self._last_step_t),
            )

    def close(self) -> None:
        self._closed = True
        remove = getattr(self._sim, "remove_step_observer", None)
        if remove is not None:
            remove(self._on_step)


def from_config(sim: _SteppedSim, sim_cfg: Any) -> SimulatedMocap:
    """``SimulatedMocap`` configured from ``cfg.sim``."""
    return SimulatedMocap.from_config(sim, sim_cfg)


def _perturb(q: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """q (x) exp(rotvec): a small body-frame rotation applied to a scalar-first quaternion."""
    angle = math.sqrt(float(rotvec @ rotvec))
    if angle < 1e-12:
        dw, dx, dy, dz = 1.0, 0.0, 0.0, 0.0
    else:
        s = math.sin(0.5 * angle) / angle
        dw, dx, dy, dz = math.cos(0.5 * angle), s * rotvec[0], s * rotvec[1], s * rotvec[2]
    w, x, y, z = (float(v) for v in q)
    out = np.array(
        [
            w * dw - x * dx - y * dy - z * dz,
            w * dx + x * dw + y * dz - z * dy,
            w * dy - x * dz + y * dw + z * dx,
            w * dz + x * dy - y * dx + z * dw,
        ]
    )
    return out / math.sqrt(float(out @ out))
