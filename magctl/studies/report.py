"""The Markdown report written by ``magctl reproduce``, and the claims tables docs/results.md carries.

``report.md`` opens with the paper's claims, one row each, judged by the rule of
:mod:`magctl.studies.paper_statistics`; ``claims.md`` is that table alone. The claims tables of docs/results.md are
generated from a committed copy of it (``docs/claims.md``): ``python -m magctl.studies.report docs/claims.md``
rewrites the page's blocks between :data:`BEGIN` and :data:`END`, and a test keeps the two equal.
The same report as one self-contained page, ``report.html``, is :mod:`magctl.studies.report_html`'s.
"""

from __future__ import annotations

import os
from pathlib import Path

from magctl.studies.paper_statistics import PAPER_TRIALS, RULE
from magctl.studies.runner import VERDICTS, StudyResult


def _probability(p: float | None) -> str:
    return "—" if p is None else "< 0.001" if p < 0.001 else f"{p:.3f}"


BEGIN, END = "<!-- claims:begin -->", "<!-- claims:end -->"
"""The markers of docs/results.md's generated claims table (magctl's conditions); the paper's conditions' table sits
between the same markers with ``claims-paper`` (:func:`markers`)."""


def markers(conditions: str = "magctl") -> tuple[str, str]:
    """The markers of the claims table of ``conditions`` in docs/results.md."""
    if conditions == "magctl":
        return BEGIN, END
    return BEGIN.replace("claims", f"claims-{conditions}"), END.replace("claims", f"claims-{conditions}")


def claims_table(results: list[StudyResult], conditions: str = "magctl") -> list[str]:
    """The paper's claims, one row each (sorted by section), with their counts and the verdict rule."""
    claims = sorted(((r.name, row) for r in results for row in r.paper if row.verdict),
                    key=lambda item: item[1].section)
    if not claims:
        return []
    counts = {v: sum(row.verdict == v for _, row in claims) for v in VERDICTS}
    lines = [f"Conditions: **{conditions}**. " + ", ".join(f"{n} {v}" for v, n in counts.items())
             + ". _model_: what produced magctl's number "
             "(closed loop: the 30 Hz simulation; attempt map: eq 14–18 iterated; analysis: closed form "
             "or linear analysis; fluid model: the flow alone). _P(paper)_: probability of the paper's "
             f"observation at its {PAPER_TRIALS} trials under magctl's model.", "", RULE, "",
             "| § | claim | paper | magctl | model | P(paper) | verdict | cause | study |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {row.section} | {row.quantity} | {row.paper} | {row.magctl} | {row.model} | "
              f"{_probability(row.p_paper)} | **{row.verdict}** | {row.cause} | {name} |" for name, row in claims]
    return lines


def quantities_table(results: list[StudyResult]) -> list[str]:
    """The paper-vs-magctl quantities (the rows without a verdict) as a Markdown table; empty when there are none."""
    rows = [(r.name, row) for r in results for row in r.paper if not row.verdict]
    if not rows:
        return []
    return ["| study | quantity | paper | magctl | model | note |", "|---|---|---|---|---|---|",
            *(f"| {name} | {row.quantity} | {row.paper} | {row.magctl} | {row.model} | {row.note} |"
              for name, row in rows)]


def write_report(out: Path, results: list[StudyResult], timings: dict[str, float],
                 conditions: str = "magctl") -> Path:
    """Write ``out/report.md`` (the claims table, the paper-vs-magctl quantities, then one section per study)
    and ``out/claims.md`` (the claims table alone), under ``conditions`` (:mod:`magctl.studies.conditions`)."""
    from magctl.studies.conditions import CONDITIONS

    lines = ["# magctl reproduce — report", "", f"Conditions: **{conditions}** — {CONDITIONS[conditions]}.", ""]
    table = claims_table(results, conditions)
    rows = quantities_table(results)
    if table:
        lines += ["## The paper's claims, one row each", "", *table, ""]
        (out / "claims.md").write_text("\n".join(table) + "\n")
    if rows:
        lines += ["## Paper vs magctl: quantities", "", *rows, ""]
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


def results_block(claims_md: str, conditions: str = "magctl") -> str:
    """docs/results.md's generated block for the text of a ``claims.md`` written under ``conditions``."""
    begin, end = markers(conditions)
    return f"{begin}\n{claims_md.rstrip()}\n{end}"


def update_results_page(claims_path: Path, page: Path, conditions: str = "magctl") -> None:
    """Rewrite ``page``'s claims block of ``conditions`` from ``claims_path``."""
    begin, end = markers(conditions)
    text = page.read_text()
    if begin not in text or end not in text:
        raise SystemExit(f"{page}: no {begin} … {end} block to rewrite")
    head, rest = text.split(begin, 1)
    tail = rest.split(end, 1)[1]
    page.write_text(head + results_block(Path(claims_path).read_text(), conditions) + tail)


if __name__ == "__main__":
    import sys

    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python -m magctl.studies.report CLAIMS.md [PAPER-CLAIMS.md]  (rewrites "
                         "docs/results.md's claims tables: magctl's conditions, then the paper's)")
    page_path = Path(__file__).resolve().parents[2] / "docs" / "results.md"
    for path, cond in zip(sys.argv[1:], ("magctl", "paper"), strict=False):
        update_results_page(Path(path), page_path, cond)
