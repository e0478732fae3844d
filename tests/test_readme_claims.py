"""The claims tables of docs/results.md are the committed docs/claims.md and docs/claims-paper.md that
``magctl reproduce`` and ``magctl reproduce --conditions paper`` wrote (their claims.md)."""

from pathlib import Path

import pytest

from magctl.studies.report import markers, results_block

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("conditions, name", [("magctl", "claims.md"), ("paper", "claims-paper.md")])
def test_the_results_page_claims_tables_are_the_committed_claims_files(conditions, name):
    text = (ROOT / "docs" / "results.md").read_text()
    claims = (ROOT / "docs" / name).read_text()
    begin, end = markers(conditions)
    block = begin + text.split(begin, 1)[1].split(end, 1)[0] + end
    fix = "python -m magctl.studies.report docs/claims.md docs/claims-paper.md"
    assert block == results_block(claims, conditions), \
        f"docs/results.md's claims table differs from docs/{name}: run {fix}"
    assert "| P(paper) |" in claims and "Verdicts: reproduced" in claims and f"Conditions: **{conditions}**" in claims
