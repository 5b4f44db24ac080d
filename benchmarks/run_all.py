"""Run every stage's benchmark and write their numbers as one markdown table into benchmarks/RESULTS.md.

    python benchmarks/run_all.py [--quick] [--only NAME[,NAME]] [--skip NAME[,NAME]] [--keep] [--out PATH]
                                 [--dope-model DIR | --dope-train DIR [--dope-minutes M]] [--dope-test DIR]
                                 [--args NAME='EXTRA ARGS'] [--logs DIR]

Benchmarks, in pipeline order: sim_camera, board_poses, masks, capture, reconstruct (the box), reconstruct_suite
(`reconstruct.py --suite`: every suite object), reconstruct_placements (`reconstruct.py --placements 2`), dataset,
dope, estimator (the default recipe within the demo's budget, trained per object), tracking (refinement and
tracking on the validation videos, with the model of `--dope-model`), then pipeline (the whole `n2d demo`;
`--args pipeline='--run DIR'` reads a finished run instead), then faults (the fault campaign). Each runs as its
own process (`python benchmarks/NAME.py ...`, the current directory kept) with N2D_BENCH_ROWS set, so that
`table.print_table` hands its rows over as JSON lines; its output is shown as it runs and kept in a log
directory (a temporary one unless `--logs`). Without `--quick` each benchmark runs with its own defaults (the
numbers the README cites, an hour or more on 2 cores); `--quick` gives each smaller settings (fewer views,
angles, frames, runs: a few minutes in all; not numbers to cite). `--args NAME='...'` appends arguments to
one benchmark's command line (after the quick ones, so they win), e.g. `--args capture='--board-poses'` or
`--args reconstruct='--session /tmp/session'`.

The DOPE benchmark needs a held-out test dataset (`--dope-test`) and a trained light model (`--dope-model`,
e.g. the one the README's numbers came from, so the hour of training is not redone) or a training dataset
(`--dope-train`, trained for `--dope-minutes`, 60 by default, 2 with `--quick`); without them it gets a
"not run" row.

The file (written atomically) holds the date, the machine (CPU, cores, RAM, GPU), this command line and one
table: stage, metric, value, goal, met (yes / **NO**; empty where the benchmark sets no goal), machine. With
`--keep`, the benchmarks not run this time keep their rows from the file being replaced (e.g. the DOPE rows of
an hour-trained model, when only the stages upstream changed), their machine cell saying when they were
measured. Every benchmark's rows are mapped into it whatever their layout: sub-rows get their parent's name,
note columns are appended to the value, columns before `metric` (reconstruct's method) go to the stage. A benchmark that
fails gets one row saying so (exit code, last line of its stderr); the others still run and this script then
exits with status 1.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

from n2d_common.contracts import atomic_write_text

HERE = Path(__file__).resolve().parent

STAGES = {"sim_camera": "sim camera", "board_poses": "board poses", "masks": "masks", "capture": "capture",
          "reconstruct": "reconstruct", "reconstruct_suite": "reconstruct suite",
          "reconstruct_placements": "reconstruct placements", "dataset": "dataset", "dope": "dope",
          "estimator": "estimator",
          "tracking": "tracking", "pipeline": "whole pipeline", "faults": "faults"}
"""Benchmark name: stage name in the table, in pipeline order."""
SCRIPTS = {"reconstruct_suite": ("reconstruct", ["--suite"]),
           "reconstruct_placements": ("reconstruct", ["--placements", "2", "--objects", "mug,spray,bracket,duck"])}
"""Benchmarks that are a mode of another script: name -> (script, its arguments); the others run NAME.py."""
QUICK = {"sim_camera": ["--angles", "3", "--republish", "10"],
         "board_poses": ["--views", "12"],
         "masks": ["--angles", "2"],
         "capture": ["--views", "8"],
         "reconstruct": ["--views", "12"],
         "reconstruct_suite": ["--objects", "cube_plain", "--views", "12"],
         "reconstruct_placements": ["--objects", "mug", "--views", "12"],
         "dataset": ["--frames", "2", "--raster-frames", "10"],
         "dope": ["--views", "4", "--runs", "3", "--node-seconds", "5"],
         "estimator": ["--test-frames", "8", "--set", "frames=60", "--set", "train_minutes=1"],
         "tracking": ["--frames", "12"],
         "pipeline": ["--set", "pipeline.views=12", "--set", "pipeline.test_views=4", "--set", "pipeline.frames=24",
                      "--set", "pipeline.test_frames=8", "--set", "pipeline.train_minutes=2", "--set", "live_views=4"],
         "faults": ["--trials", "1"]}
"""Small settings per benchmark for `--quick`."""
VERDICTS = {"yes": "yes", "met": "yes", "no": "NO", "not met": "NO"}
"""What the benchmarks print in a met column (or a note column): the table's met."""

