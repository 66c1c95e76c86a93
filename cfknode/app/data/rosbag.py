"""A ROS 2 bag of Crazyswarm2's topics as a flight table, through ``rosbags`` (pure Python, no ROS).

Read per robot ``<name>``: ``/<name>/pose`` (``geometry_msgs/msg/PoseStamped``, the pose
Crazyswarm2 publishes from motion capture or the onboard estimate) and, for the input,
``/<name>/cmd_vel_legacy`` (``geometry_msgs/msg/Twist``: linear.y roll and linear.x pitch in
degrees, linear.z the 0-65535 thrust, angular.z the yaw rate; cflib's ``send_setpoint``). The
input is held between commands and sampled at each pose; velocities come from the positions. The
result has the columns of docs/data.md (``roll_deg``, ``pitch_deg``, ``thrust_cmd`` as the input),
so the same preparation, masks and alignment apply. Message times are the bag's receive times.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cfknode.kernel.errors import ConfigError

MAX_MESSAGES = 5_000_000  # per topic; a bag larger than this is refused, not read into memory


def _short(text: str, n: int = 80) -> str:
    return text if len(text) <= n else text[:n] + "..."


def is_bag(path: str | Path) -> bool:
    """A ROS 2 bag: its folder (with metadata.yaml), or a .db3 file, or an .mcap file beside a metadata.yaml."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix == ".db3" or (path.suffix == ".mcap" and (path.parent / "metadata.yaml").is_file())


def read_bag(path: str | Path, robot: str) -> dict[str, np.ndarray]:
    """The flight table of robot ``robot`` from the ROS 2 bag (a directory, or its .mcap / .db3 file)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ConfigError("reading ROS 2 bags needs rosbags: pip install 'cfknode[data]'") from None
    path = Path(path)
    bag = path if path.is_dir() else path.parent
    pose_topic, cmd_topic = f"/{robot}/pose", f"/{robot}/cmd_vel_legacy"
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            topics = {c.topic for c in reader.connections}
            if pose_topic not in topics:
                have = ", ".join(sorted(topics)) or "none"
                raise ConfigError(f"{path}: no topic {pose_topic} (topics: {_short(have)}); name the robot with --robot")
            poses = _read(reader, pose_topic, _pose_row)
            cmds = _read(reader, cmd_topic, _cmd_row) if cmd_topic in topics else np.zeros((0, 5))
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own types for a damaged or foreign bag
        raise ConfigError(f"{path}: not a readable ROS 2 bag ({_short(str(exc))})") from None
    if poses.shape[0] < 2:
        raise ConfigError(f"{path}: fewer than two messages on {pose_topic}")
    return _table(poses, cmds)


def _read(reader, topic: str, row) -> np.ndarray:
    conns = [c for c in reader.connections if c.topic == topic]
    rows = []
    for conn, t_ns, raw in reader.messages(connections=conns):
        if len(rows) >= MAX_MESSAGES:
            raise ConfigError(f"over {MAX_MESSAGES} messages on {topic}")
        rows.append((t_ns * 1e-9, *row(reader.deserialize(raw, conn.msgtype))))
    return np.array(rows, dtype=float).reshape(len(rows), -1)


def _pose_row(msg) -> tuple[float, ...]:
    p, q = msg.pose.position, msg.pose.orientation
    return p.x, p.y, p.z, q.w, q.x, q.y, q.z


def _cmd_row(msg) -> tuple[float, ...]:
    return msg.linear.y, msg.linear.x, msg.linear.z, msg.angular.z


def _table(poses: np.ndarray, cmds: np.ndarray) -> dict[str, np.ndarray]:
    order = np.argsort(poses[:, 0], kind="stable")
    poses = poses[order]
    keep = np.concatenate(([True], np.diff(poses[:, 0]) > 0))  # a repeated stamp carries no new motion
    poses = poses[keep]
    t = poses[:, 0]
    table = {name: poses[:, k + 1] for k, name in enumerate(("px", "py", "pz", "qw", "qx", "qy", "qz"))}
    table["t"] = t
    if cmds.shape[0]:
        cmds = cmds[np.argsort(cmds[:, 0], kind="stable")]
        # The command in force at each pose: the newest sent at or before it (none before the first: NaN).
        idx = np.searchsorted(cmds[:, 0], t, side="right") - 1
        for k, name in enumerate(("roll_deg", "pitch_deg", "thrust_cmd")):
            col = cmds[np.maximum(idx, 0), k + 1]
            table[name] = np.where(idx >= 0, col, np.nan)
    return table
