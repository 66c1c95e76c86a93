"""A ROS 2 bag of Crazyswarm2's topics (written here with rosbags, as ros2 bag record would) read
as a flight table, and trained on through the command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from cfknode.app.cli import main  # noqa: E402
from cfknode.app.config import ConfigError, load_config  # noqa: E402
from cfknode.app.data.prepare import TableOptions, prepare  # noqa: E402
from cfknode.app.data.rosbag import is_bag, read_bag  # noqa: E402
from cfknode.app.data.synthetic import flight_table  # noqa: E402

MASS = 0.034


def write_bag(path: Path, table: dict[str, np.ndarray], newton_per_cmd: float, robot: str = "cf7") -> Path:
    """Poses at the table's rate; the RPYT command that gives its thrust and attitude at half that rate."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    PoseStamped, Pose = ts.types["geometry_msgs/msg/PoseStamped"], ts.types["geometry_msgs/msg/Pose"]
    Point, Quat = ts.types["geometry_msgs/msg/Point"], ts.types["geometry_msgs/msg/Quaternion"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Twist, Vector3 = ts.types["geometry_msgs/msg/Twist"], ts.types["geometry_msgs/msg/Vector3"]
    q = np.stack([table[k] for k in ("qw", "qx", "qy", "qz")], axis=1)
    w, x, y, z = q.T
    roll = np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = np.degrees(np.arcsin(np.clip(2 * (w * y - z * x), -1, 1)))
    with Writer(path, version=9) as writer:
        pose_c = writer.add_connection(f"/{robot}/pose", PoseStamped.__msgtype__, typestore=ts)
        cmd_c = writer.add_connection(f"/{robot}/cmd_vel_legacy", Twist.__msgtype__, typestore=ts)
        for i, t in enumerate(table["t"]):
            ns = int(round(t * 1e9)) + 1_000_000_000
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            msg = PoseStamped(header=Header(stamp=stamp, frame_id="world"), pose=Pose(
                position=Point(x=table["px"][i], y=table["py"][i], z=table["pz"][i]),
                orientation=Quat(x=q[i, 1], y=q[i, 2], z=q[i, 3], w=q[i, 0])))
            if i % 2 == 0:  # the command goes out just before the pose it acts on is recorded
                cmd = Twist(linear=Vector3(x=pitch[i], y=roll[i], z=table["thrust"][i] / newton_per_cmd),
                            angular=Vector3(x=0.0, y=0.0, z=0.0))
                writer.write(cmd_c, ns - 1000, ts.serialize_cdr(cmd, Twist.__msgtype__))
            writer.write(pose_c, ns, ts.serialize_cdr(msg, PoseStamped.__msgtype__))
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    cfg = load_config()
    table = flight_table(seed=3, manoeuvres=3, seconds=12, mass=MASS, rate_hz=100.0)
    return write_bag(tmp_path_factory.mktemp("bag") / "flight", table, cfg.vehicle.newton_per_cmd), table


def test_a_bag_reads_as_the_table_it_was_written_from(bag):
    path, table = bag
    assert is_bag(path) and not is_bag(path.parent)
    got = read_bag(path, "cf7")
    assert np.allclose(got["t"] - got["t"][0], table["t"] - table["t"][0], atol=1e-6)
    assert np.allclose(got["px"], table["px"]) and np.allclose(got["qz"], table["qz"])
    cfg = load_config()
    opts = TableOptions(mass=MASS, gravity=9.81, newton_per_cmd=cfg.vehicle.newton_per_cmd, align="none")
    segments, prep = prepare(got, "bag", opts)
    assert prep.input_kind == "rpyt" and prep.samples > 0.9 * table["t"].size
    # The RPYT command held between messages gives back the acceleration the table's thrust gave.
    ref_segments, _ = prepare(table, "table", opts)
    u_bag, u_ref = np.concatenate([s.u for s in segments]), np.concatenate([s.u for s in ref_segments])
    n = min(len(u_bag), len(u_ref))
    assert np.median(np.abs(u_bag[:n] - u_ref[:n])) < 0.05


def test_a_bag_without_the_robot_is_one_line(bag):
    path, _ = bag
    with pytest.raises(ConfigError, match="no topic /cf9/pose .*--robot") as err:
        read_bag(path, "cf9")
    assert "\n" not in str(err.value)


def test_train_on_a_bag_from_the_command_line(bag, tmp_path):
    path, _ = bag
    out = tmp_path / "bag.safetensors"
    assert main(["train", "--data", str(path), "--robot", "cf7", "--set", f"vehicle.mass={MASS}", "--epochs", "10",
                 "--split", "tail", "--out", str(out)]) == 0
    assert out.is_file()
