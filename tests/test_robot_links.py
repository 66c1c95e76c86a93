"""``--robots``: two robots on one link, or two names that share one file name, are refused in
one line before anything connects (exit status 2, never a traceback)."""

from __future__ import annotations

import pytest

from cfknode.app.cli import main
from cfknode.app.config import ConfigError
from cfknode.app.fleet.robots import check_robot_fleet, link_identity
from test_fleet_robots import cfg_for, ring_positions, write_robots


def test_link_identity_is_the_radio_channel_rate_and_address():
    same = ["radio://0/80/2M/E7E7E7E7E7", "radio://1/80/2M/e7e7e7e7e7", "radio://0/80/2M/E7E7E7E7E7/",
            "radio://0/80/2M", "radio://0/80/2M/E7E7E7E7E7?safelink=1"]
    assert len({link_identity(u) for u in same}) == 1
    other = ["radio://0/81/2M/E7E7E7E7E7", "radio://0/80/1M/E7E7E7E7E7", "radio://0/80/2M/E7E7E7E705"]
    assert len({link_identity(u) for u in [same[0], *other]}) == 4
    assert link_identity("sim://3") == link_identity(" SIM://3") != link_identity("sim://4")


@pytest.mark.parametrize("uris, what", [
    (("sim://40", "sim://40"), "are the same link"),
    (("radio://0/80/2M/E7E7E7E7E7", "radio://1/80/2M/E7E7E7E7E7"), "are the same link"),
])
def test_two_robots_on_one_link_are_refused_before_connecting(tmp_path, uris, what):
    pos = ring_positions(2)
    path = write_robots(tmp_path / "lab.yaml", {"cf1": (uris[0], pos[0], True), "cf2": (uris[1], pos[1], True)})
    with pytest.raises(ConfigError, match=what) as err:
        check_robot_fleet(cfg_for(tmp_path, path), ["cf1", "cf2"])
    assert "\n" not in str(err.value) and "cf1" in str(err.value) and "cf2" in str(err.value)


def test_names_that_share_a_file_name_are_refused(tmp_path):
    pos = ring_positions(2)
    path = write_robots(tmp_path / "lab.yaml", {"'cf/1'": ("sim://41", pos[0], True),
                                                 "cf_1": ("sim://42", pos[1], True)})
    with pytest.raises(ConfigError, match="share the file name 'cf_1'"):
        check_robot_fleet(cfg_for(tmp_path, path), ["cf/1", "cf_1"])


def test_the_cli_says_it_in_one_line_with_exit_status_2(tmp_path, capsys):
    pos = ring_positions(2)
    path = write_robots(tmp_path / "lab.yaml", {"cf1": ("sim://43", pos[0], True), "cf2": ("sim://43", pos[1], True)})
    code = main(["fly", "--robots", "cf1,cf2", "--headless", "--log-dir", str(tmp_path),
                 "--set", f"hardware.robots_file={path}", "--set", f"safety.estop_dir={tmp_path / 'estop'}"])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err and lines[-1].startswith("cfknode: error: --robots: cf1 (sim://43)")
