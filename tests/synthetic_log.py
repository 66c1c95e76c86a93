"""A synthetic flight log written with the real writer: the channels and rates of a lockstep flight.

For tests that need a long log (memory bounds of the readers) without flying minutes: the
messages have the fields and full-precision floats of real ones (400 Hz ticks, 100 Hz mocap,
10 Hz safety), on a circle at 1 m.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from cfknode.app.logs.writer import FlightLog

CONFIG = {
    "controller": {"kind": "mpc", "solver": "rti", "rate_hz": 400.0},
    "trajectory": {"kind": "circle", "radius": 0.5, "speed": 0.4, "height": 1.0},
    "sim": {"initial_position": [0.0, 0.0, 0.0], "mass_changes": []},
}


def write_synthetic_flight(directory: str | Path, seconds: float, rate_hz: float = 400.0) -> Path:
    """Write ``seconds`` of flight into a new log in ``directory``; returns its path."""
    with FlightLog.create(directory, CONFIG, "synthetic", "synthetic") as log:
        log.write("/events", 0.0, {"level": "info", "text": "IDLE -> TAKEOFF", "source": "supervisor"})
        for k in range(int(seconds * rate_hz)):
            t = k / rate_hz
            # Irrational-looking values, as a simulator's floats are (JSON length as in real logs).
            c, s = math.cos(0.8 * t + 0.1234567), math.sin(0.8 * t + 0.1234567)
            p = [0.5 * c + 1e-3 * math.sin(7.1 * t), 0.5 * s - 1e-3 * math.cos(5.3 * t), 1.0 + 1e-4 * c * s]
            v = [-0.4 * s + 1e-3 * c, 0.4 * c + 1.1e-3 * s, 1.3e-4 * c]
            q = [0.9964005827121208 + 1e-6 * c, 0.053360170629179 * s, -0.06577395417576869 * c, 0.0035 * s * c]
            log.write("/state", t, {"p": p, "v": v, "q": q, "p_true": [x + 3.1e-4 * s for x in p],
                                    "v_true": [x - 2.7e-3 * c for x in v]})
            log.write("/reference", t, {"p": [0.5 * c, 0.5 * s, 1.0], "v": [-0.4 * s, 0.4 * c, 0.0],
                                        "a": [-0.32 * c, -0.32 * s, 0.0], "yaw": 0.0})
            log.write("/command", t, {"acc": [-0.32 * c + 0.01 * s, -0.32 * s - 0.011 * c, 0.15038416974922325 * s],
                                      "roll_deg": 6.8876874615376265 * s, "pitch_deg": -14.613025762927812 * c,
                                      "yawrate_deg": -0.002420668876045312 * c, "thrust": 40741 + int(100 * s),
                                      "source": "mpc"})
            log.write("/tick", t, {"compute_s": 0.00038872799996170215 * (1 + 0.1 * s),
                                   "solve_s": 0.00020114900001999558 * (1 + 0.1 * c), "missed": False,
                                   "mpc_ok": True})
            if k % 4 == 0:
                log.write("/mocap", t, {"p": p, "q": q, "received": True, "stamp": t - 0.004})
            if k % 40 == 0:
                log.write("/safety", t, {"state": "TRACK", "reason": "", "pose_age_s": 0.006000000000000227,
                                         "fence_margin_m": 1.0187753243458844 + 0.1 * c,
                                         "tracking_error_m": 0.03362945780331822 * (1 + 0.1 * s),
                                         "battery_v": 3.766798249483653 - 1e-4 * t, "link_silence_s": 0.0,
                                         "fallback_ticks": 0})
    return log.path


if __name__ == "__main__":  # python tests/synthetic_log.py DIR SECONDS
    print(write_synthetic_flight(sys.argv[1], float(sys.argv[2])))