Row = tuple[str, ...]
"""(stage, metric, value, goal, met), and the machine when it is not this one (a kept row)."""


def _number(cell: str) -> bool:
    try:
        float(cell)
        return True
    except ValueError:
        return False


def map_table(stage: str, header: list[str] | None, rows: list[list[str]]) -> list[Row]:
    """The (stage, metric, value, goal, met) rows of one printed table.

    With `metric` and `value` columns (no header: just those two): columns before `metric` qualify the stage,
    an indented metric is a sub-row named after its parent (the parent's text before its last ": "), a `met`
    column or a cell reading met / NOT met / yes / NO is the verdict, a `goal` column the goal (a `goal / note`
    column only when the row has a verdict), and every other non-empty cell a note appended to the value.
    Without them (e.g. masks: object, variant, mean IoU, min IoU, ms/frame) the leading non-numeric cells
    name the metric and the remaining columns are joined into one value."""
    names = [h.strip().lower() for h in header] if header else ["metric", "value"]
    out, parent = [], ""
    for row in rows:
        if "metric" not in names or "value" not in names:
            k = next((i for i, c in enumerate(row) if _number(c)), 1)
            metric = f"{', '.join(row[:k])}: {' / '.join(header[k:len(row)])}" if header else row[0]
            out.append((stage, metric, " / ".join(row[k:]), "", ""))
            continue
        m, v = names.index("metric"), names.index("value")
        qualified = " ".join([stage] + [f"({c})" for c in row[:m] if c])
        metric = row[m]
        if metric.startswith(" "):
            metric = f"{parent}: {metric.strip()}" if parent else metric.strip()
        else:
            parent = metric.rsplit(": ", 1)[0]
        rest = [(names[i] if i < len(names) else "", c.strip()) for i, c in enumerate(row) if i > v and c.strip()]
        verdict = next((VERDICTS[c.lower()] for _, c in rest if c.lower() in VERDICTS), "")
        verdict = verdict or next((c for n, c in rest if n == "met"), "")
        goal, notes = "", []
        for name, cell in rest:
            if cell.lower() in VERDICTS or name == "met":
                continue
            if name == "goal" or ("goal" in name and verdict):
                goal = cell
            else:
                notes.append(cell[1:-1] if cell.startswith("(") and cell.endswith(")") else cell)
        value = row[v] + (f" ({'; '.join(notes)})" if notes else "")
        out.append((qualified, metric, value, goal, verdict))
    return out


def machine() -> tuple[str, str]:
    """(the whole machine line, a short one for the table's column)."""
    cpu = platform.processor() or platform.machine()
    ram = ""
    try:
        info = Path("/proc/cpuinfo").read_text()
        cpu = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), cpu)
        mem = next(line for line in Path("/proc/meminfo").read_text().splitlines() if line.startswith("MemTotal"))
        ram = f", {int(mem.split()[1]) / 2**20:.1f} GiB RAM"
    except (OSError, StopIteration):
        pass
    try:
        import torch

        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    except ImportError:
        gpu = "no GPU (torch not installed)"
    cores = f"{os.cpu_count()} cores"
    return f"{cpu}, {cores}{ram}, {gpu}", f"{cores}, {gpu}"


def _pump(stream, sinks, tail: collections.deque) -> None:
    for line in stream:
        tail.append(line)
        for sink in sinks:
            sink.write(line)
            sink.flush()


