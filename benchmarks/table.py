"""Printing benchmark results: one aligned text table per benchmark (rows of strings, first row a header).

With the environment variable N2D_BENCH_ROWS set to a path, each table is also appended to that file as one
JSON line {"title", "header", "rows"} (what `benchmarks/run_all.py` collects); the printed output is the same.
"""

import json
import os


def print_table(title: str, rows: list[tuple[str, ...]], header: tuple[str, ...] | None = None) -> None:
    """Print `title`, then `rows` (and `header` above them) as left-aligned columns."""
    body = [tuple(str(c) for c in r) for r in rows]
    lines = ([header] if header else []) + body
    widths = [max(len(r[i]) for r in lines if i < len(r)) for i in range(max(map(len, lines)))]
    print(title)
    for row in lines:
        print("  " + "  ".join(f"{c:<{w}}" for c, w in zip(row, widths)).rstrip())
    if path := os.environ.get("N2D_BENCH_ROWS"):
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps({"title": title, "header": header, "rows": body}) + "\n")
