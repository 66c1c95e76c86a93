"""Foxglove: the flight log carries Foxglove's standard schemas, and ``--foxglove`` serves them live.

Schemas are checked with foxglove-sdk's own classes, and every message is decoded through the
schema the file (or the server) carries, as Foxglove does. The live test subscribes with a
WebSocket client on localhost and checks the advertised channels and the rate in flight time.
"""

from __future__ import annotations

import base64
import json
import struct
import threading
from typing import Any

import numpy as np
import pytest
from foxglove.messages import FrameTransform, Log, SceneUpdate
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from cfknode.app.config import load_config
from cfknode.app.foxglove import scene
from cfknode.app.foxglove.live import LiveServer
from cfknode.app.foxglove.view import Drawing, FoxgloveView, ViewRates
from cfknode.app.logs.reader import read_log
from cfknode.app.mission import run_flight
from fakes import SHORT_FLIGHT
from cfknode.kernel.errors import ConfigError

KINDS = {"/tf": FrameTransform, "/scene": SceneUpdate, "/log": Log}


def decoder(name: str, fds_bytes: bytes) -> Any:
    """The protobuf class for schema ``name`` from its FileDescriptorSet, as Foxglove builds it."""
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(fds_bytes).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read(topic: str, data: bytes) -> Any:
    """A topic's message as Foxglove reads it: decoded through the SDK's schema for the topic."""
    schema = KINDS[topic].get_schema()
    return decoder(schema.name, schema.data).FromString(data)


class Recorder:
    def __init__(self) -> None:
        self.sent: list[tuple[str, float, Any]] = []

    def publish(self, topic: str, t: float, data: bytes) -> None:
        self.sent.append((topic, t, read(topic, data)))


class NullLog:
    def __init__(self) -> None:
        self.writes: list[str] = []

    def write(self, topic: str, t: float, msg: Any) -> None:
        self.writes.append(topic)


def test_box_edges_are_the_twelve_edges_of_the_box():
    pts = scene.box_edges([0, 0, 0], [1, 2, 3]).reshape(12, 2, 3)
    lengths = sorted(float(np.linalg.norm(b - a)) for a, b in pts)
    assert lengths == [1.0] * 4 + [2.0] * 4 + [3.0] * 4


def test_pose_keeps_cfknodes_scalar_first_quaternion():
    ft = scene.pose_transform(1.25, "cf1", [1, 2, 3], [0.5, 0.5, -0.5, 0.5])
    m = decoder("foxglove.FrameTransform", FrameTransform.get_schema().data).FromString(ft.encode())
    assert (m.timestamp.seconds, m.timestamp.nanos) == (1, 250_000_000)
    assert (m.parent_frame_id, m.child_frame_id) == ("world", "cf1")
    assert (m.rotation.w, m.rotation.x, m.rotation.y, m.rotation.z) == (0.5, 0.5, -0.5, 0.5)
    assert (m.translation.x, m.translation.y, m.translation.z) == (1, 2, 3)


def test_view_passes_every_write_on_and_decimates_by_frame():
    inner, rec = NullLog(), Recorder()
    ref = np.array([[0, 0, 1], [1, 0, 1.0]])
    view = FoxgloveView(inner, [rec], {"cf1": Drawing(ref), "cf2": Drawing(ref, ([-1, -1, 0], [1, 1, 2]))},
                        ViewRates(pose_every=4, plan_every=8, static_every_s=1.0))
    view.follow_plan("cf2", lambda: np.zeros((5, 3)))
    state = {"p": np.zeros(3), "q": np.array([1.0, 0, 0, 0])}
    for k in range(16):
        for name in ("cf1", "cf2"):
            view.write(f"/{name}/state", k * 0.0025, state)
    view.write("/events", 0.01, {"level": "warning", "text": "hold", "source": "safety"})
    assert len(inner.writes) == 33  # every write reached the log
    tf = [m.child_frame_id for topic, _, m in rec.sent if topic == "/tf"]
    assert tf.count("cf1") == 4 and tf.count("cf2") == 4
    scenes = [m for topic, _, m in rec.sent if topic == "/scene"]
    ids = [e.id for m in scenes for e in m.entities]
    assert ids.count("cf2/horizon") == 2 and "cf1/horizon" not in ids  # cf1 has no plan to draw
    assert ids.count("fence") == 1 and ids.count("cf1/reference") == 1
    logs = [m for topic, _, m in rec.sent if topic == "/log"]
    assert len(logs) == 1 and logs[0].message == "hold"


def test_a_failing_sink_is_dropped_and_named_and_the_log_goes_on():
    class Broken:
        def publish(self, topic: str, t: float, data: bytes) -> None:
            raise OSError("socket gone")

    inner, rec = NullLog(), Recorder()
    view = FoxgloveView(inner, [Broken(), rec], {"cf": Drawing(np.zeros((2, 3)))})
    for k in range(10):
        view.write("/state", k * 0.0025, {"p": np.zeros(3), "q": np.array([1.0, 0, 0, 0])})
    assert len(inner.writes) == 10 and rec.sent
    assert view.failures == ["Broken: socket gone"]


@pytest.fixture(scope="module")
def logged(tmp_path_factory) -> str:
    d = tmp_path_factory.mktemp("fox")
    cfg = load_config(overrides={**SHORT_FLIGHT, "log.dir": str(d), "safety.estop_dir": str(d / "estop")})
    return run_flight(cfg, name_hint="fox").summary.log_path


