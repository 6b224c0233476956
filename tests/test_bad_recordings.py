"""Bad input files: every command that reads a recording or a run file names the file and the
problem on one line of stderr, exits non-zero, and prints no traceback; a file cut short (a
killed recorder's run.mcap) is still read up to its last complete chunk.

The bad inputs are made from real files: a small recording from the project's generator, bags
converted from it, run files written the way the recorder writes them, then cut or corrupted.
"""

from __future__ import annotations

import logging
import random
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from wavegrasp.ops import latency
from wavegrasp.player import main as player
from wavegrasp.recording_io.reader import (
    RecordedMessage,
    RecordingError,
    TruncatedRecording,
    open_recording,
    read_mcap,
)
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.recording_io.writer import RecordingWriter, write_ros1_bag, write_ros2_bag
from wavegrasp.runtime.bus import Bus
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import GateDecision, Header, Hop

from conftest import make_recording, wavegrasp_cmd

MS = 1_000_000


def flip(data: bytes, start: int, n: int = 16) -> bytes:
    """`data` with `n` bytes from `start` (negative: from the end) inverted."""
    start = start % len(data)
    return data[:start] + bytes(b ^ 0xFF for b in data[start:start + n]) + data[start + n:]


def chunk_offsets(path: Path) -> list[tuple[int, int]]:
    """(start, end) byte offsets of each chunk of a complete MCAP."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
                  for c in summary.chunk_indexes)


def chunk_end_times(path: Path) -> list[int]:
    """The last log time in each chunk of a complete MCAP, in file order."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return [c.message_end_time
            for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)]


