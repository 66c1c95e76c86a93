"""CLI input errors: one line on stderr naming the key or file, exit status 2."""

import subprocess
import sys

import pytest

from cfknode.app.cli import main
from cfknode.app.backends.robots import example_robots_path


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


def _cfknode(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cfknode", *argv], capture_output=True, text=True, timeout=timeout)


def test_an_unfit_trajectory_is_refused_in_one_line_before_take_off(tmp_path):
    proc = _cfknode("fly", "--headless", "--log-dir", str(tmp_path), "--set", "trajectory.height=4.9")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert proc.stderr.startswith("cfknode: error: refusing to take off: the trajectory (circle r=0.5 m at 0.4 m/s, "
                                  "4.9 m high) reaches z = 4.90 m, beyond the fence's 1.80 m")
    assert list(tmp_path.iterdir()) == []  # no flight log: nothing flew


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["fly", "--set", "controller.rate_hz=1"], "controller.rate_hz = 1 is out of range: must be 50 to 1000 Hz"),
        (["fly", "--set", "vehicle.thrust_max_per_motor=0"], "vehicle.thrust_max_per_motor = 0 is out of range"),
        (["fly", "--set", "controller.dt=1e-9"], "controller.dt = 1e-09 s must be at least one control tick"),
        (["fly", "--name", "a" * 300], "--name must be 1 to 64 of the characters"),
        (["fly", "--name", "../etc"], "--name must be 1 to 64 of the characters"),
        (["train", "--log", "x.mcap", "--out", "m.safetensors", "--set", "training.epochs=1e9"],
         "training.epochs = 1000000000 is out of range: must be 1 to 100000"),
    ],
)
def test_more_bad_input_is_one_line_and_exit_2(argv, fragment, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert fragment in err and len(err.splitlines()) == 1


def test_bad_paths_are_one_line_and_exit_2(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes(b"trajectory:\n  radius: 0.5 # \xe9\n")
    for argv, fragment in (
        (["--log-dir", str(a_file)], "is a file, not a directory"),
        (["--log-dir", str(tmp_path), "--set", f"safety.estop_dir={a_file}/x"], "cannot create the directory"),
        (["--config", str(latin1)], "is not UTF-8 text"),
    ):
        assert main(["fly", "--headless", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert fragment in err and len(err.splitlines()) == 1


def test_a_missing_crazyradio_shows_only_the_clean_message(tmp_path):
    # Radio index 9: no such dongle on any test machine. cflib logs the failure with a traceback.
    robots = tmp_path / "robots.yaml"
    text = example_robots_path().read_text()
    robots.write_text(text.replace("radio://0/80/2M/E7E7E7E7E7 ", "radio://9/80/2M/E7E7E7E7E7 "))
    argv = ["fly", "--backend", "cf", "--mocap", "mock", "--robots-file", str(robots), "--headless",
            "--log-dir", str(tmp_path)]
    proc = _cfknode(*argv)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert proc.stderr.startswith("cfknode: error: could not connect to radio://9/80/2M/E7E7E7E7E7")
    verbose = _cfknode(*argv, "--verbose")
    assert verbose.returncode == 1 and "cflib" in verbose.stderr  # the detail is one flag away


def test_library_log_records_are_held_back_unless_verbose(capsys):
    import logging

    from cfknode.app.cli_logging import CommandLogHandler, command_logging

    with command_logging(verbose=False) as handler:
        logging.getLogger("cflib.crazyflie").error("driver trace")
        logging.getLogger("cfknode.preflight").warning("forced")
    err = capsys.readouterr().err
    assert "driver trace" not in err and "cfknode.preflight: WARNING: forced" in err and handler.held_back == 1
    with command_logging(verbose=True):
        logging.getLogger("cflib.crazyflie").error("driver trace")
    assert "cflib.crazyflie: ERROR: driver trace" in capsys.readouterr().err
    assert not any(isinstance(h, CommandLogHandler) for h in logging.getLogger().handlers)


def test_the_command_line_loads_without_torch() -> None:
    # Every command's parser is built at start: torch (hundreds of MB) loads only where a command trains.
    import subprocess
    import sys

    code = "import sys; from cfknode.app.cli import _parser; _parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
