"""The experiment's report: ``report.json``, ``report.md`` and PNG plots (the paper's Fig. 4
and 5: success per configuration and wave, first attempt and after reattempts, per predictor
side by side; Table II: what the failures were)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

FAILURES = ["prediction", "collision", "timing", "abrupt_change", "unreachable", "other",
            "no plan approved", "aborted"]


def write_report(out: Path, results: list, settings: dict) -> None:
    """results : :class:`~wavegrasp.ops.experiment.RunResult` list, in run order."""
    from wavegrasp.ops.experiment import as_json

    (out / "report.json").write_text(json.dumps(
        {"settings": settings, "runs": as_json(results), "summary": summary(results)},
        indent=2) + "\n")
    plot_success(out / "success.png", results)
    plot_failures(out / "failures.png", results)
    (out / "report.md").write_text(markdown(results, settings))


def summary(results: list) -> dict[str, dict[str, float]]:
    """Per predictor: mean success over configurations, first attempt and within all."""
    out: dict[str, dict[str, float]] = {}
    for name in dict.fromkeys(r.label for r in results):
        mine = [r for r in results if r.label == name]
        out[name] = {"first_attempt": float(np.mean([r.rate(1) for r in mine])),
                     "after_reattempts": float(np.mean([r.rate(99) for r in mine])),
                     "trials": sum(r.trials for r in mine),
                     "unfinished": sum(r.unfinished for r in mine)}
    return out


def markdown(results: list, settings: dict) -> str:
    predictors = list(dict.fromkeys(r.label for r in results))
    configs = list(dict.fromkeys(r.config for r in results))
    by = {(r.label, r.config): r for r in results}
    lines = [f"# wavegrasp eval: {settings['trials']} trials x up to {settings['attempts']} "
             f"attempts, seed {settings['seed']}, {settings['elapsed_s'] / 60:.1f} min", "",
             "Success: first attempt / after reattempts.", "",
             "| sea | wave | object | " + " | ".join(predictors) + " |",
             "|---|---|---|" + "---|" * len(predictors)]
    for config in configs:
        cells = [f"{by[p, config].rate(1):.0%} / {by[p, config].rate(99):.0%}"
                 for p in predictors]
        lines.append("| " + " | ".join(map(str, config)) + " | " + " | ".join(cells) + " |")
    s = summary(results)
    lines.append("| **mean** | | | " + " | ".join(
        f"**{s[p]['first_attempt']:.1%} / {s[p]['after_reattempts']:.1%}**"
        for p in predictors) + " |")
    lines += ["", "Failed attempts by kind (Table II):", "",
              "| predictor | " + " | ".join(FAILURES) + " |",
              "|---|" + "---|" * len(FAILURES)]
    for p in predictors:
        counts = [sum(r.failures.get(k, 0) for r in results if r.label == p)
                  for k in FAILURES]
        lines.append(f"| {p} | " + " | ".join(str(c) for c in counts) + " |")
    lines += ["", "Attempts, aborts (closed loop) and time from approval to grasp (recording s):",
              "", "| predictor | attempts | aborted | approval to grasp, median | p90 |",
              "|---|---|---|---|---|"]
    for p in predictors:
        times = [t for r in results if r.label == p for t in r.approval_to_grasp_s]
        aborted = sum(r.failures.get("aborted", 0) for r in results if r.label == p)
        median, p90 = [f"{np.percentile(times, q):.2f}" for q in (50, 90)] if times else [
            "--", "--"]
        lines.append(f"| {p} | {len(times)} | {aborted} | {median} | {p90} |")
    lines += unfinished_lines(results)
    lines += cpu_lines(results)
    lines += ["", "![success](success.png)", "", "![failures](failures.png)", ""]
    return "\n".join(lines)


def cpu_lines(results: list) -> list[str]:
    """The report's table of CPU seconds per service and predictor, over all runs: where
    the experiment's time goes (the router, not a service, is not in it)."""
    services = sorted({name for r in results for name in r.cpu_s})
    if not services:
        return []
    predictors = list(dict.fromkeys(r.label for r in results))
    lines = ["", "CPU seconds per service (all its runs; forked services from their fork):", "",
             "| predictor | runs | " + " | ".join(services) + " | total |",
             "|---|---|" + "---|" * (len(services) + 1)]
    for p in predictors:
        mine = [r for r in results if r.label == p]
        sums = [sum(r.cpu_s.get(name, 0.0) for r in mine) for name in services]
        lines.append(f"| {p} | {len(mine)} | " + " | ".join(f"{x:.0f}" for x in sums)
                     + f" | {sum(sums):.0f} |")
    return lines


