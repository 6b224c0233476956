"""Our CDR decodes with an independent implementation: Foxglove's TypeScript
``@foxglove/rosmsg2-serialization`` under node, from the ``ros2msg`` definitions in the run's
file, gives what rosbags gives for a sample of every channel (ops/setup.sh installs it)."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from dataclasses import fields
from pathlib import Path

import numpy as np

from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.recording_io.typestore import ros2_typestore

from conftest import wavegrasp_cmd

NODE_DIR = Path(__file__).with_name("ros2_decode")
SAFE = 2**53 - 1


def plain(value: object) -> object:
    """A rosbags message as decode.mjs prints one: dicts, lists, numbers, base64 bytes."""
    if isinstance(value, np.ndarray):
        if value.dtype == np.uint8:
            return {"bytes": base64.b64encode(value.tobytes()).decode()}
        return [plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool | str | float) or value is None:
        return value
    if isinstance(value, int):
        return str(value) if abs(value) > SAFE else value
    if isinstance(value, list):
        return [plain(v) for v in value]
    # ROS 2 field names are lower case; rosbags keeps the constants (upper case) beside them.
    return {f.name: plain(getattr(value, f.name)) for f in fields(value)
            if f.name != "__msgtype__" and not f.name.isupper()}


def test_foxglove_decodes_every_channel_as_rosbags_does(recording: Path,
                                                       tmp_path: Path) -> None:
    assert shutil.which("node"), "node is not installed: run ops/setup.sh"
    assert (NODE_DIR / "node_modules" / "@foxglove" / "rosmsg2-serialization").is_dir(), (
        "the decoder is not installed: run ops/setup.sh")
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd("up", str(recording), "--pace", "fast", "--out",
                                          str(out)), capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout[-3000:]
    store = ros2_typestore()
    cases, expected, topics, seen = [], [], [], {}
    for schema, channel, message in read_mcap(out / "run.mcap"):
        # The first and the last message of each channel but the camera's (one of those).
        seen.setdefault(channel.topic, []).append((schema, message))
    for topic, messages in sorted(seen.items()):
        picks = messages[:1] if topic.endswith("points") else [messages[0], messages[-1]]
        for schema, message in picks:
            assert schema.encoding == "ros2msg", topic
            cases.append({"schema": schema.data.decode(),
                          "data": base64.b64encode(message.data).decode()})
            expected.append(plain(store.deserialize_cdr(message.data, schema.name)))
            topics.append(topic)
    node = subprocess.run(["node", str(NODE_DIR / "decode.mjs")], input=json.dumps(cases),
                          capture_output=True, text=True, timeout=120, cwd=NODE_DIR)
    assert node.returncode == 0, node.stderr[-3000:]
    decoded = json.loads(node.stdout)
    for topic, got, want in zip(topics, decoded, expected, strict=True):
        assert got == want, topic
    assert {"/wavegrasp/perception/object", "/wavegrasp/predictor/prediction",
            "/wavegrasp/sim/arm_state", "/wavegrasp/clock"} <= set(seen)
