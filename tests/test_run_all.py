"""benchmarks/run_all.py --keep: a partial refresh keeps the other benchmarks' rows, dated, and loses nothing."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run_all():
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "benchmarks" / "run_all.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_keep_carries_the_rows_of_benchmarks_not_run(tmp_path):
    run_all = _run_all()
    results = tmp_path / "RESULTS.md"
    rows = [("sim camera", "new-angle rate", "1.36 frames/s", "", ""),
            ("reconstruct (fast)", "bbox size error x, y, z", "+0.46 %, +3.38 %, +1.10 %", "within 1.0 %", "NO"),
            ("reconstruct (fast)", "held-out mesh | photo", "19.08 dB", "", ""),
            ("dope", "lite INT8, 640x480 input", "21 ms (47.1 FPS)", "", "")]
    runs = ["sim camera: `python benchmarks/sim_camera.py`, 17 s, exit code 0",
            "reconstruct: `python benchmarks/reconstruct.py`, 186 s, exit code 0",
            "dope: `python benchmarks/dope.py --model M --test T`, 200 s, exit code 0"]
    run_all.write_results(results, "test machine", "2 cores, no GPU", "run_all.py", False, rows, runs)
    date = next(line[len("Date: "):].strip() for line in results.read_text().splitlines() if line.startswith("Date:"))

    # Only the DOPE benchmark is asked for, and it cannot run without its datasets: every other row is kept.
    assert run_all.main(["--only", "dope", "--keep", "--out", str(results), "--logs", str(tmp_path / "logs")]) == 0
    text = results.read_text()
    table = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| stage")]
    assert table[0] == f"| sim camera | new-angle rate | 1.36 frames/s |  |  | 2 cores, no GPU, measured {date} |"
    assert f"| +0.46 %, +3.38 %, +1.10 % | within 1.0 % | **NO** | 2 cores, no GPU, measured {date} |" in table[1]
    assert "held-out mesh \\| photo" in table[2]
    assert table[3].startswith("| dope | not run |")
    assert len(table) == 4  # the old DOPE row is replaced by this run's
    assert f"- reconstruct: `python benchmarks/reconstruct.py`, 186 s, exit code 0 (kept from the run of {date} on " \
        "test machine)" in text

    # Kept again: the first date stays, nothing is doubled.
    assert run_all.main(["--only", "dope", "--keep", "--out", str(results), "--logs", str(tmp_path / "logs")]) == 0
    again = results.read_text()
    assert again.count("measured") == 3 and again.count(f"measured {date}") == 3
    assert again.count("(kept from the run of") == 2


def test_without_keep_the_file_holds_only_this_run(tmp_path):
    run_all = _run_all()
    results = tmp_path / "RESULTS.md"
    run_all.write_results(results, "m", "2 cores, no GPU", "c", False, [("masks", "IoU", "0.99", "", "")],
                          ["masks: `python benchmarks/masks.py`, 64 s, exit code 0"])
    assert run_all.main(["--only", "dope", "--out", str(results), "--logs", str(tmp_path / "logs")]) == 0
    text = results.read_text()
    assert "| masks |" not in text and "| dope | not run |" in text


def test_modes_of_one_script_are_benchmarks_of_their_own(tmp_path):
    run_all = _run_all()
    assert all(name in run_all.STAGES and name in run_all.QUICK for name in run_all.SCRIPTS)
    assert run_all._script("reconstruct_suite") == ("reconstruct", ["--suite"])
    rows = run_all.map_table("reconstruct suite", ["object", "metric", "value", "goal", "met"],
                             [["mug", "Chamfer", "0.9 mm = 0.8 % of diameter", "<= 0.5 %", "NO"],
                              ["mug", "  F-score at 1 mm, held-out textured mesh PSNR", "0.91, 21.5 dB", "", ""]])
    assert rows == [("reconstruct suite (mug)", "Chamfer", "0.9 mm = 0.8 % of diameter", "<= 0.5 %", "NO"),
                    ("reconstruct suite (mug)", "Chamfer: F-score at 1 mm, held-out textured mesh PSNR",
                     "0.91, 21.5 dB", "", "")]
    results = tmp_path / "RESULTS.md"
    run_all.write_results(results, "m", "2 cores, no GPU", "c", False,
                          [("reconstruct (fast)", "Chamfer", "0.16 mm", "", ""), *rows],
                          ["reconstruct: `python benchmarks/reconstruct.py`, 186 s, exit code 0",
                           "reconstruct suite: `python benchmarks/reconstruct.py --suite`, 3000 s, exit code 0"])
    # The box's rows and the suite's belong to different benchmarks: refreshing one keeps the other's.
    kept, runs = run_all.kept_results(results, ["reconstruct"])
    assert [r[0] for r in kept["reconstruct"]] == ["reconstruct (fast)"] and list(runs) == ["reconstruct"]
    kept, runs = run_all.kept_results(results, ["reconstruct suite"])
    assert len(kept["reconstruct suite"]) == 2 and list(runs) == ["reconstruct suite"]