def unfinished_lines(results: list) -> list[str]:
    """The report's note of trials the recording ended first (never begun: the object never
    observed or never predicted), if any."""
    unfinished = sum(r.unfinished for r in results)
    if not unfinished:
        return []
    return ["", f"{unfinished} trials did not end before their recording did (counted as "
            "failures)."]


def plot_success(path: Path, results: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    predictors = list(dict.fromkeys(r.label for r in results))
    configs = list(dict.fromkeys(r.config for r in results))
    by = {(r.label, r.config): r for r in results}
    x = np.arange(len(configs))
    width = 0.8 / len(predictors)
    fig, ax = plt.subplots(figsize=(max(8, len(configs) * 0.9), 4.5))
    for i, p in enumerate(predictors):
        after = [100 * by[p, c].rate(99) for c in configs]
        first = [100 * by[p, c].rate(1) for c in configs]
        bars = ax.bar(x + (i - (len(predictors) - 1) / 2) * width, after, width, label=p,
                      alpha=0.45)
        ax.bar(x + (i - (len(predictors) - 1) / 2) * width, first, width,
               color=bars.patches[0].get_facecolor(), alpha=1.0)
    ax.set_xticks(x, [f"{'' if s == 'regular' else s + ' '}wave {w}\n{o}"
                      for s, w, o in configs], fontsize=8)
    ax.set_ylabel("grasp success, % of trials")
    ax.set_ylim(0, 105)
    ax.set_title("Success per configuration: solid first attempt, pale after reattempts")
    ax.legend(loc="lower right", framealpha=0.95)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_failures(path: Path, results: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    predictors = list(dict.fromkeys(r.label for r in results))
    fig, ax = plt.subplots(figsize=(7, 4))
    bottom = np.zeros(len(predictors))
    for kind in FAILURES:
        counts = np.array([sum(r.failures.get(kind, 0) for r in results if r.label == p)
                           for p in predictors], dtype=float)
        if counts.any():
            ax.bar(predictors, counts, bottom=bottom, label=kind)
            bottom += counts
    ax.set_ylabel("failed attempts")
    ax.set_title("Failures by kind (the paper's Table II)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def end_table(out: Path, results: list) -> str:
    """What ``wavegrasp eval`` prints at its end: a row per run (its trials' succeeding
    attempts, failed attempts by kind, mean prediction error at approval, the gate's
    approvals and refusals, latency p50 / p99, bad messages, restarts), each predictor's
    success, and where to look next."""
    rows = [f"{'run':34s} {'success at attempt':>18s}  {'failed attempts':24s} "
            f"{'error':>8s}  {'go plan/update/no':>17s}  {'p50/p99 ms':>11s}  bad  restarts"]
    for r in results:
        attempts = ",".join(str(a) if a else "-" for a in r.success_attempt)
        failed = ", ".join(f"{k} {n}" for k, n in sorted(r.failures.items())) or "none"
        g = r.gate
        errors = g.get("error_at_approval_mm", [])
        error = f"{np.mean(errors):.1f} mm" if errors else "-"
        gate = f"{g.get('plans_approved', 0)}/{g.get('updates_approved', 0)}/{g.get('refused', 0)}"
        p50, p99 = g.get("latency_p50_ms"), g.get("latency_p99_ms")
        latency = f"{p50:.0f}/{p99:.0f}" if p50 is not None and p99 is not None else "-"
        rows.append(f"{r.run or r.label:34s} {attempts:>18s}  {failed[:24]:24s} {error:>8s}  "
                    f"{gate:>17s}  {latency:>11s}  {r.bad_messages:3d}  {r.restarts:8d}")
    for name, s in summary(results).items():
        rows.append(f"{name}: success {s['first_attempt']:.0%} first attempt, "
                    f"{s['after_reattempts']:.0%} after reattempts, {s['trials']} trials")
    rows.append(f"see it: the report {out / 'report.md'} (plots success.png, failures.png)  |  "
                f"a run in Foxglove: open {out}/RUN/run.mcap  |  per hop: wavegrasp latency "
                f"{out}/RUN/run.mcap")
    return "\n".join(rows)
