"""A stalled flight loop never leaves the motors on a stale command: the radio's age check
(stale_setpoint.py) on an injected clock, the radio that uses it, and the signal relay."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

import pytest

from cfknode.app.backends.radio import HardwareRadio, LinkSafety
from cfknode.app.backends.stale_setpoint import FRESH, HOLD, RESUMED, STOP, ZERO, StaleGuard, StalePolicy, stale_phase
from cfknode.app.config import ConfigError, load_config
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.safety.signal_relay import relay_signals
from test_radio import FakeSim, sim_uri, wait_for  # noqa: F401 (sim_uri: the fixture, used by name)

FLY = (3.0, -2.0, 10.0, 40000)
HOLD_THRUST = 36000


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _guard(policy: StalePolicy = StalePolicy(4, 1.0)) -> tuple[StaleGuard, FakeClock, list[tuple[str, float]]]:
    clock = FakeClock()
    heard: list[tuple[str, float]] = []
    guard = StaleGuard(policy, clock)
    guard.set_hold(HOLD_THRUST, lambda phase, age: heard.append((phase, age)))
    return guard, clock, heard


SLOT = 2.0**-7  # s, a TX slot (128 Hz): exact in binary, so ages land exactly on the bounds


def _slots(guard: StaleGuard, clock: FakeClock, n: int, period: float = SLOT) -> list[Any]:
    out = []
    for _ in range(n):
        clock.t += period
        out.append(guard.outgoing())
    return out


def test_phase_by_slots_and_age() -> None:
    policy = StalePolicy(4, 1.0)
    assert stale_phase(5.0, 3, policy) == FRESH  # old, but the TX thread has not seen it resent long enough
    assert stale_phase(0.04, 4, policy) == HOLD
    assert stale_phase(1.0, 40, policy) == HOLD
    assert stale_phase(1.001, 40, policy) == STOP
    assert stale_phase(float("nan"), 4, policy) == STOP


@pytest.mark.parametrize("bad", [(0, 1.0), (2, 0.0), (2, float("inf")), (2.5, 1.0)])
def test_policy_refuses_nonsense(bad: tuple[Any, float]) -> None:
    with pytest.raises(ValueError, match="hold_slots|stop_after_s"):
        StalePolicy(*bad)


def test_a_fresh_setpoint_goes_out_as_it_is() -> None:
    guard, clock, heard = _guard()
    assert guard.outgoing() is None  # nothing before the loop's first setpoint
    for _ in range(20):  # the loop stamps between every two slots
        guard.stamp(FLY)
        assert _slots(guard, clock, 1) == [FLY]
    assert heard == [] and guard.phase == FRESH


def test_a_stall_holds_level_and_descending_then_stops_for_good() -> None:
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    sent = _slots(guard, clock, 150)  # 1.17 s of slots, no new setpoint
    hold = (0.0, 0.0, 0.0, HOLD_THRUST)
    assert sent[:4] == [FLY] * 4  # the slot after the stamp, then three resends
    first_hold = sent.index(hold)
    assert first_hold == 4
    first_zero = sent.index(ZERO)
    assert set(sent[first_hold:first_zero]) == {hold}
    assert set(sent[first_zero:]) == {ZERO}
    assert first_zero == 128  # the first slot past 1.0 s (its 129th)
    assert heard == [(HOLD, 5 * SLOT), (STOP, 129 * SLOT)]
    assert guard.stopped and guard.holds == 1 and guard.stops == 1
    guard.stamp(FLY)  # the loop comes back: the stop is latched
    assert _slots(guard, clock, 3) == [ZERO] * 3


def test_a_short_stall_holds_then_flies_on() -> None:
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    assert _slots(guard, clock, 6)[-1] == (0.0, 0.0, 0.0, HOLD_THRUST)
    guard.stamp((1.0, 1.0, 0.0, 39000))
    assert _slots(guard, clock, 1) == [(1.0, 1.0, 0.0, 39000)]
    assert guard.phase == FRESH and not guard.stopped
    assert heard == [(HOLD, 5 * SLOT), (RESUMED, 6 * SLOT)]  # and how long the loop was gone


def test_the_hold_never_asks_for_more_thrust_than_the_loop_did() -> None:
    guard, clock, _ = _guard()
    guard.stamp((0.0, 5.0, 0.0, 20000))  # touching down
    assert _slots(guard, clock, 6)[-1] == (0.0, 0.0, 0.0, 20000)


def test_over_another_drone_the_hold_is_level_at_the_hover_thrust_capped_by_the_loop() -> None:
    guard, clock, _ = _guard()
    guard.hold_level(38000)  # the fleet: a drone below this one
    guard.stamp(FLY)
    assert _slots(guard, clock, 6)[-1] == (0.0, 0.0, 0.0, 38000)  # level, not the descending 36000
    guard.stamp((0.0, 5.0, 0.0, 37000))  # never more than the loop last asked for
    assert _slots(guard, clock, 6)[-1] == (0.0, 0.0, 0.0, 37000)
    guard.hold_level(None)  # nothing below any more: descend again
    assert _slots(guard, clock, 1) == [(0.0, 0.0, 0.0, HOLD_THRUST)]


def test_zero_thrust_is_never_replaced_nor_stopped() -> None:
    # A landed drone whose loop has ended (a fleet's others still flying) keeps its heartbeat.
    guard, clock, heard = _guard()
    guard.stamp(ZERO)
    assert set(_slots(guard, clock, 300)) == {ZERO}
    assert heard == [] and not guard.stopped


def test_a_process_frozen_as_a_whole_is_not_a_stall() -> None:
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    assert _slots(guard, clock, 1, period=0.5) == [FLY]  # the TX thread woke once, 0.5 s late
    guard.stamp(FLY)  # and the loop right after it
    assert _slots(guard, clock, 3) == [FLY] * 3
    assert heard == []


def test_the_second_stop_signal_during_a_stall_stops_at_once() -> None:
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    guard.stop_signal(2)  # not stalled: the loop's supervisor acts on it
    assert guard.phase == FRESH
    _slots(guard, clock, 10)
    guard.stop_signal(1)  # the first lands: the hold is that landing
    assert guard.phase == HOLD
    guard.stop_signal(2)
    assert guard.stopped and _slots(guard, clock, 1) == [ZERO]
    assert [p for p, _ in heard] == [HOLD, STOP]


def test_a_raising_listener_does_not_stop_the_guard() -> None:
    clock = FakeClock()
    guard = StaleGuard(StalePolicy(1, 0.05), clock)

    def boom(phase: str, age: float) -> None:
        raise RuntimeError("listener")

    guard.set_hold(HOLD_THRUST, boom)
    guard.stamp(FLY)
    assert _slots(guard, clock, 10)[-1] == ZERO


def test_config_keys_and_their_order() -> None:
    cfg = load_config()
    assert (cfg.radio.stale_hold_slots, cfg.radio.stale_stop_s) == (4, 1.0)
    with pytest.raises(ConfigError, match="stale_stop_s"):
        load_config(overrides={"radio.stale_stop_s": 2.5})
    with pytest.raises(ConfigError, match="stale_hold_slots"):
        load_config(overrides={"radio.stale_hold_slots": 0})
    with pytest.raises(ConfigError, match="must be longer than radio.stale_hold_slots"):
        load_config(overrides={"radio.stale_hold_slots": 40, "radio.stale_stop_s": 0.3})


# --- the radio: what reaches the firmware when nobody stamps -------------------------------------

def test_a_threaded_radio_holds_then_stops_and_ends_the_heartbeat(sim_uri: tuple[FakeSim, str], tmp_path: Any) -> None:
    sim, uri = sim_uri
    radio = HardwareRadio(uri, params={}, lockstep=False, rw_cache=str(tmp_path), reboot_after_heartbeat=False,
                          safety=LinkSafety(heartbeat_hz=50.0, stale=StalePolicy(3, 0.3)))
    heard: list[str] = []
    radio.set_stale_hold(AttitudeSetpoint(0.0, 0.0, 0.0, HOLD_THRUST), lambda phase, age: heard.append(phase))
    radio.connect(timeout=5.0)
    try:
        radio.set_setpoint(AttitudeSetpoint(3.0, -2.0, 10.0, 40000))  # then the loop stalls
        assert wait_for(lambda: radio.stats().stale_stops == 1, timeout=20.0)
        assert wait_for(lambda: sum(1 for c in sim.firmware.named("rpyt") if c[-1] == 0) >= 5, timeout=20.0)
    finally:
        radio.shutdown()
    calls = sim.firmware.calls
    rpyt = [i for i, c in enumerate(calls) if c[0] == "rpyt"]
    thrusts = [calls[i][-1] for i in rpyt]
    first_hold = thrusts.index(HOLD_THRUST)
    first_zero = thrusts.index(0, first_hold)
    assert set(thrusts[1:first_hold]) == {40000}  # after the unlock: the loop's, while fresh
    assert all(calls[i][2:5] == (0.0, 0.0, 0.0) for i in rpyt[first_hold:first_zero])  # level, no yaw rate
    assert set(thrusts[first_hold:first_zero]) == {HOLD_THRUST}
    assert set(thrusts[first_zero:]) == {0}
    heartbeats = [i for i, c in enumerate(calls) if c[0] == "heartbeat"]
    assert heartbeats and max(heartbeats) < rpyt[first_zero]  # none once the motors are off
    assert heard == [HOLD, STOP]
    assert radio.stats().stale_holds == 1


# --- the signal relay --------------------------------------------------------------------------


class Target:
    def __init__(self) -> None:
        self.calls: list[tuple[str, int]] = []
        self.got = threading.Event()

    def interrupt(self, signal_name: str) -> None:
        self.calls.append((signal_name, threading.get_ident()))
        self.got.set()


def test_a_signal_reaches_the_target_while_the_main_thread_is_blocked() -> None:
    target = Target()
    before = signal.getsignal(signal.SIGTERM)
    with relay_signals(target, (signal.SIGTERM,)) as installed:
        assert installed
        sender = threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGTERM))
        sender.start()
        # The main thread stays blocked here; only the relay thread can end the wait early.
        assert target.got.wait(timeout=60.0)
        sender.join()
    assert [name for name, _ in target.calls] == ["SIGTERM"]
    assert target.calls[0][1] != threading.main_thread().ident
    assert signal.getsignal(signal.SIGTERM) is before


def test_other_signals_go_on_to_the_wakeup_fd_that_was_there() -> None:
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    old_fd = signal.set_wakeup_fd(write_fd)
    previous = signal.signal(signal.SIGUSR1, lambda *a: None)
    target = Target()
    try:
        with relay_signals(target, (signal.SIGTERM,)):
            os.kill(os.getpid(), signal.SIGUSR1)
            os.kill(os.getpid(), signal.SIGTERM)
        assert signal.set_wakeup_fd(old_fd) == write_fd  # put back on exit
        assert os.read(read_fd, 16) == bytes([signal.SIGUSR1])
        assert [name for name, _ in target.calls] == ["SIGTERM"]
    finally:
        signal.signal(signal.SIGUSR1, previous)
        os.close(read_fd)
        os.close(write_fd)


def test_the_relay_off_the_main_thread_is_not_installed() -> None:
    out: list[bool] = []

    def run() -> None:
        with relay_signals(Target(), (signal.SIGTERM,)) as installed:
            out.append(installed)

    worker = threading.Thread(target=run)
    worker.start()
    worker.join()
    assert out == [False]


def test_an_operator_stop_stops_a_stalled_loop_at_once_and_leaves_a_ticking_one_to_its_supervisor() -> None:
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    guard.operator_stop()  # the loop ticks: its supervisor stops the motors at its next tick
    assert _slots(guard, clock, 1) == [FLY] and guard.phase == FRESH
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    out = _slots(guard, clock, 6)  # stalled: holding from the fifth slot
    assert out[-1] == (0.0, 0.0, 0.0, HOLD_THRUST) and guard.phase == HOLD
    guard.operator_stop()  # e.g. ``cfknode estop`` taken by the mailbox's watch thread
    assert guard.phase == STOP and guard.stops == 1 and heard[-1][0] == STOP
    assert _slots(guard, clock, 2) == [ZERO, ZERO]
    guard, clock, heard = _guard()
    guard.stamp(FLY)
    _slots(guard, clock, 2)  # stalled, not yet holding: the request waits for the slot the hold would start
    guard.operator_stop()
    assert _slots(guard, clock, 3)[-1] == ZERO and guard.stops == 1
