"""The user docs (README.md, docs/*.md) as files: short README, no lab-notebook history outside
docs/experiments.md, links and pictures that exist, CI's test command in place, results quoted from
benchmarks/RESULTS.md. Pure text checks, no imports of n2d."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
HISTORY_PAGE = ROOT / "docs" / "experiments.md"
"""The one page where development history (sessions, before -> after figures) may live."""
README_MAX_LINES = 300
TEST_COMMAND = ".venv/bin/python -m pytest"
"""What .ci/run executes: the second line of the README's first ```sh block."""
RESULTS_HEADING = "## Results"
RESULTS_COLUMNS = ["stage", "metric", "value", "goal", "met"]

FENCE = re.compile(r"^ *(```|~~~).*?^ *\1[^\n]*$", re.M | re.S)
LINK = re.compile(r"(!?)\[((?:[^\[\]]|\[[^\]]*\])*)\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HISTORY = re.compile(r"session [0-9]+|→|->", re.I)


def _text(page: Path) -> str:
    return page.read_text(encoding="utf-8")


def _without_code_blocks(text: str) -> str:
    """The text with fenced code blocks blanked out (their lines kept, so line numbers still match)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def _links(page: Path) -> list[tuple[bool, str, int]]:
    """(is_image, target, line) of every markdown link outside code blocks."""
    text = _without_code_blocks(_text(page))
    text = re.sub(r"`[^`\n]*`", lambda m: " " * len(m.group(0)), text)  # inline code is not a link
    return [(m.group(1) == "!", m.group(3), text.count("\n", 0, m.start()) + 1) for m in LINK.finditer(text)]


def _is_external(target: str) -> bool:
    return bool(re.match(r"[a-z][a-z0-9+.-]*:", target, re.I))


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    anchors = set()
    for line in _without_code_blocks(_text(page)).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = _slug(m.group(1))
            anchors.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
            seen[slug] = seen.get(slug, 0) + 1
    return anchors


def _table_rows(lines: list[str]) -> list[list[str]]:
    """Cells of the markdown table rows among `lines` (header and separator included)."""
    rows = []
    for line in lines:
        if line.startswith("|") and line.rstrip().endswith("|"):
            rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]])
    return rows


def _readme_results_table() -> list[list[str]]:
    lines = _text(README).splitlines()
    assert RESULTS_HEADING in lines, f"README.md has no '{RESULTS_HEADING}' section"
    start = lines.index(RESULTS_HEADING) + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    block, table = lines[start:end], []
    for i, line in enumerate(block):  # the first table of the section
        if line.startswith("|"):
            table = block[i:]
            table = table[:next((j for j, ln in enumerate(table) if not ln.startswith("|")), len(table))]
            break
    rows = _table_rows(table)
    assert rows, f"README.md's '{RESULTS_HEADING}' section has no table"
    return rows


def test_pages_exist():
    names = {p.name for p in DOCS}
    for name in ("capture.md", "reconstruct.md", "dataset.md", "dope.md", "simulator.md", "pipeline.md",
                 "formats.md", "ros.md", "hardware.md", "experiments.md"):
        assert name in names, f"docs/{name} is missing"
    assert (ROOT / "CHANGELOG.md").is_file(), "CHANGELOG.md is missing"


def test_readme_is_short():
    lines = _text(README).count("\n")
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines (at most {README_MAX_LINES}): move detail to docs/"


@pytest.mark.parametrize("page", [p for p in PAGES if p != HISTORY_PAGE], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_history_outside_experiments(page):
    """Sessions and before -> after arrows belong in docs/experiments.md; the other pages are the present tense."""
    hits = [f"{page.relative_to(ROOT)}:{n}: {line.strip()}"
            for n, line in enumerate(_without_code_blocks(_text(page)).splitlines(), 1) if HISTORY.search(line)]
    assert not hits, "history outside docs/experiments.md:\n" + "\n".join(hits)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_images_exist(page):
    missing = [f"{page.relative_to(ROOT)}:{line}: {target}" for image, target, line in _links(page)
               if image and not _is_external(target) and not (page.parent / target.split("#")[0]).is_file()]
    assert not missing, "images that do not exist:\n" + "\n".join(missing)
    if page == README:
        images = [t for image, t, _ in _links(page) if image]
        assert images and all(t.startswith("docs/") and t.endswith(".jpg") for t in images), images


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(page):
    """Every relative link names an existing file or folder, and a #fragment a heading of the .md file it names."""
    broken = []
    for image, target, line in _links(page):
        if image or _is_external(target):
            continue
        path, _, fragment = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        where = f"{page.relative_to(ROOT)}:{line}: {target}"
        if not dest.exists():
            broken.append(f"{where} (no such file)")
        elif fragment and dest.suffix == ".md" and fragment not in _anchors(dest):
            broken.append(f"{where} (no heading '#{fragment}' in {dest.name})")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_readme_first_sh_block_is_ci_command():
    """.ci/run runs the second line of the README's first ```sh block: it must stay the test command."""
    lines = _text(README).splitlines()
    start = lines.index("```sh") + 1
    block = lines[start:lines.index("```", start)]
    assert len(block) >= 2, block
    assert block[0] == "./install.sh && .venv/bin/n2d demo", block[0]
    assert block[1] == TEST_COMMAND, f"the first sh block's second line is {block[1]!r}, CI expects {TEST_COMMAND!r}"


def test_readme_results_come_from_results_md():
    """Each row of the README's results table is a row of benchmarks/RESULTS.md: its stage, metric, value, goal
    and met cells, as written there."""
    rows = _readme_results_table()
    assert rows[0] == RESULTS_COLUMNS, f"README results table columns {rows[0]}, expected {RESULTS_COLUMNS}"
    body = rows[2:]
    assert body, "README results table has no rows"
    results = {tuple(r[:len(RESULTS_COLUMNS)]) for r in _table_rows(_text(RESULTS).splitlines())}
    text = _text(RESULTS)
    for row in body:
        assert len(row) == len(RESULTS_COLUMNS), row
        assert row[2] and row[2] in text, f"value {row[2]!r} does not occur in benchmarks/RESULTS.md"
        assert tuple(row) in results, (f"README results row {row} is not a row of benchmarks/RESULTS.md "
                                       "(stage, metric, value, goal, met must be copied as they stand there)")
    assert "](benchmarks/RESULTS.md)" in _text(README), "the README's results section links benchmarks/RESULTS.md"
