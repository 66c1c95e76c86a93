"""The simulator as a motioncapture client: every frame, in order, stamped when the simulated system sent it."""

from __future__ import annotations

import time

import numpy as np

from cfknode.app.backends.sim_mocap import SimulatedMotionCaptureClient
from cfknode.app.config import load_config
from cfknode.mocap.motioncapture_source import MotioncaptureSource
from cfknode.sim_backend.crazyflie import SimCrazyflie

BASE = 1000.0  # the monotonic time of simulator time 0, for the stamps


def simulator() -> SimCrazyflie:
    cfg = load_config(overrides={"sim.mocap_rate_hz": 100.0})
    return SimCrazyflie(cfg.vehicle, cfg.sim)


def test_frames_sent_in_a_burst_all_arrive_in_order_stamped_when_sent() -> None:
    sim = simulator()
    client = SimulatedMotionCaptureClient({"cf1": sim}, rate_hz=100.0, frame_time=lambda t: BASE + t)
    sim.step_to(0.5)  # a simulator catching up half a second at once, nobody reading meanwhile
    stamps = []
    for _ in range(50):
        client.waitForNextFrame()
        assert "cf1" in client.rigidBodies
        stamps.append(client.frame_monotonic)
    client.close()
    gaps = np.diff(stamps)
    assert np.allclose(gaps, 0.01, atol=1e-9), gaps  # the stream's own rate, not the burst's
    assert BASE <= stamps[0] and stamps[-1] <= BASE + 0.5


def test_without_a_frame_time_frames_carry_no_stamp() -> None:
    sim = simulator()
    client = SimulatedMotionCaptureClient({"cf1": sim}, rate_hz=100.0)
    sim.step_to(0.05)
    client.waitForNextFrame()
    assert client.frame_monotonic is None  # the reader stamps it on arrival
    client.close()


def test_the_source_keeps_every_frame_of_a_burst_and_its_stamp() -> None:
    sim = simulator()
    client = SimulatedMotionCaptureClient({"cf1": sim}, rate_hz=100.0, frame_time=lambda t: BASE + t)
    source = MotioncaptureSource.open("mock", "", "cf1", connect=lambda kind, cfg: client)
    try:
        sim.step_to(1.0)
        sent = int(round(1.0 * 100))
        end = time.monotonic() + 30.0  # a hang guard, not a timing test
        while source.stats().frames < sent and time.monotonic() < end:
            time.sleep(0.01)
        assert source.stats().frames == sent and source.stats().dropouts == 0
        latest = source.status().latest
        assert latest is not None and abs(latest.t - (BASE + 1.0)) < 0.011  # stamped when sent, not when read
    finally:
        source.close()