def run_benchmark(name: str, args: list[str], log: Path) -> tuple[int, list[dict], str, float]:
    """Run benchmark NAME (benchmarks/NAME.py, or its SCRIPTS entry) with `args`, echoing and logging its output:
    (exit code, its tables, the last line of its stderr, wall seconds)."""
    script, fixed = _script(name)
    with tempfile.TemporaryDirectory(prefix="n2d-bench-rows-") as tmp:
        rows_file = Path(tmp) / "rows.jsonl"
        env = dict(os.environ, N2D_BENCH_ROWS=str(rows_file), PYTHONUNBUFFERED="1")
        t0 = time.perf_counter()
        with open(log, "w", encoding="utf-8") as log_file, subprocess.Popen(
                [sys.executable, str(HERE / f"{script}.py"), *fixed, *args], env=env, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE, text=True, errors="replace") as proc:
            out_tail, err_tail = collections.deque(maxlen=1), collections.deque(maxlen=50)
            pumps = [threading.Thread(target=_pump, args=(proc.stdout, [sys.stdout, log_file], out_tail)),
                     threading.Thread(target=_pump, args=(proc.stderr, [sys.stderr, log_file], err_tail))]
            for pump in pumps:
                pump.start()
            for pump in pumps:
                pump.join()
            code = proc.wait()
        seconds = time.perf_counter() - t0
        tables = [json.loads(line) for line in rows_file.read_text().splitlines()] if rows_file.exists() else []
    last = next((line.strip() for line in reversed(err_tail) if line.strip()), "")
    return code, tables, last, seconds


def _script(name: str) -> tuple[str, list[str]]:
    return SCRIPTS.get(name, (name, []))


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _display(path: str) -> str:
    rel = os.path.relpath(path)
    return rel if not rel.startswith("..") else path


def write_results(out: Path, machine_line: str, machine_short: str, command: str, quick: bool, rows: list[Row],
                  runs: list[str]) -> None:
    """Write the results file atomically."""
    lines = ["# Benchmark results", "",
             f"Date: {datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')}  ",
             f"Machine: {machine_line}  ",
             f"Command: `{command}`", ""]
    if quick:
        lines += ["With `--quick`: small settings, not the numbers the README cites.", ""]
    lines += ["| stage | metric | value | goal | met | machine |", "|---|---|---|---|---|---|"]
    for stage, metric, value, goal, met, *where in rows:
        met = "**NO**" if met in ("NO", "**NO**") else met
        cells = (stage, metric, value, goal, met, where[0] if where else machine_short)
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    lines += ["", "Benchmarks run:", ""] + [f"- {r}" for r in runs]
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines) + "\n")


def kept_results(path: Path, stages: list[str]) -> tuple[dict[str, list[Row]], dict[str, str]]:
    """The rows and the "Benchmarks run" lines of `stages` (table names) in an earlier results file, by stage,
    each row's machine cell dated with that file's date and each line naming its machine; nothing when there is
    no such file."""
    if not path.exists():
        return {}, {}
    text = path.read_text(encoding="utf-8")
    date, machine = (next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith(key)), "?")
                     for key in ("Date:", "Machine:"))

    def owner(stage: str) -> str | None:  # "reconstruct (fast)" belongs to "reconstruct"
        return next((s for s in stages if stage == s or stage.startswith(s + " (")), None)

    rows: dict[str, list[Row]] = collections.defaultdict(list)
    runs: dict[str, str] = {}
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith(("| stage |", "|---")):
            cells = [c.replace("\\|", "|") for c in line[2:-2].split(" | ")]
            stage = owner(cells[0])
            if stage and len(cells) == 6:
                where = cells[5] if ", measured " in cells[5] else f"{cells[5]}, measured {date}"
                rows[stage].append((*cells[:5], where))
        elif line.startswith("- "):
            stage = owner(line[2:].split(":", 1)[0])
            if stage:
                kept = "(kept from the run of " in line
                runs[stage] = line[2:] if kept else f"{line[2:]} (kept from the run of {date} on {machine})"
    return rows, runs


