"""The fuzz test's harness (``test_fuzz.py``): the sample recording, the bus's "bad message"
log, a service on its own loop thread fed by a test session, and the base of the scenarios that
say how each service is fed (``fuzz_pipeline.py``, ``fuzz_sim_recorder_player.py``)."""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from pydantic import BaseModel

from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import decode_points, decode_pose
from wavegrasp.runtime.service import Service
from wavegrasp.schemas import (
    HEARTBEAT_KEY,
    KEY_TYPES,
    ROS_KEYS,
    Clock,
    FrameAck,
    Heartbeat,
    MotionPrediction,
    PredictionSample,
    model_for_key,
)

from conftest import ROOT, Router, wait_until
from fuzz_cases import (
    EXAMPLES,
    Case,
    cdr_cases,
    header,
    json_cases,
    message_case,
    own_cdr_cases,
    rng_for,
    tf_semantic_cases,
)

SAMPLE = ROOT / "recordings" / "wave1-buoy-5s.mcap"
#: Concrete keys a wildcard subscription (the recorder's ``**``) is fuzzed on.
WILDCARD_SAMPLE = sorted({*KEY_TYPES, *ROS_KEYS, "wavegrasp/gate/ack",
                          "wavegrasp/planner/stats", "fuzz/unknown"})


class Sample:
    """The sample recording: its transforms, camera frames and ground truth."""

    def __init__(self) -> None:
        messages = list(open_recording(SAMPLE).messages())
        self.tf = next(m.cdr for m in messages if m.topic == "/tf_static")
        self.frames = [m for m in messages if m.topic == "/trisect/points"]
        truths = [m for m in messages if m.topic == "/groundtruth/object"]
        self.truth_cdr = [m.cdr for m in truths]
        poses = [decode_pose(m.cdr) for m in truths]
        self.truth_ns = np.array([s for _, _, s in poses])
        self.truth_xyz = np.array([T[:3, 3] for T, _, _ in poses])

    def truth_at(self, stamp_ns: int) -> np.ndarray:
        return self.truth_xyz[int(np.searchsorted(self.truth_ns, stamp_ns))]

    def camera_points(self, k: int) -> np.ndarray:
        return decode_points(self.frames[k].cdr).points

    def prediction(self, i0: int, warm: bool = True, seq: int = 1) -> MotionPrediction:
        """The true motion from truth sample ``i0`` on, 3 s, every 50 ms: a perfect forecast."""
        idx = range(i0, min(i0 + 300, len(self.truth_ns)), 5)
        return MotionPrediction(
            header=header(int(self.truth_ns[i0]), seq), model="truth", period_s=1.5, warm=warm,
            samples=[PredictionSample(t_ns=int(self.truth_ns[i]), x=self.truth_xyz[i][0],
                                      y=self.truth_xyz[i][1], z=self.truth_xyz[i][2],
                                      sigma=0.002) for i in idx])


# --- the harness ---------------------------------------------------------------------------

