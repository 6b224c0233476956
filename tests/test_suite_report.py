"""The random suite's report: what it says of a scenario whose trials never began."""

from __future__ import annotations

from wavegrasp.ops.suite import ScenarioResult, factors, observed_share
from wavegrasp.ops.suite_report import markdown
from wavegrasp.wavetank.suite import draw_scenarios


def test_a_scenario_never_observed_shows_why_its_trials_failed() -> None:
    """Perception reported the object in 8 of 945 frames: no trial began. The row says how
    much was observed and that both trials went unfinished; the report counts them."""
    s = draw_scenarios(1, 41, seconds=63.0)[0][0]
    summary = {"services": {"perception": {"counters": {
        "observed": 8, "missing: partial view": 933, "missing: object not found": 4}}}}
    assert observed_share(summary) == 8 / 945
    assert observed_share({}) == 0.0
    never = ScenarioResult("blend", s.name, factors(s), 0, 0, {}, observed_share(summary),
                           trials=2, success_attempt=[0, 0], unfinished=2)
    grasped = ScenarioResult("blend", "other", factors(s), 4, 4, {}, 1.0, trials=2,
                             success_attempt=[1, 1])
    md = markdown([never, grasped], {"scenarios": 2, "seed": 41, "trials": 2, "attempts": 3,
                                     "elapsed_s": 60.0}, {}, [])
    row = next(line for line in md.splitlines() if line.startswith(f"| {s.name} |"))
    assert "| 1% |" in row and row.endswith("| unfinished 2 |"), row
    assert "| 100% |" in next(line for line in md.splitlines() if line.startswith("| other |"))
    assert "2 trials did not end before their recording did" in md
    assert "Success 50.0% on the first attempt" in md
