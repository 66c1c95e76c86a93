"""The supervisor's slow inputs: battery and radio link, read on a 40-tick cycle, and the /safety status.

Mixed into ``Supervisor``, which owns the state these methods read and write.
"""

from __future__ import annotations

import math
from typing import Any

from cfknode.safety.supervisor_types import _FLYING, _LAND, _STOP


class SlowInputs:
    """Battery and link watchdogs (``_escalate`` and the readings are ``Supervisor``'s)."""

    config: Any
    _state: Any
    _enabled: bool
    _battery: Any
    _battery_source: Any
    _link_source: Any
    _link_silence: float
    _log: Any

    def _poll(self, now: float, slot: str) -> None:
        """One slow input (``slot``): battery, link or the /safety status message."""
        flying = self._state in _FLYING and self._enabled
        cfg = self.config
        if slot == "status":
            self._log_status(now)
        elif slot == "battery":
            volts = self._battery_now()
            if volts is not None:
                filtered = self._battery.update(now, volts)
                if flying and filtered < cfg.battery_land_v:
                    self._escalate(now, _LAND, "battery_low",
                                   f"battery {filtered:.2f} V below {cfg.battery_land_v:g} V")
        elif self._link_source is not None:
            link = self._link_source(now)
            self._link_silence = link.silence_s
            if flying:
                if link.lost:
                    self._escalate(now, _STOP, "link_lost", f"radio link lost ({link.lost})",
                                   "nothing reaches the drone: its watchdog levels it at 0.5 s and stops "
                                   "the motors at 2 s")
                elif link.silence_s > cfg.link_silence_s:
                    self._escalate(now, _LAND, "link_silent", f"no answer on the radio link for {link.silence_s:.2f} s")
                elif link.latency_s > cfg.link_max_latency_s:
                    self._escalate(now, _LAND, "link_latency", f"radio latency {link.latency_s * 1e3:.0f} ms")

    def _battery_now(self) -> float | None:
        if self._battery_source is None:
            return None
        volts = self._battery_source()
        return None if volts is None or not math.isfinite(volts) else float(volts)

    def _log_status(self, now: float) -> None:
        self._log.write("/safety", now, {
            "state": self._state.value,
            "reason": self._cause,
            "pose_age_s": now - self._pose_t,
            "fence_margin_m": self._fence_margin,
            "tracking_error_m": self._track_err,
            "battery_v": self._battery.value,
            "link_silence_s": self._link_silence,
            "fallback_ticks": self._fallback_run,
        })
