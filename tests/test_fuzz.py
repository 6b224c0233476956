"""Every subscriber survives malformed input ("Reliability and security").

Each service class runs its own loop on a thread, over a real router and real zenoh sessions,
and a test session publishes to every key it subscribes (taken from ``bus.subscriptions``, so
a new subscription is fuzzed too; a wildcard gets a sample of concrete keys) every kind of bad
input, seeded: random bytes, valid JSON of the wrong type or of another message type, JSON
missing required fields, NaN / inf / numbers too big, and on CDR keys truncated messages, clouds
empty, huge, of NaN points or with a wrong field layout, broken transforms and attachments; then
valid messages with duplicate and out-of-order stamps. Each key's batch ends with a valid
message. Checked: every malformed payload is counted under its key and logged with a reason
naming the problem; each valid-but-odd one is counted the same way where taking it would corrupt
the service (an older or repeated camera frame, observation or prediction) and otherwise taken;
the loop lives on and the service still handles valid input correctly afterwards.

The cases are in ``fuzz_cases.py``, the harness in ``fuzz_harness.py``, how each service is fed
in ``fuzz_pipeline.py`` and ``fuzz_sim_recorder_player.py``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from wavegrasp.checks import StampOrder

from conftest import Router, stop
from fuzz_harness import BadLog, Harness, Sample, Scenario, concrete_keys
from fuzz_pipeline import GateScenario, PerceptionScenario, PlannerScenario, PredictorScenario
from fuzz_sim_recorder_player import PlayerScenario, RecorderScenario, SimScenario


@pytest.fixture(scope="module")
def sample() -> Sample:
    return Sample()


@pytest.fixture(scope="module")
def router() -> Iterator[Router]:
    r = Router()
    yield r
    stop(r.proc)


@pytest.fixture
def bad_log() -> Iterator[BadLog]:
    handler = BadLog()
    logger = logging.getLogger("wavegrasp.runtime.bus")
    logger.addHandler(handler)
    yield handler
    logger.removeHandler(handler)


SCENARIOS = [PerceptionScenario, PredictorScenario, PlannerScenario, GateScenario,
             SimScenario, RecorderScenario, PlayerScenario]


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.name for s in SCENARIOS])
def test_every_subscriber_survives_malformed_input(
        scenario: type[Scenario], router: Router, sample: Sample, bad_log: BadLog,
        tmp_path: Path) -> None:
    feed = scenario(router, sample, tmp_path)
    service = feed.make()
    h = Harness(router, service, bad_log)
    try:
        h.start()
        feed.before(h)
        keys = concrete_keys(service)
        assert keys, f"{service.name} subscribes nothing"
        for key in keys:
            cases = feed.cases(key)
            h.fuzz_key(key, cases, feed.valid(key))
        feed.after(h)
        if not h.stopped:
            h.alive()
        print(f"\n{service.name}: " + "; ".join(
            f"{key}: {sum(kinds.values())} ({', '.join(f'{k} {n}' for k, n in kinds.items())})"
            for key, kinds in h.matrix.items()))
    finally:
        h.stop()
    assert h.error is None, f"{service.name} loop died: {h.error!r}"


def test_stamp_order_refuses_repeats_and_the_past_but_takes_a_restart() -> None:
    order = StampOrder(restart_s=1.0)
    order.check(5 * 10**9)
    with pytest.raises(ValueError, match=r"^duplicate: stamp 5000000000 <= last 5000000000$"):
        order.check(5 * 10**9)
    with pytest.raises(ValueError, match=r"^out of order: stamp 4100000000 <= last 5000000000$"):
        order.check(4_100_000_000)
    order.check(4 * 10**9)  # a second back or more: the stream starts over
    assert order.last_ns == 4 * 10**9
    order.check(4 * 10**9 + 1)
