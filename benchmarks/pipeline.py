"""Benchmark of the whole pipeline: `n2d demo` on the simulated world, time per stage and pose accuracy.

    python benchmarks/pipeline.py [--run DIR] [--set KEY=VALUE ...]

Runs the default demo (what `n2d demo` runs: empty-plate sweep, the Pipeline action through every stage node,
then dope_node scored live against the simulator) into `--run` (default: a temporary directory), or reads a
finished run there, and prints the seconds of each stage, the total against the 30-minute goal on 2 CPU
cores, and ADD / ADD-S of the trained model on the held-out synthetic frames, on the board-posed test sweep
and live in dope_node.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from n2d.demo import DemoConfig, run_demo
from n2d_common.config import load_config
from table import print_table

GOAL_MINUTES = 30.0
"""The default demo on 2 CPU cores."""
LIVE_GOAL = 0.8
"""Share of the live frames dope_node's poses get right (ADD-S within 10 % of the diameter)."""
TURNTABLE_GOAL = 0.9
"""Share of the board-posed test sweep's views the refined poses get right (what dope_node publishes)."""


def _goal(r: dict, share: float | None) -> tuple[str, str]:
    """(goal, met) of an accuracy row: ADD-S of at least `share` of the instances, or only reported."""
    if share is None:
        return "reported", ""
    return f"ADD-S >= {100 * share:.0f} %", "yes" if r["adds_accuracy_10pct"] >= share else "NO"


def _accuracy(r: dict) -> str:
    median = r.get("adds_median_mm")
    return (f"ADD-S {100 * r['adds_accuracy_10pct']:.1f} % / ADD {100 * r['add_accuracy_10pct']:.1f} %, "
            f"AUC ADD-S {100 * r['adds_auc_10cm']:.1f}, median ADD-S "
            + ("-" if median is None else f"{median:.0f} mm") + f" ({r['detected']}/{r['instances']} found)")


def rows(summary: dict) -> list[tuple[str, str, str, str]]:
    """The table rows (metric, value, goal, met) of a demo summary (demo.json)."""
    out = [(f"stage: {stage}", f"{seconds:.0f} s", "", "") for stage, seconds in summary["seconds"].items()]
    minutes = summary["seconds_total"] / 60
    out.append(("whole demo", f"{minutes:.1f} min", f"<= {GOAL_MINUTES:.0f} min on 2 CPU cores",
                "yes" if minutes <= GOAL_MINUTES else "NO"))
    for test, by_precision in summary["evaluation"].items():
        for precision, r in by_precision.items():
            goal = TURNTABLE_GOAL if (test, precision) == ("turntable", "fp32 refined") else None
            out.append((f"{test} test set, {precision}", _accuracy(r), *_goal(r, goal)))
    if summary.get("live"):
        live = summary["live"]
        out.append((f"live dope_node vs simulator truth, {live['precision']}", _accuracy(live),
                    *_goal(live, LIVE_GOAL)))
        if live.get("latency_ms_mean") is not None:
            out.append(("live dope_node latency, mean", f"{live['latency_ms_mean']:.0f} ms", "", ""))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="run directory (a finished one is read, not run again)")
    parser.add_argument("-s", "--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a DemoConfig value, e.g. --set pipeline.frames=60")
    args = parser.parse_args(argv)
    cfg = load_config(DemoConfig, None, args.set)
    with tempfile.TemporaryDirectory(prefix="n2d-bench-pipeline-") as tmp:
        run = args.run.absolute() if args.run else Path(tmp) / "run"
        summary = run_demo(run, cfg, log=lambda line: None)
        print_table(f"Whole pipeline (n2d demo, {summary['object']}; {run})", rows(summary),
                    ("metric", "value", "goal", "met"))


if __name__ == "__main__":
    main()
