"""CLI input errors: one line on stderr naming the key or file, exit status 2."""

import subprocess
import sys

import pytest

from cfknode.cli import main


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["fly", "--set", "trajectory.radiuss=1"], "unknown config key 'trajectory.radiuss'"),
        (["fly", "--set", "trajectory.speed=fast"], "'trajectory.speed' must be a number"),
        (["fly", "--config", "/nonexistent/my.yaml"], "config file not found: /nonexistent/my.yaml"),
        (["fly", "--radius", "-0.5"], "trajectory.radius = -0.5 is out of range: must be 0.05 to 5 m"),
        (["fly", "--set", "novalue"], "--set expects key=value"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, fragment, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert fragment in err
    assert len(err.splitlines()) == 1 and err.startswith("cfknode: error:")


def test_bad_flag_value_exits_2():
    proc = subprocess.run(
        [sys.executable, "-m", "cfknode", "fly", "--traj", "square"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2
    assert "invalid choice: 'square'" in proc.stderr


def test_wrong_type_in_user_file(tmp_path, capsys):
    f = tmp_path / "my.yaml"
    f.write_text("controller:\n  horizon: twenty\n")
    assert main(["fly", "--config", str(f)]) == 2
    assert "'controller.horizon' must be an integer" in capsys.readouterr().err