class BadLog(logging.Handler):
    """The bus's "bad message" warnings: (service, key, reason)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[tuple[str, str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if str(record.msg).startswith("%s: bad message on"):
            service, key, _n, reason = record.args
            self.records.append((service, key, reason))

    def reasons(self, service: str, key: str) -> list[str]:
        return [r for s, k, r in list(self.records) if s == service and k == key]


class Harness:
    """A service on its own loop thread, and the test's session that feeds it."""

    def __init__(self, router: Router, service: Service, bad_log: BadLog) -> None:
        self.service = service
        self.fuzz = router.bus("fuzz")
        self.log = bad_log
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._loop, name=service.name, daemon=True)
        self.collected: dict[str, list] = {}
        self.timings: dict[str, float] = {}
        self.accepted: dict[str, int] = {}  # key -> payloads the service took (no bad count)
        self.matrix: dict[str, dict[str, int]] = {}  # key -> kind of input -> payloads
        self.stopped = False

    def _loop(self) -> None:
        """What ``Service.run`` does, less the signal handlers (the main thread's)."""
        s = self.service
        try:
            s.bus.declare_alive()
            s.on_start()
            Service.serve(s)  # the player: its loop, without the playback
            s.drain()
            s.on_stop()
        except BaseException as exc:  # a dying loop is what this test is about
            self.error = exc
            raise

    def start(self) -> None:
        self.thread.start()
        assert not self.fuzz.wait_for_services([self.service.name], timeout_s=15)

    def stop(self) -> None:
        if self.stopped:
            return
        self.stopped = True
        self.service.stop()
        self.thread.join(20)
        self.fuzz.close()
        self.service.bus.close()

    def alive(self) -> None:
        assert self.error is None, f"{self.service.name} loop died: {self.error!r}"
        assert self.thread.is_alive(), f"{self.service.name} loop ended"

    # -- sending and receiving -------------------------------------------------------------
    def send(self, key: str, case: Case) -> None:
        self.fuzz.session.put(key, case.payload, encoding=zenoh.Encoding(case.encoding),
                              attachment=case.attachment,
                              congestion_control=zenoh.CongestionControl.BLOCK)

    def send_msg(self, key: str, msg: BaseModel) -> None:
        self.send(key, message_case("valid", msg))

    def routes(self, key: str) -> int:
        """How many of the service's subscriptions take ``key``."""
        ke = zenoh.KeyExpr(key)
        return sum(zenoh.KeyExpr(s).includes(ke) for s in self.service.bus.subscriptions)

    def deliver(self, key: str, cases: list[Case], timeout: float = 30.0) -> None:
        """Send ``cases`` on ``key``; wait until the service has begun the last of them (so it
        has finished every one before it: one loop handles them in order)."""
        bus, before, n = self.service.bus, self.service.bus.received[key], len(cases)
        n *= self.routes(key)
        for case in cases:
            self.send(key, case)
        assert wait_until(lambda: bus.received[key] >= before + n, timeout=timeout), (
            f"{self.service.name} took {bus.received[key] - before} of {n} samples on {key}")

    def collect(self, key: str, model: type[BaseModel]) -> list:
        got: list = []
        self.fuzz.subscribe(key, lambda m, d: got.append(m), model)
        self.collected[key] = got
        return got

    def wait_for(self, key: str, predicate: Callable[[Any], bool], timeout: float = 20.0):
        """The first message collected on ``key`` that satisfies ``predicate``."""
        got = self.collected[key]

        def found() -> Any:
            while not self.fuzz.inbox.empty():
                self.fuzz.dispatch(self.fuzz.inbox.get())
            return next((m for m in got if predicate(m)), None)

        assert wait_until(lambda: found() is not None, timeout=timeout), (key, got[-3:])
        return found()

    # -- fuzzing --------------------------------------------------------------------------
    def fuzz_key(self, key: str, cases: list[Case], sentinel: Case) -> None:
        """Send every case then ``sentinel`` (valid) on ``key``; check each one that is
        malformed was counted and logged under ``key`` with its reason, and nothing else was."""
        bus, name = self.service.bus, self.service.name
        bad_before, logged_before = bus.bad[key], len(self.log.reasons(name, key))
        started = time.monotonic()
        self.deliver(key, [*cases, sentinel])
        self.timings[key] = time.monotonic() - started
        expected = [(c.kind, c.expect(name)) for c in cases
                    if c.expect(name) is not None] * self.routes(key)
        got = self.log.reasons(name, key)[logged_before:]
        pairs = match(got, [pattern for _, pattern in expected])
        surprises = [r for i, r in enumerate(got) if i not in pairs]
        unmatched = [e for j, e in enumerate(expected) if j not in pairs.values()]
        assert not surprises and not unmatched, (
            f"{name} on {key}:\n  counted with a reason no case expects: {surprises}\n"
            f"  not counted, or with another reason: {unmatched}")
        assert bus.bad[key] - bad_before == len(expected)
        if expected:
            assert re.search(expected[-1][1], bus.last_bad_reason[key]), bus.last_bad_reason
        self.accepted[key] = sum(c.expect(name) is None for c in cases) + 1
        kinds = self.matrix.setdefault(key, {})
        for c in cases:
            group = c.kind.split(" (")[0] if c.expect(name) else f"taken: {c.kind}"
            kinds[group] = kinds.get(group, 0) + 1
        self.alive()


