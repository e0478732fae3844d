"""The report's claim-by-claim table: every claim labelled with its model and verdict, and a cause where
it is not reproduced."""

import pytest

from magctl.core.errors import MagctlError
from magctl.studies.report import write_report
from magctl.studies.runner import Cause, PaperRow, StudyResult, claim

C = Cause("c", True)


def test_a_claim_not_reproduced_needs_its_cause():
    with pytest.raises(MagctlError, match="needs its cause"):
        PaperRow("q", "p", "m", model="closed loop", verdict="not reproduced")
    with pytest.raises(MagctlError, match="model"):
        PaperRow("q", "p", "m", model="a hunch")
    with pytest.raises(MagctlError, match="verdict"):
        PaperRow("q", "p", "m", verdict="roughly")


def test_claim_sets_the_verdict_from_the_test():
    assert claim("§VI-A", "q", "p", "m", "closed loop", holds=True, cause=C).verdict == "reproduced"
    assert claim("§VI-A", "q", "p", "m", "closed loop", holds=True, cause=C).cause == ""
    assert claim("§VI-A", "q", "p", "m", "analysis", holds=False, cause=C).verdict == "not reproduced"
    assert claim("§VI-A", "q", "p", "m", "analysis", holds=False, opposite=True, cause=C).verdict == "opposite"


def test_a_cause_is_printed_only_where_its_own_check_holds():
    """A cause is a sentence and the check of the numbers it cites: where the check fails the row says the
    claim is unexplained (and still shows the numbers), and a bare string is refused."""
    held = claim("§VI-A", "q", "p", "m", "closed loop", holds=False, cause=Cause("x is 3 µm, above 2 µm.", 3 > 2))
    assert held.cause == "x is 3 µm, above 2 µm."
    failed = claim("§VI-A", "q", "p", "m", "closed loop", holds=False, cause=Cause("x is 1 µm, above 2 µm.", 1 > 2))
    assert failed.cause.startswith("unexplained:") and "x is 1 µm" in failed.cause
    with pytest.raises(MagctlError, match="computed Cause"):
        claim("§VI-A", "q", "p", "m", "closed loop", holds=False, cause="fixed prose")


def test_report_puts_claims_in_one_table_ordered_by_section(tmp_path):
    rows = [claim("§VI-B", "side claim", "yes", "no", "closed loop", holds=False, cause=Cause("because of x.", True)),
            PaperRow("a quantity", "1", "2", model="fluid model"),
            claim("§VI-A", "front claim", "yes", "yes", "attempt map", holds=True, cause=C)]
    path = write_report(tmp_path, [StudyResult("s", {}, [], ["summary"], rows)], {"s": 1.0})
    text = path.read_text()
    claims = text[text.index("## The paper's claims"):text.index("## Paper vs magctl: quantities")]
    assert "1 reproduced, 0 consistent at n = 10, 0 not resolvable, 1 not reproduced, 0 opposite" in claims
    assert claims.index("front claim") < claims.index("side claim")
    assert "| — | **not reproduced** | because of x. | s |" in claims
    assert "Verdicts: reproduced" in claims
    assert "a quantity" not in claims and "| s | a quantity | 1 | 2 | fluid model |" in text


def test_claims_are_judged_at_the_papers_ten_trials():
    """A share magctl's sample does not bear out is consistent at n = 10 when the paper's observation has
    probability ≥ 5 % under magctl's model, an ordering is not resolvable then; below 5 % the verdict stands."""
    from magctl.studies.paper_statistics import p_all, p_at_least, p_none, p_order

    assert p_none(0.18) == pytest.approx(0.82**10)                     # 0.137: "never" seen in 10 trials
    assert p_all(0.99) == pytest.approx(0.99**10) and p_all(1.0) == 1.0
    row = claim("§VI-A", "q", "never", "18 %", "closed loop", holds=False, cause=C, p_paper=p_none(0.18))
    assert row.verdict == "consistent at n = 10" and row.p_paper == pytest.approx(0.1374, abs=1e-4)
    assert claim("§VI-A", "q", "p", "m", "closed loop", holds=False, cause=C,
                 p_paper=0.01).verdict == "not reproduced"
    # two controllers whose attempts overlap: ten-trial means come out either way
    a, b = [2, 4, 6, 8], [3, 5, 7, 9]
    p = p_order(b, a)
    assert 0.05 < p < 0.5
    assert claim("§VI-B", "b faster than a", "yes", "no", "closed loop", holds=False, cause=C, p_paper=p,
                 ordering=True).verdict == "not resolvable"
    # identical samples: the paper's order half the time (ties count half); disjoint samples: never
    assert p_order([2, 3], [2, 3]) == pytest.approx(0.5, abs=0.02)
    assert p_order([9, 10], [1, 2]) == 0.0
    # at least 5 of 10 failures at a 30 % failure rate: the binomial tail, summed here term by term
    from math import comb
    assert p_at_least(5, 0.3) == pytest.approx(sum(comb(10, k) * 0.3**k * 0.7 ** (10 - k) for k in range(5, 11)))
    with pytest.raises(ValueError, match="share"):
        p_all(1.5)
