"""The benchmark tables of the docs (docs/benchmarks.md, docs/identify.md), generated from committed results files.

    python benchmarks/readme.py benchmarks/results/2026-12-04-abc1234567.json [more files …]

writes the rows every named file's benchmarks give (``rows``: name, target, value, unit, verdict, note;
each verdict computed by the benchmark from the figure it names) between docs/benchmarks.md's markers
``<!-- benchmarks:begin -->`` and ``<!-- benchmarks:end -->`` (``--into PAGE.md``: another page's), each row with
the file and commit it came from; a page with a line ``<!-- benchmarks:only NAME … -->`` before its table shows only
those benchmarks' rows. ``tests/test_readme_benchmarks.py`` checks that each page holds exactly this
table for the files it names, so no page can quote a number no committed file contains.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- benchmarks:begin -->", "<!-- benchmarks:end -->"
ONLY = "<!-- benchmarks:only"


def _value(row: dict) -> str:
    v = row["value"]
    if v != v or v in (float("inf"), float("-inf")):
        return "not measured"
    if abs(v) >= 1000:
        return f"{v:,.0f} {row['unit']}"
    return f"{v:.3g} {row['unit']}"


def render(files: list[Path], only: list[str] | None = None) -> str:
    """The section between the markers for these results files (paths relative to the repository); ``only``: the
    benchmarks (names in the files, e.g. ``identify``) whose rows it shows, None: all."""
    lines = [BEGIN, "", "| benchmark | target | measured | verdict | results file (commit) | note |",
             "|---|---|---|---|---|---|"]
    for path in files:
        doc = json.loads((ROOT / path).read_text())
        meta = doc.get("meta", {})
        for name, result in doc.items():
            if name == "meta" or not isinstance(result, dict) or (only is not None and name not in only):
                continue
            for row in result.get("rows", ()):
                verdict = "met" if row["met"] else "**missed**"
                lines.append(f"| {row['name']} | {row['target']} | {_value(row)} | {verdict} | "
                             f"`{Path(path).as_posix()}` ({meta.get('commit', '?')}, {meta.get('cores', '?')} cores, "
                             f"numpy small op {meta.get('numpy_small_op_us', float('nan')):.2f} µs) | "
                             f"{row.get('note', '')} |")
    lines += ["", END]
    return "\n".join(lines)


def named_only(readme: str) -> list[str] | None:
    """The benchmarks a page's table is limited to: its line ``<!-- benchmarks:only NAME … -->`` before the table,
    None without one."""
    m = re.search(r"^" + re.escape(ONLY) + r"((?: [\w-]+)+) -->$", readme.split(BEGIN, 1)[0], flags=re.M)
    return m.group(1).split() if m else None


def named_files(readme: str) -> list[Path]:
    """The results files a page's table was generated from (its rows' file column)."""
    if BEGIN not in readme:
        return []
    section = readme.split(BEGIN, 1)[1].split(END, 1)[0]
    files = []
    for line in section.splitlines()[3:]:
        cells = [c.strip() for c in line.split("|")]
        if len(cells) > 5 and cells[5].startswith("`"):
            f = Path(cells[5].split("`")[1])
            if f not in files:
                files.append(f)
    return files


def main(argv: list[str]) -> int:
    target = "docs/benchmarks.md"
    if argv[:1] == ["--into"] and len(argv) > 1:      # another page with the same markers, e.g. docs/identify.md
        target, argv = argv[1], argv[2:]
    files = [Path(a).resolve().relative_to(ROOT) for a in argv]
    if not files:
        print("usage: python benchmarks/readme.py [--into PAGE.md] RESULTS.json [RESULTS.json …]", file=sys.stderr)
        return 2
    page = ROOT / target
    text = page.read_text()
    if BEGIN not in text or END not in text:
        print(f"{target} has no {BEGIN} … {END} section", file=sys.stderr)
        return 2
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    page.write_text(head + render(files, named_only(text)) + tail)
    print(f"{target}: benchmark table from {', '.join(map(str, files))}", file=sys.stderr)
    return 0

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