def _names(text: str, parser: argparse.ArgumentParser) -> list[str]:
    names = [n.strip().replace("-", "_").replace(" ", "_") for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in STAGES]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(STAGES)}")
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", metavar="NAME[,NAME]", help="run only these benchmarks")
    parser.add_argument("--skip", metavar="NAME[,NAME]", help="leave these benchmarks out")
    parser.add_argument("--quick", action="store_true", help="small settings for each benchmark (a few minutes)")
    parser.add_argument("--keep", action="store_true",
                        help="keep the rows of the benchmarks not run from the results file being replaced")
    parser.add_argument("--out", type=Path, default=HERE / "RESULTS.md", help="results file (default: %(default)s)")
    parser.add_argument("--logs", type=Path, help="keep each benchmark's output here as NAME.log "
                        "(default: a new temporary directory)")
    parser.add_argument("--dope-model", metavar="DIR", help="trained light DOPE model (dope.py --model)")
    parser.add_argument("--dope-train", metavar="DIR", help="train the light model on this dataset first "
                        "(dope.py --train)")
    parser.add_argument("--dope-minutes", type=float, help="training minutes with --dope-train (dope.py --minutes; "
                        "default 60, 2 with --quick)")
    parser.add_argument("--dope-test", metavar="DIR", help="held-out DOPE test dataset (dope.py --test)")
    parser.add_argument("--args", dest="extra", action="append", default=[], metavar="NAME='ARGS'",
                        help="extra arguments for one benchmark, e.g. capture='--board-poses' (repeatable)")
    args = parser.parse_args(argv)

    selected = _names(args.only, parser) if args.only else list(STAGES)
    skipped = set(_names(args.skip, parser)) if args.skip else set()
    selected = [n for n in STAGES if n in selected and n not in skipped]
    extra: dict[str, list[str]] = collections.defaultdict(list)
    for item in args.extra:
        name, sep, text = item.partition("=")
        if not sep:
            parser.error(f"--args {item!r}: expected NAME='ARGS'")
        extra[_names(name, parser)[0]] += shlex.split(text)
    dope_args = []
    for option, value in (("--model", args.dope_model), ("--train", args.dope_train), ("--test", args.dope_test)):
        if value:
            dope_args += [option, value]
    minutes = args.dope_minutes if args.dope_minutes is not None else (2.0 if args.quick else None)
    if args.dope_train and minutes is not None:
        dope_args += ["--minutes", f"{minutes:g}"]

    logs = args.logs or Path(tempfile.mkdtemp(prefix="n2d-bench-logs-"))
    logs.mkdir(parents=True, exist_ok=True)
    command = shlex.join([_display(sys.executable), *sys.argv]) if argv is None else shlex.join(
        [_display(sys.executable), _display(__file__), *argv])
    machine_line, machine_short = machine()
    rows: list[Row] = []
    runs: list[str] = []
    failed = []
    kept_rows, kept_runs = kept_results(args.out, [STAGES[n] for n in STAGES if n not in selected]) if args.keep \
        else ({}, {})
    for name in STAGES:
        stage = STAGES[name]
        if name not in selected:
            rows += kept_rows.get(stage, [])
            runs += [kept_runs[stage]] if stage in kept_runs else []
            continue
        model_args = ["--model", str(args.dope_model)] if name == "tracking" and args.dope_model else []
        bench_args = (QUICK[name] if args.quick else []) + (dope_args if name == "dope" else []) + model_args \
            + extra[name]
        script, fixed = _script(name)
        shown = shlex.join(["python", _display(str(HERE / f"{script}.py")), *fixed, *bench_args])
        if name == "dope" and ("--test" not in bench_args or not {"--model", "--train"} & set(bench_args)):
            rows.append((stage, "not run", "needs --dope-test DIR and --dope-model DIR or --dope-train DIR", "", ""))
            runs.append(f"{stage}: not run (no test dataset, or no model or training dataset given)")
            print(f"== {name}: not run (give --dope-test and --dope-model or --dope-train, or --skip dope)",
                  file=sys.stderr)
            continue
        if name == "tracking" and "--model" not in bench_args:
            rows.append((stage, "not run", "needs --dope-model DIR", "", ""))
            runs.append(f"{stage}: not run (no DOPE model given)")
            print(f"== {name}: not run (give --dope-model, or --skip tracking)", file=sys.stderr)
            continue
        print(f"== {name}: {shown}", flush=True)
        code, tables, last, seconds = run_benchmark(name, bench_args, logs / f"{name}.log")
        for table in tables:
            rows += map_table(stage, table["header"], table["rows"])
        if code != 0 or not tables:
            failed.append(name)
            why = f"exit code {code}" + (f": {last}" if last else "") if code else "printed no table"
            rows.append((stage, "benchmark failed", why, "", "NO"))
        titles = "; ".join(t["title"] for t in tables)
        runs.append(f"{stage}: `{shown}`, {seconds:.0f} s, exit code {code}" + (f" ({titles})" if titles else ""))
        print(f"== {name}: exit code {code} after {seconds:.0f} s", flush=True)

    write_results(args.out, machine_line, machine_short, command, args.quick, rows, runs)
    print(f"results: {args.out}\nlogs: {logs}")
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
