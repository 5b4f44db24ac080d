"""Printing benchmark results: one aligned text table per benchmark (rows of strings, first row a header)."""


def print_table(title: str, rows: list[tuple[str, ...]], header: tuple[str, ...] | None = None) -> None:
    """Print `title`, then `rows` (and `header` above them) as left-aligned columns."""
    lines = ([header] if header else []) + [tuple(str(c) for c in r) for r in rows]
    widths = [max(len(r[i]) for r in lines if i < len(r)) for i in range(max(map(len, lines)))]
    print(title)
    for row in lines:
        print("  " + "  ".join(f"{c:<{w}}" for c, w in zip(row, widths)).rstrip())