def match(reasons: list[str], patterns: list[str]) -> dict[int, int]:
    """Pair each reason with a pattern it matches, as many as can be (reasons of two routes
    interleave): reason index -> pattern index."""
    owner: dict[int, int] = {}  # pattern -> reason

    def place(i: int, seen: set[int]) -> bool:
        for j, pattern in enumerate(patterns):
            if j not in seen and re.search(pattern, reasons[i]):
                seen.add(j)
                if j not in owner or place(owner[j], seen):
                    owner[j] = i
                    return True
        return False

    for i in range(len(reasons)):
        place(i, set())
    return {i: j for j, i in owner.items()}


def concrete_keys(service: Service) -> list[str]:
    """The keys to fuzz: each subscription, a wildcard one as a sample of concrete keys."""
    keys: list[str] = []
    for sub in service.bus.subscriptions:
        if "*" in sub or "$" in sub:
            keys += [k for k in WILDCARD_SAMPLE if zenoh.KeyExpr(sub).includes(zenoh.KeyExpr(k))]
        else:
            keys.append(sub)
    return list(dict.fromkeys(keys))


# --- the services ----------------------------------------------------------------------------

class Scenario:
    """How one service is fed: valid traffic before and after the fuzz, a valid message per
    key to end each batch, and each key's well-formed but bad or odd messages."""

    name = ""

    def __init__(self, router: Router, sample: Sample, tmp_path: Path) -> None:
        self.env, self.sample, self.tmp_path = router.env, sample, tmp_path
        self.t_ns = int(sample.frames[0].log_time_ns)
        self.acks = 0

    def make(self) -> Service:
        raise NotImplementedError

    def before(self, h: Harness) -> None:
        """Valid traffic that gives the service state to protect."""

    def after(self, h: Harness) -> None:
        """Valid traffic after the fuzz, and checks that the service still does its job."""

    def valid(self, key: str) -> Case:
        """A valid message on ``key`` that does not disturb the checks after the fuzz."""
        if key == "wavegrasp/clock":
            return message_case("valid", Clock(header=header(self.t_ns), rate=0.0))
        if key == HEARTBEAT_KEY:  # the gate is there: nothing changes
            return message_case("valid", Heartbeat(header=header(self.t_ns), period_s=0.1))
        if key.endswith("/ack"):
            self.acks += 1
            return message_case("valid", FrameAck(header=header(self.t_ns),
                                                  service=key.split("/")[1],
                                                  frame_seq=self.acks))
        raise AssertionError(f"{self.name}: no valid message for {key}: add one to the scenario")

    def cdr_basis(self, key: str) -> bytes:
        """A valid CDR message of ``key`` to truncate."""
        return self.valid(key).payload

    def semantic(self, key: str) -> list[Case]:
        """Well-formed messages of the key's type that are bad in what they say."""
        return tf_semantic_cases() if key == "tf_static" else []

    def odd(self, key: str) -> list[Case]:
        """Valid messages with duplicate or out-of-order stamps, and other odd ones."""
        if key == "wavegrasp/clock":  # the clock follows the player, a replay may restart
            return [message_case("duplicate tick", Clock(header=header(self.t_ns), rate=0.0)),
                    message_case("tick from before", Clock(header=header(self.t_ns - 10**9)))]
        if key.endswith("/ack"):  # acknowledging a frame again is harmless
            ack = FrameAck(header=header(self.t_ns), service=key.split("/")[1],
                           frame_seq=self.acks)
            return [message_case("duplicate ack", ack),
                    message_case("ack of an older frame",
                                 ack.model_copy(update={"frame_seq": max(0, self.acks - 1)}))]
        return []

    def cases(self, key: str) -> list[Case]:
        rng = rng_for(self.name, key)
        model = model_for_key(key)
        if key in ROS_KEYS:
            fuzz = cdr_cases(key, ROS_KEYS[key], self.cdr_basis(key), rng)
        else:  # a key outside the contract: what its sender's encoding names
            example = EXAMPLES[model or FrameAck]()
            fuzz = [*json_cases(key, example, rng), *own_cdr_cases(key, example, rng)]
        return [*fuzz, *self.semantic(key), *self.odd(key)]
