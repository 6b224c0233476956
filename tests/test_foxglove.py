"""Foxglove: ``wavegrasp up --foxglove`` serves the bus live over the Foxglove WebSocket
protocol, the scene (``/tf``, ``robot_description``, markers) among its channels, and the
run's file carries the same scene channels."""

from __future__ import annotations

import json
import re
import struct
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import websocket
from mcap.reader import make_reader

from wavegrasp.ops.launcher import free_port
from wavegrasp.recording_io.own_messages import read_own
from wavegrasp.runtime.trace import hop_times_ms
from wavegrasp.schemas import model_for_key

from conftest import make_recording, wavegrasp_cmd

LAYOUT = Path(__file__).parents[1] / "ops" / "foxglove" / "layout.json"
SCENE = {"/tf", "/robot_description", "/wavegrasp/scene/markers", "/wavegrasp/scene/mesh"}


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
        self.status: list[str] = []  # the server's status messages (a refused subscription)

    def read(self, seconds: float, done: Callable[[], bool] = lambda: False) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not done():
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
                elif msg["op"] == "status":
                    self.status.append(msg["message"])
            elif opcode == websocket.ABNF.OPCODE_CLOSE:
                return
            elif opcode == websocket.ABNF.OPCODE_BINARY and data[:1] == b"\x01":
                # message data: the subscription, the log time, the message
                topic = self.topics[struct.unpack_from("<I", data, 1)[0]]
                self.received[topic] = self.received.get(topic, 0) + 1


def layout_paths() -> dict[str, set[str]]:
    """The topics the committed layout's panels show, each with the first fields of its
    message paths (``/wavegrasp/gate/decision.mean_error_m``: ``mean_error_m``)."""
    config = json.loads(LAYOUT.read_text())["configById"]
    paths: dict[str, set[str]] = {}
    for panel in config.values():
        texts = [p["value"] for p in panel.get("paths", [])] + list(panel.get("topics", {}))
        texts += [panel.get("topicPath", "")] + [layer.get("topic", "") for layer in
                                                 panel.get("layers", {}).values()]
        for text in filter(None, texts):
            topic, field = re.match(r"(/[\w/]+)\.?(\w*)", text).groups()
            paths.setdefault(topic, set()).update({field} - {""})
    return paths


def test_foxglove_sees_the_scene_live_and_the_run_file_has_it(tmp_path: Path) -> None:
    # long enough for the gate to decide (the latency per hop comes with each decision)
    recording = make_recording(tmp_path / "can.mcap", seconds=12.0, seed=3, wave=2,
                               object="can_empty")
    port, out, log = free_port(), tmp_path / "run", tmp_path / "up.log"
    with log.open("w") as sink:
        run = subprocess.Popen(wavegrasp_cmd("up", str(recording), "--foxglove",
                                             "--foxglove-port", str(port), "--out", str(out)),
                               stdout=sink, stderr=subprocess.STDOUT, text=True)
        try:
            client = Client(port)
            client.read(120.0, done=lambda: run.poll() is not None)  # the whole run, live
        finally:
            run.wait(timeout=120)
    assert run.returncode == 0, log.read_text()[-3000:]
    assert not client.status, client.status
    advertised = set(client.topics.values())
    assert SCENE | {"/trisect/points", "/wavegrasp/gate/heartbeat"} <= advertised, advertised
    assert client.schemas["/wavegrasp/scene/markers"] == "visualization_msgs/msg/MarkerArray"
    for topic in ("/tf", "/wavegrasp/scene/markers", "/trisect/points",
                  "/wavegrasp/perception/object"):
        assert client.received.get(topic, 0) > 5, (topic, client.received)
    # A channel's first message reaches a client connected before it: each plan and outcome.
    for topic in ("/wavegrasp/planner/plan", "/wavegrasp/sim/outcome"):
        assert client.received.get(topic, 0) >= 1, (topic, client.received)
    with (out / "run.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    counts = {c.topic: summary.statistics.channel_message_counts.get(i, 0)
              for i, c in summary.channels.items()}
    assert all(counts.get(topic, 0) > 0 for topic in SCENE), counts
    # The committed layout shows what a run serves and records (the edge stage's clouds
    # only cross a tether; the latency comes with the first decision), and its plots' fields
    # are the messages' own.
    layout = layout_paths()
    shown = advertised | {t for t, n in counts.items() if n} | {"/wavegrasp/edge/points"}
    assert set(layout) <= shown, set(layout) - shown
    for topic, fields in layout.items():
        model = model_for_key(topic.lstrip("/"))
        assert model is not None or not fields, topic
        assert fields <= set(model.model_fields if model else ()), (topic, fields)
    # The latency per hop, as the layout plots it: each decision's trace, hop by hop.
    decisions = [m for _, m, _ in read_own(out / "run.mcap", ["wavegrasp/gate/decision"])]
    latencies = [m for _, m, _ in read_own(out / "run.mcap", ["wavegrasp/scene/latency"])]
    assert latencies, "no decision's latency"
    assert sorted(m.plan_id for m in latencies) == sorted(m.plan_id for m in decisions)
    for m in latencies:
        trace = next(d.header.trace for d in decisions if d.plan_id == m.plan_id)
        assert m.hops_ms == dict(hop_times_ms(trace))
        assert {"perception", "predictor", "planner", "gate"} <= set(m.hops_ms)
        assert m.total_ms == (trace[-1].sent_ns - trace[0].recv_ns) / 1e6


def test_the_layout_has_what_an_import_needs() -> None:
    """Foxglove's (and Lichtblick's) import refuses a layout without ``playbackConfig``; every
    panel the arrangement names is configured; an optional field (``float64[<=1]``) is
    plotted by its element."""
    layout = json.loads(LAYOUT.read_text())
    assert {"configById", "layout", "playbackConfig", "globalVariables", "userNodes"} <= set(
        layout)

    def panels(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert isinstance(node, dict), node
        return panels(node["first"]) + panels(node["second"])

    assert sorted(panels(layout["layout"])) == sorted(layout["configById"])
    paths = [p["value"] for c in layout["configById"].values() for p in c.get("paths", [])]
    assert "/wavegrasp/gate/decision.mean_error_m[0]" in paths
