"""The ``sim://N`` registry: which simulator serves which URI, with its parameters and power state.

cflib instantiates link drivers itself, with no arguments (``cflib.crtp.get_link_driver``),
so the URI -> simulator map has to be module state.
"""

from __future__ import annotations

import re
import threading
from typing import Any, Callable, Protocol

from cflib.crtp.exceptions import CommunicationException

from cfknode.sim_backend.accelerometer import Accelerometer
from cfknode.sim_backend.crtp_codes import SCHEME
from cfknode.sim_backend.sim_toc import PARAM_TOC, PM_BATTERY, PM_LOW_POWER, param_index

PM_LOW_TIMEOUT_S = 5.0  # firmware: sustained low voltage before lowPower (docs/hardware.md#battery)


class SimulatorLike(Protocol):
    """What the driver needs of ``SimCrazyflie``."""

    t: float
    firmware: Any
    lock: threading.RLock
    battery_voltage: float

    def add_step_observer(self, cb: Callable[[float, Any], None]) -> None: ...


class AttachedLink(Protocol):
    """What an endpoint needs of a link attached to it."""

    def _on_sim_step(self, t: float) -> None: ...

    def _lose_link(self, message: str) -> None: ...


class SimLinkError(CommunicationException):
    """A ``sim://`` URI that is malformed or has no simulator registered."""


def parse_sim_uri(uri: str) -> str:
    """Canonical ``sim://N``; raises ``SimLinkError`` if ``uri`` is a malformed sim URI.

    Link options after ``?`` (cflib's ``PowerSwitch`` appends ``?safelink=0&...``) are ignored:
    the simulated link has no packet loss to protect against."""
    m = re.fullmatch(r"sim://(\d+)/?(\?[\w=&.-]*)?", uri.strip())
    if m is None:
        raise SimLinkError(f"malformed simulator URI {uri!r}: expected sim://N with N an integer")
    return f"{SCHEME}{int(m.group(1))}"


class _Endpoint:
    """One registered simulator: its parameters, power state and the links attached to it."""

    def __init__(self, uri: str, sim: SimulatorLike) -> None:
        self.uri = uri
        self.sim = sim
        self.param_values: list[float] = [p.default for p in PARAM_TOC]
        self.pm_state = PM_BATTERY
        self.drivers: tuple[AttachedLink, ...] = ()  # replaced whole: read lock-free per step
        self._low_since: float | None = None
        self._low_voltage_index = param_index("pm", "lowVoltage")
        self._lock = threading.Lock()
        self.active = True  # cleared on unregister (a step observer cannot be removed)
        self._accelerometer: Accelerometer | None = None
        # Observed from registration on: pm.state needs the voltage history, logs need sim time.
        sim.add_step_observer(self._on_step)

    @property
    def accelerometer(self) -> Accelerometer:
        """The simulator's accelerometer, built when a log block first reads it."""
        if self._accelerometer is None:
            self._accelerometer = Accelerometer(self.sim)
        return self._accelerometer

    def attach(self, driver: AttachedLink) -> None:
        with self._lock:
            self.drivers = self.drivers + (driver,)

    def detach(self, driver: AttachedLink) -> None:
        with self._lock:
            self.drivers = tuple(d for d in self.drivers if d is not driver)

    def _on_step(self, t: float, state: Any) -> None:
        if not self.active:
            return
        # Firmware pm task: below pm.lowVoltage for PM_LOW_TIMEOUT_S -> lowPower (docs/hardware.md#battery).
        if self.sim.battery_voltage < self.param_values[self._low_voltage_index]:
            if self._low_since is None:
                self._low_since = t
            if t - self._low_since >= PM_LOW_TIMEOUT_S:
                self.pm_state = PM_LOW_POWER
        else:
            self._low_since = None
            self.pm_state = PM_BATTERY
        for driver in self.drivers:
            driver._on_sim_step(t)


_registry: dict[str, _Endpoint] = {}
_registry_lock = threading.Lock()


def registered_uris() -> list[str]:
    with _registry_lock:
        return sorted(_registry)


def lookup(uri: str) -> _Endpoint:
    """The endpoint serving ``uri``; ``SimLinkError`` naming the registered ones if none does."""
    key = parse_sim_uri(uri)
    with _registry_lock:
        endpoint = _registry.get(key)
        known = sorted(_registry)
    if endpoint is None:
        raise SimLinkError(
            f"no simulator registered at {key} (registered: {', '.join(known) or 'none'}); "
            "call cfknode.sim_backend.link_driver.register_simulator(uri, sim) first"
        )
    return endpoint


def add_endpoint(uri: str, sim: SimulatorLike) -> None:
    """Register ``sim`` at ``uri``; registering the same simulator again is a no-op."""
    key = parse_sim_uri(uri)
    with _registry_lock:
        old = _registry.get(key)
        if old is not None and old.sim is not sim:
            raise SimLinkError(f"{key} is already registered to another simulator; unregister it first")
        if old is None:
            _registry[key] = _Endpoint(key, sim)


def remove_endpoint(uri: str) -> None:
    """Stop serving ``uri``; links attached to it are told they are lost."""
    key = parse_sim_uri(uri)
    with _registry_lock:
        endpoint = _registry.pop(key, None)
    if endpoint is not None:
        endpoint.active = False
        for driver in endpoint.drivers:
            driver._lose_link(f"simulator {key} was unregistered")
