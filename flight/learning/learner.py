"""Online learning, flight side (the paper's Algorithm 1): the learner that ties the parts together.

No torch here: the trainer is a child process (``cfknode.models.trainer_process``); this side sends numpy windows.

One ``OnlineLearner`` is a loop observer. Its ``on_tick`` runs after every tick's setpoint is
decided, i.e. between ticks, and does, in order:

1. record the tick (``WindowRecorder``, ``windows.py``): airborne MPC ticks are cut into windows of
   ``t_col``; a model change discards the partial window, so every window was flown under one model;
2. watch the ticks right after a swap: MPC fallbacks there roll the model back;
3. every ``online.monitor_every_ticks``, judge the flying model (``ModelMonitor``, ``monitor.py``): one
   that explains the newest motion clearly worse than nominal is dropped for nominal;
4. talk to the trainer (``TrainerClient``, ``trainer_client.py``): at most one request outstanding; a
   newer finished window replaces an unsent older one; crashes and hangs restart the trainer;
5. a finished candidate goes through the validation gate (``gate_steps``, ``gate.py``), one slice of up
   to about a millisecond per tick gap, and is then swapped into the ``ModelSlot``: a reference
   assignment, so no rebuild.

Honest latency in lockstep simulation: a model is applied no earlier than the moment its
request was sent (its window's end) plus the observed training round trip. The simulation is
paced only while the trainer works (a round, or a restart after a fault), and only when sim
time would otherwise run ahead of the wall time the trainer has had (the loop blocks on the
result pipe until the wall catches up); the rest of the flight runs at full lockstep speed.
That is the ``wall`` latency policy. With ``cpu`` or ``fixed`` (``latency.py``) the
delay comes from the trainer's report instead and the flight is never paced: a result counts
as received at exactly send time + delay in flight time, and the loop blocks on the trainer
only when flight time reaches the earliest moment the result could apply. The flight then
depends only on the trainer's outputs, not on how loaded the machine is. ``paper_lockstep``
instead waits for every model and applies it at once, as the paper's code does (reproduction only).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import replace
from typing import Any, Callable

import numpy as np

from cfknode.flight.learning.monitor import ModelMonitor
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.learning.gate import GateVerdict
from cfknode.flight.learning.install import GateRules, TrainerJudging, held_out_tail, install_steps
from cfknode.flight.learning.latency import applied_latency
from cfknode.flight.learning.rejudge import FlyingRejudge
from cfknode.flight.learning.windows import TickLike, WindowRecorder, nothing_to_learn_above
from cfknode.flight.learning.trainer_client import TrainerClient, TrainerFault
from cfknode.models.modelfile import ModelFile
from cfknode.models.residual_check import SCORE_KEY
from cfknode.models.trainer_process import JobOutcome, TrainerReady, TrainOutcome, TrainRequest, Window

from cfknode.flight.learning.records import (  # noqa: F401 (re-exported: the app and tests use them)
    LearnerSettings, Log, OnlineStats, RoundRecord, SwapEvent, _ENDING_STATES, _Flying, _Gating, _Held, _Outstanding,
    _PaceFrom, _Watch,
)
from cfknode.flight.learning.reports import LearnerReports, SwapTimes


class OnlineLearner(LearnerReports, TrainerJudging, FlyingRejudge):
    """The flight side of online learning: a ``TickObserver`` (see the module docstring)."""

    def __init__(
        self,
        settings: LearnerSettings,
        slot: ModelSlot,
        client: TrainerClient,
        log: Log,
        base: ModelFile | None = None,
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.s = settings
        self.slot = slot
        self.client = client
        self.log = log
        self._wall = wall
        self.recorder = WindowRecorder(settings.t_col, 1.0 / settings.period, settings.start_time, ground_z=settings.ground_z,
                                       min_height=settings.min_height, neighbour=getattr(slot, "neighbour", None),
                                       wake_only=settings.wake_only, command_lag_s=settings.command_lag_s)
        self.monitor = ModelMonitor(settings.monitor, 1.0 / settings.period) if settings.monitor is not None else None
        n0 = len(base.networks) if base is not None else 0
        self._flying = _Flying(slot.model, slot.version, base, (slot.version,) * n0)
        self._next_version = slot.version + 1
        self._round = 0
        self._pending: Window | None = None  # newest finished window not yet sent
        self._recent: deque[Window] = deque(maxlen=settings.replay_windows + 1)
        self._out: _Outstanding | None = None
        self._pace_from: _PaceFrom | None = None
        self._held: _Held | None = None
        self._gating: _Gating | None = None
        self._watch: _Watch | None = None
        self._arrived: TrainOutcome | None = None  # cpu/fixed latency: a result not yet due in flight time
        self.failed = False  # restarts exhausted: learning stopped, flight goes on
        self.ending = False  # the supervisor is landing or has ended the flight: no trainer restarts
        self._install_work_s = 0.0  # wall time of the last on_tick when it folded, gated or swapped a model
        self._rules = GateRules(settings.gate, settings.filter_hz, settings.limits)
        self._held_rules = (None if settings.held_limits is None
                            else GateRules(settings.gate, settings.filter_hz, settings.held_limits))
        self.stats = OnlineStats()
        self.rounds: list[RoundRecord] = []
        self.swaps: list[SwapEvent] = []
        self.windows: list[tuple[int, float, float, int]] = []  # (index, t0, t1, version) of finished windows
        self.recent_models: deque[tuple[int, ModelFile]] = deque(maxlen=8)  # newest swapped-in files, for inspection
        self.attitude_lag: Any = None  # the attitude loop's lag identified beside it (attitude_lag.py), for the summary

    # The loop calls this after every tick.
    def on_tick(self, tick: TickLike) -> None:
        if self._install_work_s > 0.0 and tick.compute_s + self._install_work_s > self.s.period:
            self.stats.late_ticks += 1  # on a wall clock this tick started late because of the install work
        start, paced = self._wall(), self.stats.pace_wait_s
        installing = self._gating is not None or self._held is not None
        self._on_tick(tick)
        installing = installing or self._gating is not None
        # Pacing (lockstep waiting for the trainer) is simulated wall time, not work.
        self._install_work_s = (self._wall() - start) - (self.stats.pace_wait_s - paced) if installing else 0.0

    def _on_tick(self, tick: TickLike) -> None:
        t = tick.t
        if getattr(tick, "supervisor_state", "") in _ENDING_STATES:
            self.ending = True
        window = self.recorder.add(tick)
        if window is not None:
            self._on_window(window)
        if self._watch is not None:
            self._watch_tick(tick)
        if getattr(tick, "guarded", False) and self._flying.model is not None:  # the thrust changed under it
            self._drop(t, f"model {self._flying.version} was fitted before the lost thrust the fall guard caught")
        elif self.monitor is not None and not self.s.paper_lockstep:
            self._monitor_tick(tick)
        if self.failed:
            return
        if self.s.paper_lockstep:
            self._paper_step(t)
        else:
            self._service(t)

    # --- honest mode -------------------------------------------------------------------------

    def _service(self, t: float) -> None:
        if self.s.lockstep and self.s.latency.sim_time:
            self._service_sim_time(t)
            return
        timeout = 0.0
        pace = self._pace_from
        if pace is not None and self.s.lockstep and self.client.state in ("busy", "starting"):
            # Pace: the next tick may not start before the trainer has had as much wall time as
            # the simulation will have advanced since the round (or restart) began.
            timeout = max(0.0, (self._next_tick_time(t) - pace.t) - (self._wall() - pace.wall))
        waited = self._wall() if timeout > 0.0 else 0.0  # the wall is read only while pacing
        event = self.client.poll(timeout)
        if timeout > 0.0:
            self.stats.pace_wait_s += self._wall() - waited
        if event is not None:
            self._pace_from = None
            self._on_event(event, t)
        self._advance(t)

    def _service_sim_time(self, t: float) -> None:
        """cpu/fixed latency: the trainer's result is taken at send + delay in flight time, whatever the wall did."""
        waited = self._wall()
        while self.client.state == "starting":  # a restart: the flight waits for it, so the wall does not leak in
            event = self.client.poll(1.0)
            if event is not None:
                self._on_event(event, t)
        nxt = self._next_tick_time(t)
        out = self._out
        if out is not None and self._arrived is None and self.client.state == "busy":
            # Block only once the next tick could fly the result: before that no answer can change the flight.
            must_wait = nxt >= out.sent_t + self.s.latency.floor_s - 1e-9
            while self._out is out and self._arrived is None and self.client.state == "busy":
                event = self.client.poll(self.client.timeout if must_wait else 0.0)
                if isinstance(event, TrainOutcome) and event.round == out.request.round:
                    self._arrived = event
                elif event is not None:
                    self._on_event(event, t)  # a fault, a stale result, a ready note: as they come
                elif not must_wait:
                    break
        self.stats.pace_wait_s += self._wall() - waited
        if self._arrived is not None and self._out is not None:
            due = self._out.sent_t + self._delay(self._arrived)
            if nxt >= due - 1e-9:
                event, self._arrived = self._arrived, None
                self._on_event(event, t)
        self._advance(t)

    def _advance(self, t: float) -> None:
        """Between ticks: one gate slice (or start the held candidate's gate), then send a waiting window."""
        if self._gating is not None:
            self._step_gate(t)
        elif self._held is not None:
            self._start_gate(t)
        self._maybe_send(t)

    def _delay(self, event: TrainOutcome) -> float:
        out = self._out
        wall = self._wall() - out.sent_wall if out is not None else math.nan
        return applied_latency(self.s.latency, event.cpu_s, wall)

    def _maybe_send(self, t: float) -> None:
        if self._arrived is not None:
            return  # the trainer is idle, but in flight time its result is still on the way
        if self._held is not None or self._gating is not None or self._pending is None:
            return
        if self._job_out and self.s.lockstep:
            self._await_job(t)  # a discarded candidate's verdict: the window goes out on the tick it would have
        if self.client.state != "idle":
            return
        window, self._pending = self._pending, None
        if window.version != self._flying.version:
            self.stats.windows_stale += 1
            return
        earlier = [w for w in self._recent if w.index < window.index]
        replay = tuple(earlier[-self.s.replay_windows :]) if self.s.replay_windows > 0 else ()
        if self.s.wake_only and (count := nothing_to_learn_above((window, *replay))):
            setattr(self.stats, count, getattr(self.stats, count) + 1)  # a network of the neighbour alone learns nothing
            return
        self._round += 1
        holdout = self.s.holdout_fraction if (self.s.paper_lockstep and self.s.gate) else 0.0
        request = TrainRequest(self._round, self._next_version, window, replay, self._flying.file, holdout)
        self._next_version += 1
        self.client.submit(request)
        self._out = _Outstanding(request, t, self.client.sent_wall)
        self._pace_from = _PaceFrom(t, self.client.sent_wall)
        self.stats.rounds_sent += 1

    def _on_window(self, window: Window) -> None:
        self.windows.append((window.index, window.t0, window.t1, window.version))
        self._recent.append(window)
        if self._pending is not None:
            self.stats.windows_superseded += 1  # no backlog: the newest window wins
        self._pending = window

    def _on_event(self, event: Any, t: float) -> None:
        if isinstance(event, TrainOutcome):
            out, self._out = self._out, None
            if out is None or out.request.round != event.round:
                return  # a result from before a restart: nothing waits for it
            sim_time = self.s.lockstep and self.s.latency.sim_time and not self.s.paper_lockstep
            latency = applied_latency(self.s.latency, event.cpu_s, self._wall() - out.sent_wall) if sim_time \
                else self._wall() - out.sent_wall
            self.stats.latency_s.append(latency)
            self.stats.train_wall_s.append(event.wall_s)
            self.stats.trainer_cpu_s += event.cpu_s
            self._log_training(t, event, latency)
            if event.model is None:
                self.stats.rounds_failed += 1
                self._record(event, out.sent_t, latency, "failed", event.error, received_t=t)
                self._log_model(t, event.version, "reject", f"training failed: {event.error}", event, latency)
                self.stats.rejected += 1
                return
            self.stats.rounds_trained += 1
            # On a wall clock the round trip has already elapsed in flight time; in lockstep it is added.
            apply_at = out.sent_t + latency if self.s.lockstep and not self.s.paper_lockstep else t
            self._held = _Held(event, out.request.window, t, out.sent_t, latency, apply_at)
        elif isinstance(event, JobOutcome):
            self._on_job(event, t)
        elif isinstance(event, TrainerFault):
            self._on_fault(event, t)
        elif isinstance(event, TrainerReady):
            self._log_event(t, "info", f"trainer ready (pid {event.pid}, warm-up {event.warmup_s:.2f} s)")

    def _on_fault(self, fault: TrainerFault, t: float) -> None:
        out, self._out = self._out, None
        self._arrived = None
        self._lose_job(t, fault.kind)
        version = out.request.version if out is not None else self._flying.version
        if fault.kind == "hang":
            self.stats.hangs += 1
        else:
            self.stats.crashes += 1
        if out is not None:
            r = out.request
            self.rounds.append(RoundRecord(r.round, r.version, (r.window.t0, r.window.t1), out.sent_t, math.nan,
                                           math.nan, math.nan, math.nan, "lost", fault.reason))
        self._log_model(t, version, "crash", f"{fault.kind}: {fault.reason}")
        if self.ending:
            # A model trained now would never fly, and a new trainer would outlive the flight's end.
            self.failed = True
            self._log_event(t, "warning", "online trainer lost while the flight is ending; not restarted")
            return
        if self.stats.restarts >= self.s.max_restarts:
            self.failed = True
            self._log_event(t, "error", f"online trainer failed {self.stats.restarts + 1} times; learning stopped, "
                            f"flying model {self._flying.version} to the end")
            return
        self.stats.restarts += 1
        self.client.start()
        self._pace_from = _PaceFrom(t, self.client.start_wall)  # a restart costs flight time too
        self._log_model(t, self._flying.version, "restart", f"trainer restart {self.stats.restarts} of {self.s.max_restarts}")

    # --- gate and swap -----------------------------------------------------------------------

    def _next_tick_time(self, t: float) -> float:
        """Earliest flight time of the next tick: tick k runs at the first clock reading >= k * period
        (a lockstep clock reads in plant steps), so the next one is at (floor(t / period) + 1) * period or later."""
        return (math.floor(t / self.s.period + 1e-9) + 1) * self.s.period

    def _start_gate(self, t: float) -> None:
        """Begin installing the held result once honest latency and fresh data allow it."""
        held = self._held
        assert held is not None
        if self._next_tick_time(t) < held.apply_at - 1e-9:
            return  # honest latency: the next tick is still too early for this model
        out = held.outcome
        if (not self.s.paper_lockstep and self.s.gate and out.base_version == self._flying.version
                and self.recorder.count_after(out.window_t1) - 1 < self.s.gate_min_pairs):
            return  # not enough fresh data yet to judge it
        self._held = None
        start = self._wall()
        if self.s.paper_lockstep:
            # No fresh data exists (the paper applies at once): judge on the window's held-out tail.
            fresh = held_out_tail(out, held.window)
        else:
            fresh = self.recorder.fresh(out.window_t1)
        assert out.model is not None
        current = self._flying.model
        rules = self._rules_for(out.window_t1)
        g = _Gating(held, None, install_steps(out.model, current, held.window, fresh, rules), 0.0, 0.0)
        if not self.s.paper_lockstep:
            self._send_gate_job(g, current, fresh, rules)
        g.work_s = g.max_slice_s = self._wall() - start
        self._gating = g

    def _step_gate(self, t: float) -> None:
        """One slice of the gate per tick gap; the swap itself (a reference write) follows the last slice."""
        g = self._gating
        assert g is not None
        start = self._wall()
        if g.job:
            self._step_judged(t, g, start)
            return
        try:
            next(g.steps)
        except StopIteration as done:
            self._gating = None
            verdict, g.candidate = done.value
            self._finish_gate(t, g, verdict, start)
            return
        slice_s = self._wall() - start
        g.work_s += slice_s
        g.max_slice_s = max(g.max_slice_s, slice_s)

    def _finish_gate(self, t: float, g: _Gating, verdict: GateVerdict, start: float) -> None:
        held, out = g.held, g.held.outcome
        if out.base_version != self._flying.version:
            self._reject(t, held, f"stale: trained on version {out.base_version}, flying {self._flying.version}", None)
            return
        if not verdict.accepted:
            self._reject(t, held, verdict.reason, verdict)
            self._rejudge(t, verdict)
            return
        candidate, candidate_file = g.candidate, out.model
        assert candidate_file is not None and candidate is not None
        if verdict.score:  # beside the layer it flies only on the axes it earned, as a stored score does offline
            # An axis at or below the gate's min_score (online.gate_layer_min_score) earned nothing there.
            score = np.asarray(verdict.score, dtype=np.float64)
            candidate.beyond_layer = np.where(score > self.s.limits.min_score, score, 0.0)
            candidate_file = replace(candidate_file, extra={**candidate_file.extra, SCORE_KEY: list(verdict.score)})
        queue = (self._flying.queue + (out.version,))[-self.s.queue_size :]
        previous = self._flying
        record = self.slot.swap(candidate, out.version, t)
        last_slice = self._wall() - start
        install_s = g.work_s + last_slice
        self.stats.max_slice_s = max(self.stats.max_slice_s, g.max_slice_s, last_slice)
        self._flying = _Flying(candidate, out.version, candidate_file, queue)
        self.recent_models.append((out.version, candidate_file))
        self._model_changed()
        self._watch = _Watch(previous, out.version, self.s.rollback_ticks)
        self.stats.accepted += 1
        self.stats.swap_s.append(record.swap_s)
        self.stats.install_s.append(install_s)
        max_slice = max(g.max_slice_s, last_slice)
        self.swaps.append(SwapEvent(t, out.version, record.swap_s, install_s, max_slice, "swap"))
        self._record(out, held.sent_t, held.latency_s, "swap", "", t, verdict, held.received_t)
        self._log_model(t, out.version, "swap", "", out, held.latency_s, verdict,
                        SwapTimes(record.swap_s, install_s, max_slice))

    def _reject(self, t: float, held: _Held, reason: str, verdict: GateVerdict | None) -> None:
        self.stats.rejected += 1
        self._record(held.outcome, held.sent_t, held.latency_s, "reject", reason, math.nan, verdict, held.received_t)
        self._log_model(t, held.outcome.version, "reject", reason, held.outcome, held.latency_s, verdict)

    def _model_changed(self) -> None:
        """Every model change ends the run: no window spans it, and unsent windows are stale."""
        self.recorder.reset()
        if self._pending is not None:
            self.stats.windows_stale += 1
            self._pending = None

    # --- rollback ----------------------------------------------------------------------------

    def _watch_tick(self, tick: TickLike) -> None:
        w = self._watch
        assert w is not None
        if tick.source == "fallback":
            w.fallbacks += 1
        w.ticks_left -= 1
        if w.fallbacks >= self.s.rollback_fallbacks:
            self._rollback(tick.t, w)
        elif w.ticks_left <= 0:
            self._watch = None

    def _rollback(self, t: float, w: _Watch) -> None:
        self._watch = None
        prev = w.previous
        record = self.slot.swap(prev.model, prev.version, t)
        self._flying = prev
        self._model_changed()
        self._discard_pending_candidates(t, "rolled back")
        self.stats.rollbacks += 1
        self.swaps.append(SwapEvent(t, prev.version, record.swap_s, record.swap_s, record.swap_s, "rollback"))
        reason = f"{w.fallbacks} MPC fallbacks in the {self.s.rollback_ticks - w.ticks_left} ticks after swapping in {w.version}"
        self._log_model(t, prev.version, "rollback", reason, times=SwapTimes(record.swap_s))

    def _discard_pending_candidates(self, t: float, what: str) -> None:
        """A result waiting for the gate, or in it, was trained on the model just replaced: reject it as stale."""
        for held in (self._held, self._gating.held if self._gating is not None else None):
            if held is not None:
                self._reject(t, held, f"stale: its base {held.outcome.base_version} was {what}", None)
        self._held = self._gating = None

    # --- model monitor -----------------------------------------------------------------------

    def _monitor_tick(self, tick: TickLike) -> None:
        monitor, rec = self.monitor, self.recorder  # the recorder's command: what the networks were trained on
        assert monitor is not None
        if not rec.last_added:
            monitor.reset()  # the same ticks the windows use: airborne, flown by the MPC
            return
        if monitor.add(tick.t, tick.est.v, rec.last_u, rec.last_nb) and self._flying.model is not None:
            verdict = monitor.judge(self._flying.model)
            if verdict.drop:
                self._drop(tick.t, f"model {self._flying.version} predicts the last {verdict.ticks} ticks worse than "
                           f"nominal ({verdict.error_model:.2f} vs {verdict.error_nominal:.2f} m/s^2 mean acceleration error)")

    def _drop(self, t: float, reason: str) -> None:
        """Fly nominal: the flying model explains the newest motion worse than none, or the fall guard caught a
        lost thrust the model was fitted without."""
        self.stats.drops += 1
        self._replace_flying(t, None, None, (), "drop", reason)
        self._log_event(t, "warning", f"online: {reason}; flying nominal until the next accepted model")

    def _replace_flying(self, t: float, model: Any, file: ModelFile | None, queue: tuple[int, ...], event: str,
                        reason: str) -> None:
        """Fly ``model`` (None: nominal) from the next tick, a new version: what is trained on the old is stale."""
        version, self._next_version = self._next_version, self._next_version + 1
        record = self.slot.swap(model, version, t)
        self._flying = _Flying(model, version, file, queue)
        self._model_changed()
        self._watch = None
        self._discard_pending_candidates(t, {"drop": "dropped", "narrow": "narrowed"}.get(event, event))
        self.swaps.append(SwapEvent(t, version, record.swap_s, record.swap_s, record.swap_s, event))
        self._log_model(t, version, event, reason, times=SwapTimes(record.swap_s))

    # --- paper lockstep ----------------------------------------------------------------------

    def _paper_step(self, t: float) -> None:
        """The paper's code: every window is trained at once while the simulation waits."""
        event = self.client.poll(0.0)
        if event is not None:
            self._on_event(event, t)
        if self._pending is None:
            return
        while self.client.state == "starting":  # a restart: wait for it (the client reports one that never comes up)
            event = self.client.poll(1.0)
            if event is not None:
                self._on_event(event, t)
        self._maybe_send(t)
        while self._out is not None:
            event = self.client.poll(self.client.timeout)
            if event is not None:
                self._on_event(event, t)
        if self._held is not None:
            self._start_gate(t)
        while self._gating is not None:  # the simulation waits anyway: the whole gate at once
            self._step_gate(t)


__all__ = ["LearnerSettings", "OnlineLearner", "OnlineStats", "RoundRecord", "SwapEvent"]
