"""The random suite's report: ``report.json``, ``report.md`` and PNG plots (success and plan
rate by factor; failures by kind), overall, per scenario and per bucket of each factor."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from wavegrasp.ops.report import FAILURES, unfinished_lines

#: Buckets per numeric factor (equal counts of scenarios in each).
BUCKETS = 3


def pooled(results: list) -> dict[str, float]:
    """Success over all the trials of ``results`` (first attempt, after reattempts), the
    plan rate over all their planned-on predictions, and the worst scenario's plan rate."""
    trials = sum(r.trials for r in results)
    return {"first_attempt": sum(r.rate(1) * r.trials for r in results) / max(trials, 1),
            "after_reattempts": sum(r.rate(99) * r.trials for r in results) / max(trials, 1),
            "plan_rate": sum(r.plans for r in results) / max(sum(r.planned_on for r in results),
                                                             1),
            "worst_plan_rate": min((r.plan_rate for r in results), default=0.0),
            "trials": trials, "scenarios": len(results)}


def buckets(results: list, factor: str) -> list[tuple[str, list]]:
    """``results`` grouped by ``factor``: by value for a text factor, else in
    :data:`BUCKETS` ranges holding about equal numbers of scenarios."""
    values = [r.factors[factor] for r in results]
    if isinstance(values[0], str):
        return [(v, [r for r in results if r.factors[factor] == v])
                for v in sorted(set(values))]
    edges = np.quantile(values, np.linspace(0.0, 1.0, BUCKETS + 1))
    groups = []
    for i in range(BUCKETS):
        lo, hi = edges[i], edges[i + 1]
        mine = [r for r in results if lo <= r.factors[factor] <= hi
                and (i == 0 or r.factors[factor] > lo)]
        if mine:
            groups.append((f"{lo:.3g}-{hi:.3g}", mine))
    return groups


def by_factor(results: list) -> dict[str, list[tuple[str, dict[str, float]]]]:
    return {f: [(label, pooled(group)) for label, group in buckets(results, f)]
            for f in results[0].factors} if results else {}


def write_report(out: Path, results: list, settings: dict, scenarios: dict,
                 out_of_reach: dict[str, str], redrawn: list[str]) -> None:
    """results : :class:`~wavegrasp.ops.suite.ScenarioResult` list, in run order; scenarios :
    every drawn scenario by name; out_of_reach : name -> why it was not run."""
    from wavegrasp.ops.suite import as_json

    predictors = list(dict.fromkeys(r.predictor for r in results))
    report = {"settings": settings, "runs": as_json(results),
              "overall": {p: pooled([r for r in results if r.predictor == p])
                          for p in predictors},
              "by_factor": {p: by_factor([r for r in results if r.predictor == p])
                            for p in predictors},
              "out_of_reach": out_of_reach, "redrawn": redrawn,
              "scenarios": {k: json.loads(s.model_dump_json()) for k, s in scenarios.items()}}
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    if results:
        plot_by_factor(out / "by_factor.png", [r for r in results
                                               if r.predictor == predictors[0]])
    (out / "report.md").write_text(markdown(results, settings, out_of_reach, redrawn))


def markdown(results: list, settings: dict, out_of_reach: dict[str, str],
             redrawn: list[str]) -> str:
    lines = [f"# wavegrasp eval --suite random: {settings['scenarios']} scenarios, seed "
             f"{settings['seed']}, {settings['trials']} trials x up to {settings['attempts']} "
             f"attempts, {settings['elapsed_s'] / 60:.1f} min", ""]
    for p in dict.fromkeys(r.predictor for r in results):
        mine = [r for r in results if r.predictor == p]
        o = pooled(mine)
        lines += [f"## {p}", "",
                  f"Success {o['first_attempt']:.1%} on the first attempt, "
                  f"{o['after_reattempts']:.1%} after reattempts, over {o['trials']} trials in "
                  f"{o['scenarios']} scenarios. The planner planned {o['plan_rate']:.1%} of "
                  f"the predictions it planned on (worst scenario {o['worst_plan_rate']:.1%}).",
                  "", "| factor | bucket | scenarios | first attempt | after reattempts | "
                  "plan rate |", "|---|---|---|---|---|---|"]
        for factor, rows in by_factor(mine).items():
            for label, g in rows:
                lines.append(f"| {factor} | {label} | {g['scenarios']} | "
                             f"{g['first_attempt']:.0%} | {g['after_reattempts']:.0%} | "
                             f"{g['plan_rate']:.0%} |")
        lines += ["", "| scenario | object | bearing | yaw | distance | period | observed | "
                  "success | plan rate | top rejections | failures |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in mine:
            f = r.factors
            top = ", ".join(f"{k} {v}" for k, v in sorted(r.rejected.items(),
                                                          key=lambda kv: -kv[1])[:2])
            fails = ", ".join([f"{k} {v}" for k, v in r.failures.items()]
                              + ([f"unfinished {r.unfinished}"] if r.unfinished else []))
            lines.append(f"| {r.scenario} | {f['object']} {f['size (m)'] * 100:.0f} cm | "
                         f"{f['mount bearing (deg)']:.0f} | {f['mount yaw (deg)']:.0f} | "
                         f"{f['distance (m)']:.2f} | {f['period (s)']:.2f} | "
                         f"{r.observed:.0%} | "
                         f"{r.rate(1):.0%} / {r.rate(99):.0%} | {r.plan_rate:.0%} | {top} | "
                         f"{fails} |")
        lines += ["", "Failed attempts by kind:", "", "| " + " | ".join(FAILURES) + " |",
                  "|" + "---|" * len(FAILURES),
                  "| " + " | ".join(str(sum(r.failures.get(k, 0) for r in mine))
                                    for k in FAILURES) + " |", *unfinished_lines(mine), ""]
    lines += ["## Not run: judged out of reach from the arm model", ""]
    lines += [f"- {name}: {why}" for name, why in out_of_reach.items()] or ["- none"]
    lines += ["", f"{len(redrawn)} draws could not be and were drawn again.", "",
              "![success and plan rate by factor](by_factor.png)", ""]
    return "\n".join(lines)


def plot_by_factor(path: Path, results: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = by_factor(results)
    fig, axes = plt.subplots(2, (len(table) + 1) // 2, figsize=(3.2 * ((len(table) + 1) // 2),
                                                                 6.5), squeeze=False)
    for ax, (factor, rows) in zip(axes.flat, table.items(), strict=False):
        x = np.arange(len(rows))
        ax.bar(x - 0.2, [100 * g["after_reattempts"] for _, g in rows], 0.4,
               label="success after reattempts")
        ax.bar(x + 0.2, [100 * g["plan_rate"] for _, g in rows], 0.4, label="plan rate")
        ax.set_xticks(x, [label for label, _ in rows], fontsize=7)
        ax.set_title(factor, fontsize=9)
        ax.set_ylim(0, 105)
    for ax in list(axes.flat)[len(table):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, loc="lower left")
    fig.suptitle("Random suite: success and plan rate by factor, %")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
