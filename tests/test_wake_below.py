"""A fleet's drones that fly under another learn its wake alone; the others keep learning their own air."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from cfknode.app.bench.learning_cells import CELLS
from cfknode.app.config import ConfigError, load_config, packaged_settings, with_defaults
from cfknode.app.fleet import learning as fleet_learning
from cfknode.app.fleet.flight import drone_configs
from cfknode.app.fleet.robots import check_robot_fleet
from cfknode.app.fleet.wake_below import passes_under
from cfknode.app.learning import trainer_settings, wake_only


class Path:
    """A reference: ``p(t)`` for t in [0, duration]."""

    def __init__(self, p: Any, duration: float = 4.0) -> None:
        self._p, self.duration = p, duration

    def sample(self, t: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(p=np.array([self._p(x) for x in t]))


def hover(x: float, y: float, z: float) -> Path:
    return Path(lambda t: (x, y, z))


LINE = Path(lambda t: (-0.5 + 0.25 * t, 0.0, 1.0))  # along x through the origin at 1 m


def test_a_line_under_a_hovering_drone_passes_under_it() -> None:
    assert passes_under(LINE, [hover(0.0, 0.0, 1.3)])
    assert passes_under(LINE, [hover(0.2, 0.1, 1.5)])  # 0.1 m aside: inside the wake's reach


def test_beside_above_beyond_reach_or_below_is_not_under() -> None:
    assert not passes_under(LINE, [hover(0.0, 0.3, 1.3)])  # 0.3 m aside
    assert not passes_under(LINE, [hover(0.0, 0.0, 2.8)])  # 1.8 m higher: the wake has died out
    assert not passes_under(LINE, [hover(0.0, 0.0, 0.7)])  # below it
    assert not passes_under(LINE, [hover(0.0, 0.0, 1.0)])  # level with it
    assert not passes_under(LINE, [])


def test_under_at_the_same_time_only() -> None:
    later = Path(lambda t: (0.0, 0.0, 1.3) if t > 3.5 else (1.0, 1.0, 1.3))  # over the crossing point after the line
    assert not passes_under(LINE, [later])


def _cell_configs(name: str, **extra: Any) -> list:
    cell = next(c for c in CELLS if c.name == name)
    cfg = load_config(overrides={**cell.config("online+layer", 0, "/tmp/unused", 0), **extra})
    return drone_configs(cfg)[1]


@pytest.mark.parametrize("name", ["crossing dz=0.3 v=1", "stacked pair dz=0.5 r=0.5 v=0.4"])
def test_the_lower_drone_learns_the_wake_and_the_upper_its_own_air(name: str) -> None:
    lower, upper = _cell_configs(name)
    assert lower.fleet.wake_only and not upper.fleet.wake_only
    assert lower.sim.seed != upper.sim.seed  # each drone's own config, changed in its fleet section alone


def test_the_choice_is_off_with_the_key_off_or_without_the_neighbour_input() -> None:
    name = "crossing dz=0.3 v=1"
    assert [c.fleet.wake_only for c in _cell_configs(name, **{"fleet.wake_below": False})] == [False, False]
    assert [c.fleet.wake_only for c in _cell_configs(name, **{"fleet.neighbour_input": False})] == [False, False]
    assert [c.fleet.wake_only for c in _cell_configs(name, **{"fleet.wake_only": True})] == [True, True]
    # Without the layer (the paper's method) a wake network would leave the drone's own mass unlearned.
    assert [c.fleet.wake_only for c in _cell_configs(name, **{"controller.adaptation": "none"})] == [False, False]


def test_drones_that_train_alike_share_a_trainer(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[Any] = []

    class Trainer:
        def __init__(self, settings: Any, timeout: float, n: int, start_timeout: float) -> None:
            self.settings, self.ports, self.closed = settings, [f"port{len(made)}.{i}" for i in range(n)], False
            self.client = SimpleNamespace(start_problem="")
            made.append(self)

        def start(self) -> None: ...

        def wait_ready(self, timeout: float) -> bool:
            return True

        def close(self) -> None:
            self.closed = True

    monkeypatch.setattr(fleet_learning, "SharedTrainer", Trainer)
    lower, upper = _cell_configs("crossing dz=0.3 v=1")
    with fleet_learning.fleet_trainers([lower, upper, upper]) as ports:
        assert len(made) == 2 and made[0].settings.wake_only and not made[1].settings.wake_only
        assert ports == ["port0.0", "port1.0", "port1.1"]  # each drone's port, in the drones' order
    assert all(t.closed for t in made)


def _wake_settings_of(c: Any) -> tuple:
    return (c.online.t_col, c.online.epochs, c.knode.queue_size, c.online.layer_filter_hz, c.online.layer_command_lag_s,
            c.online.gate_layer_rejudge)


WAKE = (2.0, 300, 1, 8.0, (0.015, 0.015), False)  # cfknode/config/wake.yaml


def test_a_drone_learning_a_wake_flies_the_wake_settings_and_the_others_the_defaults() -> None:
    lower, upper = _cell_configs("crossing dz=0.3 v=0.5")
    assert _wake_settings_of(lower) == WAKE
    assert _wake_settings_of(upper) == _wake_settings_of(load_config())
    both = _cell_configs("crossing dz=0.3 v=0.5", **{"fleet.wake_only": True})
    assert [_wake_settings_of(c) for c in both] == [WAKE, WAKE]
    assert [_wake_settings_of(c) for c in _cell_configs("crossing dz=0.3 v=0.5", **{"fleet.wake_below": False})] \
        == [_wake_settings_of(upper)] * 2
    # The paper's method, without the layer: no drone is a wake drone, and none changes its settings.
    assert [c.online.t_col for c in _cell_configs("crossing dz=0.3 v=0.5", **{"controller.adaptation": "none"})] \
        == [upper.online.t_col] * 2


def test_a_setting_the_user_gave_stays_the_wake_drone_s_own() -> None:
    lower, upper = _cell_configs("crossing dz=0.3 v=0.5", **{"online.t_col": 1.0, "online.layer_filter_hz": 4.0})
    assert (lower.online.t_col, lower.online.layer_filter_hz, lower.online.epochs) == (1.0, 4.0, 300)
    assert (upper.online.t_col, upper.online.layer_filter_hz) == (1.0, 4.0)


def test_the_wake_settings_are_each_a_change_from_the_defaults_and_valid() -> None:
    default, wake = load_config(), packaged_settings("wake")
    changed = with_defaults(default, wake, default)
    for key, value in wake.items():
        section, name = key.split(".")
        assert getattr(getattr(changed, section), name) == (tuple(value) if isinstance(value, list) else value)
        assert getattr(getattr(changed, section), name) != getattr(getattr(default, section), name), key
    with pytest.raises(ConfigError, match="unknown config key 'online.nope'"):
        with_defaults(default, {"online.nope": 1}, default)


def test_a_fleet_of_robots_learns_a_wake_where_it_asks_and_sees_its_fleet(tmp_path) -> None:
    """A robot's flight config is a drone of a fleet of robots: ``fleet.wake_only`` reaches its learning, with the
    wake's settings; no drone is chosen from references, which are placed where the mocap sees the robots."""
    from test_fleet_robots import cfg_for, ring_positions, write_robots

    a, b = ring_positions(2)
    robots = write_robots(tmp_path / "robots.yaml", {"cf1": ("sim://0", a, True), "cf2": ("sim://1", b, True)})
    learning = {"fleet.neighbour_input": True, "online.enabled": True}
    waking = check_robot_fleet(cfg_for(tmp_path, robots, **learning, **{"fleet.wake_only": True}), ["cf1", "cf2"])[1]
    assert [c.fleet.size for c in waking] == [2, 2]
    assert [wake_only(c) and trainer_settings(c).wake_only for c in waking] == [True, True]
    assert [_wake_settings_of(c) for c in waking] == [WAKE, WAKE]
    own_air = check_robot_fleet(cfg_for(tmp_path, robots, **learning), ["cf1", "cf2"])[1]
    assert [wake_only(c) for c in own_air] == [False, False]
    assert [_wake_settings_of(c) for c in own_air] == [_wake_settings_of(load_config())] * 2