def foreign_mcap(path: Path, encoding: str, schema_encoding: str, profile: str = "") -> Path:
    """A valid MCAP whose /trisect/points is not ROS 2 CDR."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile=profile, library="test")
        schema = w.register_schema("PointCloud", schema_encoding, b"{}")
        channel = w.register_channel("/trisect/points", encoding, schema)
        w.add_message(channel, 1, b"\x08\x01", 1)
        w.finish()
    return path


@pytest.fixture(scope="module")
def tank(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """1 s of wave tank: 10 camera frames, 4 MB in four chunks."""
    return make_recording(tmp_path_factory.mktemp("tank") / "tank.mcap", 1.0, seed=3)


@pytest.fixture(scope="module")
def tank_messages(tank: Path) -> list[RecordedMessage]:
    return list(open_recording(tank).messages())


@pytest.fixture(scope="module")
def bad(tank: Path, tank_messages: list[RecordedMessage],
        tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every bad input, by name."""
    out = tmp_path_factory.mktemp("bad")
    data = tank.read_bytes()
    chunks = chunk_offsets(tank)
    made: dict[str, Path] = {}

    def put(name: str, content: bytes) -> None:
        made[name] = out / name
        made[name].write_bytes(content)

    made["missing.mcap"] = out / "missing.mcap"
    put("empty.mcap", b"")
    put("random.mcap", random.Random(0).randbytes(5000))
    put("random", random.Random(1).randbytes(5000))
    put("notes.txt", b"hello, not a recording\n")
    put("cut_in_magic.mcap", data[:5])
    put("header_only.mcap", data[: chunks[0][0]])
    put("cut_in_first_chunk.mcap", data[: chunks[0][0] + 5000])
    put("cut_in_chunk.mcap", data[: chunks[2][0] + 5000])
    put("cut_after_chunk.mcap", data[: chunks[1][1]])
    put("cut_in_summary.mcap", data[:-100])
    put("corrupt_chunk.mcap", flip(data, chunks[1][0] + 1000))
    put("corrupt_chunk_cut.mcap", flip(data, chunks[1][0] + 1000)[: chunks[2][1]])
    put("json_only.mcap", foreign_mcap(out / "j", "json", "jsonschema").read_bytes())
    put("protobuf.mcap", foreign_mcap(out / "p", "protobuf", "protobuf").read_bytes())
    with RecordingWriter(out / "no_camera.mcap", {}) as w:
        w.write_groundtruth(1, (0, 0, 0), (0, 0, 0, 1))
    made["no_camera.mcap"] = out / "no_camera.mcap"
    text = ros2_typestore().serialize_cdr(
        ros2_typestore().types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")
    with RecordingWriter(out / "camera_not_clouds.mcap", {}) as w:
        w.write_cdr("/trisect/points", "std_msgs/msg/String", 1, text)
    made["camera_not_clouds.mcap"] = out / "camera_not_clouds.mcap"
    bag = write_ros1_bag(out / "good.bag", tank_messages).read_bytes()
    put("random.bag", random.Random(2).randbytes(3000))
    put("bag_magic_only.bag", bag[:13])
    put("bag_cut.bag", bag[: len(bag) // 2])
    put("bag_index_corrupt.bag", flip(bag, -250, 100))
    good2 = write_ros2_bag(out / "good_ros2", tank_messages)
    for name, spoil in [("ros2_no_metadata", lambda d: (d / "metadata.yaml").unlink()),
                        ("ros2_bad_metadata", lambda d: (d / "metadata.yaml").write_text("{{")),
                        ("ros2_no_db3", lambda d: (d / "good_ros2.db3").unlink()),
                        ("ros2_corrupt_db3", lambda d: (d / "good_ros2.db3").write_bytes(
                            random.Random(3).randbytes(4096)))]:
        made[name] = shutil.copytree(good2, out / name)
        spoil(made[name])
    made["plain_folder"] = out / "plain_folder"
    made["plain_folder"].mkdir()
    (made["plain_folder"] / "notes.txt").write_text("x")
    return made


#: What `wavegrasp player` says of each input it refuses before playing.
PLAYER_REFUSES = {
    "missing.mcap": "no such file",
    "empty.mcap": "empty file (0 bytes)",
    "random.mcap": "not an MCAP file (bad magic)",
    "random": "not a recording: expected an MCAP file, a ROS 1 .bag or a ROS 2 bag folder",
    "notes.txt": "not a recording",
    "cut_in_magic.mcap": "truncated after 5 bytes, inside the MCAP magic",
    "header_only.mcap": "contains none of the topics /trisect/points, /tf_static, "
                        "/groundtruth/object (truncated after",
    "cut_in_first_chunk.mcap": "(no summary or footer): it ends inside a chunk that starts at "
                               "byte {first_chunk})",
    "json_only.mcap": "contains none of the topics /trisect/points, /tf_static, "
                      "/groundtruth/object; it has /trisect/points (json, jsonschema)",
    "protobuf.mcap": "it has /trisect/points (protobuf, protobuf)",
    "no_camera.mcap": "no /trisect/points (sensor_msgs/msg/PointCloud2) to replay: it has only "
                      "/groundtruth/object",
    "camera_not_clouds.mcap": "it has /trisect/points as std_msgs/msg/String",
    "random.bag": "not a ROS 1 bag (bad magic",
    "bag_magic_only.bag": "cannot read the ROS 1 bag",
    "bag_cut.bag": "truncated ROS 1 bag: it ends at byte",
    "bag_index_corrupt.bag": "cannot read the ROS 1 bag: AnyReaderError: Bag index looks damaged",
    "ros2_no_metadata": "folder without metadata.yaml, not a recording: expected an MCAP file, "
                        "a ROS 1 .bag or a ROS 2 bag folder (it holds good_ros2.db3)",
    "ros2_bad_metadata": "cannot read the ROS 2 bag: AnyReaderError: Could not load YAML",
    "ros2_no_db3": "cannot read the ROS 2 bag: AnyReaderError: Some database files are missing",
    "ros2_corrupt_db3": "cannot read the ROS 2 bag: AnyReaderError: Cannot open database",
    "plain_folder": "folder without metadata.yaml",
}

#: What `wavegrasp latency` says of each input that is no usable run file.
LATENCY_REFUSES = {
    "missing.mcap": "no such file",
    "empty.mcap": "empty file (0 bytes)",
    "random.mcap": "not a readable MCAP file: bad magic",
    "random": "not a readable MCAP file: bad magic",
    "notes.txt": "not a readable MCAP file: bad magic, it starts with b'hello, n'",
    "cut_in_magic.mcap": "truncated after 5 bytes, inside the MCAP magic",
    "header_only.mcap": "no wavegrasp/gate/decision messages with a trace (truncated after",
    "cut_in_first_chunk.mcap": "it ends inside a chunk that starts at byte",
    "cut_in_chunk.mcap": "it ends inside a chunk that starts at byte",
    "cut_after_chunk.mcap": "it ends after a complete chunk record",
    "corrupt_chunk.mcap": "corrupt MCAP: the chunk at byte",
    "corrupt_chunk_cut.mcap": "corrupt MCAP: the chunk at byte",
    "json_only.mcap": "no wavegrasp/gate/decision messages with a trace",
    "protobuf.mcap": "no wavegrasp/gate/decision messages with a trace",
    "good.bag": "not a readable MCAP file: it is a ROS 1 bag",
    "bag_cut.bag": "not a readable MCAP file: it is a ROS 1 bag",
    "good_ros2": "a folder, not an MCAP file",
    "plain_folder": "a folder, not an MCAP file",
}


def one_clear_line(err: str, path: Path, problem: str, command: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"wavegrasp {command}: {path}: "), lines[0]
    assert problem in lines[0], lines[0]


@pytest.mark.parametrize("name", sorted(PLAYER_REFUSES))
def test_player_names_the_file_and_the_problem(name: str, bad: dict[str, Path], tank: Path,
                                               capsys) -> None:
    assert player.main([str(bad[name])]) == 2
    problem = PLAYER_REFUSES[name].format(first_chunk=chunk_offsets(tank)[0][0])
    one_clear_line(capsys.readouterr().err, bad[name], problem, "player")


@pytest.mark.parametrize("name", sorted(LATENCY_REFUSES))
def test_latency_names_the_file_and_the_problem(name: str, bad: dict[str, Path],
                                                capsys) -> None:
    path = bad.get(name) or bad["missing.mcap"].parent / name
    assert latency.main([str(path)]) == 2
    one_clear_line(capsys.readouterr().err, path, LATENCY_REFUSES[name], "latency")


def test_the_cli_entry_prints_no_traceback(bad: dict[str, Path]) -> None:
    """As a user runs them: ``python -m wavegrasp ...``, one line on stderr."""
    for command, name in [("player", "bag_cut.bag"), ("latency", "corrupt_chunk.mcap"),
                          ("player", "ros2_bad_metadata")]:
        result = subprocess.run(wavegrasp_cmd(command, str(bad[name])), capture_output=True,
                                text=True, timeout=60)
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
        assert str(bad[name]) in result.stderr


@pytest.mark.parametrize("name", ["cut_in_chunk.mcap", "cut_after_chunk.mcap"])
def test_a_cut_recording_reads_to_its_last_complete_chunk(
        name: str, bad: dict[str, Path], tank: Path, tank_messages: list[RecordedMessage]) -> None:
    rec = open_recording(bad[name])
    assert rec.problem is not None and rec.problem.startswith("truncated after")
    got: list[RecordedMessage] = []
    with pytest.raises(TruncatedRecording) as err:
        got.extend(rec.messages())
    end_ns = chunk_end_times(tank)[1]  # both files keep the first two chunks whole
    assert len(got) == rec.message_count == sum(m.log_time_ns <= end_ns for m in tank_messages)
    assert got == tank_messages[: len(got)]
    assert str(err.value).startswith(f"{bad[name]}: truncated after")
    assert f"read the {len(got)} messages before it" in str(err.value)


def test_damage_after_the_data_loses_nothing(bad: dict[str, Path],
                                             tank_messages: list[RecordedMessage]) -> None:
    rec = open_recording(bad["cut_in_summary.mcap"])
    assert rec.problem is not None and "no message is lost" in rec.problem
    assert list(rec.messages()) == tank_messages


def test_a_corrupt_chunk_is_named_by_byte_and_time(bad: dict[str, Path], tank: Path) -> None:
    start = chunk_offsets(tank)[1][0]
    rec = open_recording(bad["corrupt_chunk.mcap"])  # indexed: found when read
    with pytest.raises(RecordingError, match=rf"corrupt_chunk\.mcap: corrupt MCAP: the chunk at "
                       rf"byte {start} \(its messages from 0\.\d s to 0\.\d s\) fails its CRC"):
        list(rec.messages())


@pytest.fixture
def offline_bus() -> Iterator[Bus]:
    """A zenoh session that talks to no one: the player publishes into the void."""
    bus = Bus(Settings(service="player", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    yield bus
    bus.close()


@pytest.mark.parametrize("name,error", [
    ("cut_in_chunk.mcap", "truncated after"),  # found when opened (no index): warned of
    ("corrupt_chunk_cut.mcap", "corrupt MCAP: the chunk at byte"),  # likewise
    ("corrupt_chunk.mcap", "corrupt MCAP: the chunk at byte"),  # indexed: found when read
])
def test_the_player_plays_what_is_whole_then_warns(
        name: str, error: str, bad: dict[str, Path], tank: Path,
        tank_messages: list[RecordedMessage], offline_bus: Bus, capsys, caplog) -> None:
    rec = player.open_for_replay(bad[name])
    settings = player.PlayerSettings(service="player", pace="fast", ack_services=[])
    play = player.Player(settings, rec, bus=offline_bus)
    with caplog.at_level(logging.WARNING, logger="wavegrasp.player"):
        assert play.serve() == 0  # what could be played was: the replay is finished
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    if rec.problem:
        assert len(warnings) == 1 and warnings[0].startswith(f"{bad[name]}: {rec.problem}")
        assert f"playing its {rec.message_count} readable messages" in warnings[0]
    else:
        assert not warnings
    end_ns = chunk_end_times(tank)[0 if "corrupt" in name else 1]  # the last whole chunk's
    assert play.messages == sum(m.log_time_ns <= end_ns for m in tank_messages) > 0
    assert play.frames == sum(m.topic == "/trisect/points"
                              for m in tank_messages[: play.messages])
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"wavegrasp player: warning: {bad[name]}: ") and error in err, err
    assert err.strip().endswith(f"played {play.frames} camera frames"), err


# -- a killed recorder's run.mcap -------------------------------------------------------------


def chain(t0: int) -> list[Hop]:
    hops, t = [Hop(service="source", recv_ns=t0, sent_ns=t0)], t0
    for name in ["perception", "predictor", "planner", "gate"]:
        hops.append(Hop(service=name, recv_ns=t + MS, sent_ns=t + 3 * MS))
        t += 3 * MS
    return hops


def write_run(path: Path, decisions: int, per_flush: int) -> list[int]:
    """Gate decisions written as the recorder writes (zstd chunks, a flush every `per_flush`
    decisions, as its 0.5 s timer does); returns the file size after each flush."""
    flushed = []
    with path.open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="wavegrasp recorder")
        schema = w.register_schema("GateDecision", "jsonschema", b"{}")
        channel = w.register_channel("wavegrasp/gate/decision", "json", schema)
        for k in range(decisions):
            t = 10**18 + k * 100 * MS
            msg = GateDecision(header=Header(seq=k, stamp_ns=t, trace=chain(t)), plan_id=f"p{k}",
                               go=False, mean_error_m=None, threshold_m=0.01, window_s=2.0)
            w.add_message(channel, t, msg.model_dump_json().encode(), t, sequence=k)
            if (k + 1) % per_flush == 0:
                w.flush()
                flushed.append(f.tell())
        w.finish()
    return flushed


def test_latency_reads_a_killed_recorders_run_to_its_last_flush(tmp_path: Path,
                                                                capsys) -> None:
    run = tmp_path / "whole.mcap"
    flushed = write_run(run, decisions=40, per_flush=10)
    data = run.read_bytes()
    whole = latency.read_latency(run).end_to_end
    assert len(whole) == 40
    cuts = [(flushed[1], 20),  # killed right after a flush
             (flushed[2] + 200, 30),  # killed while writing the next chunk
             ((flushed[2] + flushed[3]) // 2, 30),
             (flushed[3] - 3, 40)]  # only its last message index is cut: nothing is lost
    for cut_at, decisions in cuts:
        killed = tmp_path / f"killed_{cut_at}" / "run.mcap"
        killed.parent.mkdir()
        killed.write_bytes(data[:cut_at])
        assert latency.main([str(killed)]) == 0
        out, err = capsys.readouterr()
        assert f"{killed}: {decisions} gate decisions" in out
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert err.startswith(f"wavegrasp latency: warning: {killed}: truncated after "
                              f"{cut_at} bytes (no summary or footer)")
        span = f"(0.0 s to {decisions / 10 - 0.1:.1f} s)"
        assert f"read the {decisions} messages before it {span}" in err
        assert latency.read_latency(killed).end_to_end == whole[:decisions]
        seqs: list[int] = []
        with pytest.raises(TruncatedRecording):
            for _, _, message in read_mcap(killed):
                seqs.append(message.sequence)
        assert seqs == list(range(decisions))


def test_up_names_a_recording_it_cannot_replay(bad: dict[str, Path], tmp_path: Path) -> None:
    path = bad["protobuf.mcap"]
    result = subprocess.run(wavegrasp_cmd("up", str(path), "--pace", "fast", "--out",
                                          str(tmp_path / "run")),
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and not (tmp_path / "run").exists(), "nothing started"
    one_clear_line(result.stderr, path, "contains none of the topics", "up")
    assert "(protobuf, protobuf)" in result.stderr
