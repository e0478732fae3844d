"""The report's claim-by-claim table: every claim labelled with its model and verdict, and a cause where
it is not reproduced."""

import pytest

from magctl.core.errors import MagctlError
from magctl.studies.report import write_report
from magctl.studies.runner import PaperRow, StudyResult, claim


def test_a_claim_not_reproduced_needs_its_cause():
    with pytest.raises(MagctlError, match="needs its cause"):
        PaperRow("q", "p", "m", model="closed loop", verdict="not reproduced")
    with pytest.raises(MagctlError, match="model"):
        PaperRow("q", "p", "m", model="a hunch")
    with pytest.raises(MagctlError, match="verdict"):
        PaperRow("q", "p", "m", verdict="roughly")


def test_claim_sets_the_verdict_from_the_test():
    assert claim("§VI-A", "q", "p", "m", "closed loop", holds=True, cause="c").verdict == "reproduced"
    assert claim("§VI-A", "q", "p", "m", "closed loop", holds=True, cause="c").cause == ""
    assert claim("§VI-A", "q", "p", "m", "analysis", holds=False, cause="c").verdict == "not reproduced"
    assert claim("§VI-A", "q", "p", "m", "analysis", holds=False, opposite=True, cause="c").verdict == "opposite"


def test_report_puts_claims_in_one_table_ordered_by_section(tmp_path):
    rows = [claim("§VI-B", "side claim", "yes", "no", "closed loop", holds=False, cause="because of x."),
            PaperRow("a quantity", "1", "2", model="fluid model"),
            claim("§VI-A", "front claim", "yes", "yes", "attempt map", holds=True, cause="unused")]
    path = write_report(tmp_path, [StudyResult("s", {}, [], ["summary"], rows)], {"s": 1.0})
    text = path.read_text()
    claims = text[text.index("## The paper's claims"):text.index("## Paper vs magctl: quantities")]
    assert "1 reproduced, 1 not reproduced, 0 opposite" in claims
    assert claims.index("front claim") < claims.index("side claim")
    assert "| **not reproduced** | because of x. | s |" in claims
    assert "a quantity" not in claims and "| s | a quantity | 1 | 2 | fluid model |" in text
