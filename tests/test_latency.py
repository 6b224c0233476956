"""``wavegrasp latency`` on MCAP files whose traces are known."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.writer import Writer

from wavegrasp.ops.latency import format_table, main, merge, read_latency
from wavegrasp.recording_io.typestore import ros2_msgdef
from wavegrasp.runtime.trace import check_trace
from wavegrasp.schemas import GateDecision, Header, Hop, ObjectObservation
from wavegrasp.schemas.ros import msgtype, to_cdr

MS = 1_000_000


def chain(t0: int, perception_ms: float, planner_ms: float) -> list[Hop]:
    """source -> perception -> predictor -> planner -> gate, 1 ms per transfer."""
    hops, t = [Hop(service="source", recv_ns=t0, sent_ns=t0)], t0
    for name, busy in [("perception", perception_ms), ("predictor", 0.5),
                       ("planner", planner_ms), ("gate", 0.2)]:
        t += MS
        hops.append(Hop(service=name, recv_ns=t, sent_ns=t + int(busy * MS)))
        t += int(busy * MS)
    return hops


def write_run(path: Path, observed: list[int], decisions: list[list[Hop]],
              clouds: list[int] = (), json: bool = False) -> None:
    """A run file: observations of frames ``observed``, the ``decisions``' traces, and the
    camera clouds of frames ``clouds`` (their bytes do not matter here), 100 ms apart. Our
    messages as a run records them (ROS 2 channels), or ``json`` as runs before did."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        schema = w.register_schema("x", "jsonschema", b"{}")
        points = w.register_channel("/trisect/points", "cdr", schema)
        for seq in clouds:
            w.add_message(points, seq * 100 * MS, b"", seq * 100 * MS, sequence=seq)

        def channel(key: str, model: type) -> tuple[int, Callable]:
            if json:
                return (w.register_channel(key, "json", w.register_schema(
                    model.__name__, "jsonschema", b"{}")), lambda m: m.model_dump_json().encode())
            name = msgtype(model.__name__)
            return (w.register_channel("/" + key, "cdr", w.register_schema(
                name, "ros2msg", ros2_msgdef(name).encode())), to_cdr)
        obs, encode_obs = channel("wavegrasp/perception/object", ObjectObservation)
        dec, encode_dec = channel("wavegrasp/gate/decision", GateDecision)
        for seq in observed:  # the first without a trace (a camera that sends no publish time)
            trace = [] if seq == observed[0] else [
                Hop(service="source", recv_ns=seq * 100 * MS, sent_ns=seq * 100 * MS),
                Hop(service="perception", recv_ns=seq * 100 * MS + MS,
                    sent_ns=seq * 100 * MS + 5 * MS)]
            msg = ObjectObservation(header=Header(seq=seq, stamp_ns=seq * 100 * MS, trace=trace))
            w.add_message(obs, seq, encode_obs(msg), seq)
        for k, trace in enumerate(decisions):
            msg = GateDecision(header=Header(seq=k, stamp_ns=k * 100 * MS, trace=trace),
                               plan_id=f"p{k}", go=False, mean_error_m=None, threshold_m=0.01,
                               window_s=2.0)
            w.add_message(dec, 1000 + k, encode_dec(msg), 1000 + k)
        w.finish()


def test_hops_and_end_to_end_from_decision_traces(tmp_path: Path) -> None:
    run = tmp_path / "run.mcap"
    write_run(run, observed=[0, 1, 2, 4, 5], decisions=[
        chain(10**18, 5.0, 4.0), chain(10**18 + 100 * MS, 7.0, 12.0),
        chain(10**18 + 200 * MS, 6.0, 8.0)])
    lat = read_latency(run)
    rows = {r["hop"]: r for r in lat.table()}
    assert rows["planner"]["p50"] == pytest.approx(8.0)
    assert rows["planner"]["max"] == pytest.approx(12.0)
    assert rows["source -> perception"]["p50"] == pytest.approx(1.0)
    # 4 transfers of 1 ms, perception, 0.5 ms predictor, planner, 0.2 ms gate.
    assert lat.end_to_end == pytest.approx([13.7, 23.7, 18.7])
    assert (lat.frames_published, lat.frames_observed, lat.frames_dropped) == (6, 5, 1)
    assert lat.to_observation == pytest.approx([5.0] * 4)  # every frame with a trace
    assert rows["camera frame -> observation"]["n"] == 4
    assert "1 dropped" in format_table(lat)
    assert main([str(run), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "latency.png").stat().st_size > 0


def test_several_runs_are_taken_together(tmp_path: Path, capsys) -> None:
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    write_run(a, observed=[0, 1, 2], decisions=[chain(10**18, 5.0, 4.0)])
    # b recorded as runs were before our messages became ROS 2 types: JSON channels.
    write_run(b, observed=[0, 2], decisions=[chain(10**18, 7.0, 12.0),
                                             chain(10**18 + 100 * MS, 6.0, 8.0)], json=True)
    lat = merge([read_latency(a), read_latency(b)])
    assert lat.end_to_end == pytest.approx([13.7, 23.7, 18.7])
    assert (lat.frames_published, lat.frames_observed, lat.frames_dropped) == (6, 5, 1)
    assert {r["hop"]: r["n"] for r in lat.table()}["planner"] == 3
    # A recorder that wrote one cloud in three: the frames and their interval still count.
    write_run(a, observed=[0, 1, 2, 3, 4, 6, 7], decisions=[chain(10**18, 5.0, 4.0)],
              clouds=[0, 3, 6])
    thinned = read_latency(a)
    assert (thinned.frames_published, thinned.frames_dropped) == (8, 1)
    assert thinned.frame_interval_ms == pytest.approx(100.0)
    assert main([str(a), str(b)]) == 0
    assert "2 runs (" in capsys.readouterr().out
    assert main([str(a), str(tmp_path / "missing.mcap")]) == 2
    assert "missing.mcap" in capsys.readouterr().err


def test_broken_traces_and_files_are_named(tmp_path: Path, capsys) -> None:
    trace = chain(10**18, 5.0, 4.0)
    trace[3].recv_ns = trace[2].sent_ns - 1  # the planner got it before the predictor sent it
    with pytest.raises(ValueError, match=r"hop 3 \(planner\) received before hop 2"):
        check_trace(trace)
    run = tmp_path / "run.mcap"
    write_run(run, observed=[0], decisions=[trace])
    with pytest.raises(ValueError, match="run.mcap: hop 3"):
        read_latency(run)
    (tmp_path / "notes.txt").write_text("not a recording")
    assert main([str(tmp_path / "notes.txt")]) == 2
    assert "notes.txt: not a readable MCAP file" in capsys.readouterr().err
    write_run(run, observed=[0, 1], decisions=[])
    assert main([str(run)]) == 2
    assert "no wavegrasp/gate/decision messages" in capsys.readouterr().err
