"""The Markdown report written by ``magctl reproduce``."""

from __future__ import annotations

import os
from pathlib import Path

from magctl.studies.paper_statistics import PAPER_TRIALS, RULE
from magctl.studies.runner import VERDICTS, StudyResult


def _probability(p: float | None) -> str:
    return "—" if p is None else "< 0.001" if p < 0.001 else f"{p:.3f}"


def write_report(out: Path, results: list[StudyResult], timings: dict[str, float]) -> Path:
    """Write ``out/report.md``: the paper-vs-magctl table, then one section per study."""
    lines = ["# magctl reproduce — report", ""]
    claims = sorted(((r.name, row) for r in results for row in r.paper if row.verdict),
                    key=lambda item: item[1].section)
    rows = [(r.name, row) for r in results for row in r.paper if not row.verdict]
    if claims:
        counts = {v: sum(row.verdict == v for _, row in claims) for v in VERDICTS}
        lines += ["## The paper's claims, one row each", "",
                  ", ".join(f"{n} {v}" for v, n in counts.items()) + ". _model_: what produced magctl's number "
                  "(closed loop: the 30 Hz simulation; attempt map: eq 14–18 iterated; analysis: closed form "
                  "or linear analysis; fluid model: the flow alone). _P(paper)_: probability of the paper's "
                  f"observation at its {PAPER_TRIALS} trials under magctl's model.", "", RULE, "",
                  "| § | claim | paper | magctl | model | P(paper) | verdict | cause | study |",
                  "|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {row.section} | {row.quantity} | {row.paper} | {row.magctl} | {row.model} | "
                  f"{_probability(row.p_paper)} | **{row.verdict}** | {row.cause} | {name} |" for name, row in claims]
        lines.append("")
    if rows:
        lines += ["## Paper vs magctl: quantities", "", "| study | quantity | paper | magctl | model | note |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {name} | {row.quantity} | {row.paper} | {row.magctl} | {row.model} | {row.note} |"
                  for name, row in rows]
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