@pytest.mark.flight
@pytest.mark.slow
def test_the_flight_log_carries_foxglove_schemas_the_3d_panel_reads(logged):
    found: dict[str, list[Any]] = {}
    with open(logged, "rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages(topics=list(KINDS)):
            kind = KINDS[channel.topic].get_schema()
            assert (schema.name, schema.encoding, channel.message_encoding) == (kind.name, "protobuf", "protobuf")
            assert schema.data == kind.data  # the SDK's own schema, byte for byte
            found.setdefault(channel.topic, []).append((msg.log_time, decoder(schema.name, schema.data).FromString(msg.data)))
    tf = found["/tf"]
    assert {m.child_frame_id for _, m in tf} == {"cf231"}
    # 50 Hz in flight time (every 8th tick of 400 Hz), and the message's stamp is its log time.
    assert np.allclose(np.diff([t for t, _ in tf]), 0.02e9, atol=1e3)
    assert all(t == m.timestamp.seconds * 10**9 + m.timestamp.nanos for t, m in tf)
    ids = {e.id for _, m in found["/scene"] for e in m.entities}
    assert {"cf231/reference", "cf231/horizon", "fence"} <= ids
    assert found["/log"] and all(m.message and m.level in (1, 2, 3, 4, 5) for _, m in found["/log"])
    # cfknode's own reader passes the Foxglove channels over, and reads its own as before.
    data = read_log(logged)
    assert "/state" in data.messages and "/tf" not in data.messages


@pytest.mark.flight
@pytest.mark.slow
def test_live_server_advertises_standard_schemas_and_streams_at_the_flight_rate(tmp_path):
    from websockets.sync.client import connect

    cfg = load_config(overrides={**SHORT_FLIGHT, "log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "e")})
    with LiveServer(port=0) as live:
        ws = connect(f"ws://127.0.0.1:{live.port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                     open_timeout=30, legacy=True)
        channels: dict[int, dict[str, Any]] = {}
        while len(channels) < 3:
            frame = json.loads(ws.recv(timeout=30))
            if frame.get("op") == "advertise":
                channels.update({c["id"]: c for c in frame["channels"]})
        by_topic = {c["topic"]: c for c in channels.values()}
        for topic, kind in KINDS.items():
            c = by_topic[topic]
            assert (c["schemaName"], c["encoding"]) == (kind.get_schema().name, "protobuf")
            assert base64.b64decode(c["schema"]) == kind.get_schema().data
        subs = {i + 1: c for i, c in enumerate(channels.values())}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": k, "channelId": c["id"]}
                                                                 for k, c in subs.items()]}))
        received: list[tuple[str, int, bytes]] = []
        done = threading.Event()

        def listen() -> None:
            while not done.is_set():
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except Exception:  # noqa: BLE001 - the server closed at the end of the test
                    return
                if isinstance(frame, bytes) and frame[0] == 1:  # message data: op, sub id, time, payload
                    sub, ns = struct.unpack_from("<IQ", frame, 1)
                    received.append((subs[sub]["topic"], ns, frame[13:]))

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        result = run_flight(cfg, name_hint="live", live=live)
        # The last messages may still be on their way: wait (bounded) until the count stops short of what was sent.
        for _ in range(100):
            if len(received) >= live.messages:
                break
            done.wait(0.1)
        done.set()
        listener.join(5)
        ws.close()
    assert result.outcome.state.value == "LANDED"
    tf = [(ns, data) for topic, ns, data in received if topic == "/tf"]
    assert len(received) == live.messages
    cls = decoder("foxglove.FrameTransform", FrameTransform.get_schema().data)
    assert {cls.FromString(d).child_frame_id for _, d in tf} == {"cf231"}
    assert np.allclose(np.diff([ns for ns, _ in tf]), 0.02e9, atol=1e3)


def test_a_bad_port_is_one_line():
    with pytest.raises(ConfigError, match="port must be 0 to 65535"):
        LiveServer(port=70000)
    with LiveServer(port=0) as first, pytest.raises(ConfigError, match=f"cannot serve Foxglove on 127.0.0.1:{first.port}"):
        LiveServer(port=first.port)


@pytest.mark.flight
@pytest.mark.slow
def test_a_fleet_log_shows_every_drone_as_its_own_frame(tmp_path):
    from cfknode.app.fleet.flight import run_fleet

    cfg = load_config(overrides={**SHORT_FLIGHT, "fleet.size": 2, "log.dir": str(tmp_path),
                                 "safety.estop_dir": str(tmp_path / "e")})
    result = run_fleet(cfg, name_hint="foxfleet")
    frames: dict[str, int] = {}
    ids: set[str] = set()
    with open(result.log_path, "rb") as fh:
        for _, channel, msg in make_reader(fh).iter_messages(topics=["/tf", "/scene"]):
            m = read(channel.topic, msg.data)
            if channel.topic == "/tf":
                frames[m.child_frame_id] = frames.get(m.child_frame_id, 0) + 1
            else:
                ids.update(e.id for e in m.entities)
    assert set(frames) == {"cf1", "cf2"} and frames["cf1"] == frames["cf2"] > 10
    assert {"cf1/reference", "cf2/reference", "cf1/horizon", "cf2/horizon", "fence"} <= ids


def test_foxglove_is_refused_for_a_ray_fleet_in_one_line(capsys):
    from cfknode.app.cli import main

    assert main(["fly", "--fleet", "2", "--executor", "ray", "--foxglove"]) == 2
    err = capsys.readouterr().err
    assert "--foxglove serves fleets flown here" in err and err.count("\n") == 1
