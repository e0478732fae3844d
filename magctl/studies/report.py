"""The Markdown report written by ``magctl reproduce``."""

from __future__ import annotations

import os
from pathlib import Path

from magctl.studies.runner import StudyResult


def write_report(out: Path, results: list[StudyResult], timings: dict[str, float]) -> Path:
    """Write ``out/report.md``: the paper-vs-magctl table, then one section per study."""
    lines = ["# magctl reproduce — report", ""]
    rows = [(r.name, row) for r in results for row in r.paper]
    if rows:
        lines += ["## Paper vs magctl", "", "| study | quantity | paper | magctl | note |", "|---|---|---|---|---|"]
        lines += [f"| {name} | {row.quantity} | {row.paper} | {row.magctl} | {row.note} |" for name, row in rows]
        lines.append("")
    for r in results:
        lines += [f"## {r.name}", "", f"_wall time {timings.get(r.name, 0.0):.1f} s_", ""]
        lines += r.summary + [""]
        for fig in r.figures:
            rel = os.path.relpath(fig, out)
            lines.append(f"![{Path(fig).stem}]({rel})")
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
