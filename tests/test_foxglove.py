"""Foxglove: ``wavegrasp up --foxglove`` serves the bus live over the Foxglove WebSocket
protocol, the scene (``/tf``, ``robot_description``, markers) among its channels, and the
run's file carries the same scene channels."""

from __future__ import annotations

import json
import struct
import subprocess
import time
from pathlib import Path

import websocket
from mcap.reader import make_reader

from wavegrasp.ops.launcher import free_port

from conftest import wavegrasp_cmd

SCENE = {"/tf", "/robot_description", "/wavegrasp/scene/markers"}


class Client:
    """A Foxglove WebSocket client: subscribes to every channel advertised and counts the
    messages that come on each."""

    def __init__(self, port: int, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.ws = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=1,
                                                      subprotocols=["foxglove.sdk.v1"])
                break
            except (OSError, websocket.WebSocketException):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.topics: dict[int, str] = {}
        self.schemas: dict[str, str] = {}
        self.received: dict[str, int] = {}

    def read(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                opcode, data = self.ws.recv_data()
            except websocket.WebSocketTimeoutException:
                continue
            except websocket.WebSocketConnectionClosedException:
                return
            if opcode == websocket.ABNF.OPCODE_TEXT:
                msg = json.loads(data)
                if msg["op"] == "advertise":
                    for c in msg["channels"]:
                        self.topics[c["id"]] = c["topic"]
                        self.schemas[c["topic"]] = c["schemaName"]
                    self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in msg["channels"]]}))
            elif opcode == websocket.ABNF.OPCODE_CLOSE:
                return
            elif opcode == websocket.ABNF.OPCODE_BINARY and data[:1] == b"\x01":
                # message data: the subscription, the log time, the message
                topic = self.topics[struct.unpack_from("<I", data, 1)[0]]
                self.received[topic] = self.received.get(topic, 0) + 1


def test_foxglove_sees_the_scene_live_and_the_run_file_has_it(recording: Path,
                                                               tmp_path: Path) -> None:
    port, out = free_port(), tmp_path / "run"
    run = subprocess.Popen(wavegrasp_cmd("up", str(recording), "--foxglove", "--foxglove-port",
                                         str(port), "--out", str(out)),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        client = Client(port)
        client.read(15.0)
    finally:
        output, _ = run.communicate(timeout=120)
    assert run.returncode == 0, output[-3000:]
    advertised = set(client.topics.values())
    assert SCENE | {"/trisect/points", "/wavegrasp/gate/heartbeat"} <= advertised, advertised
    assert client.schemas["/wavegrasp/scene/markers"] == "visualization_msgs/msg/MarkerArray"
    for topic in ("/tf", "/wavegrasp/scene/markers", "/trisect/points",
                  "/wavegrasp/perception/object"):
        assert client.received.get(topic, 0) > 5, (topic, client.received)
    with (out / "run.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    counts = {c.topic: summary.statistics.channel_message_counts.get(i, 0)
              for i, c in summary.channels.items()}
    assert all(counts.get(topic, 0) > 0 for topic in SCENE), counts
