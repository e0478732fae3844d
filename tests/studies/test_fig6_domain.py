"""The fig6-domain study on two domains (the unbounded half-space and a 1 mm lid): confinement
speeds the decay of the side-push curve, as a flow screened by a second wall must, and the
verdict names the domain whose decay rate is closer to the paper's eq 22."""

from __future__ import annotations

import pytest

from magctl.plant.fluid.calibration import paper_side
from magctl.plant.fluid.domain import Domain
from magctl.studies import runner as studies


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    module = studies.discover()["fig6-domain"]
    saved = module.LAYERS
    module.LAYERS = (Domain(), Domain("lid", 1e-3))
    try:
        ctx = studies.StudyContext(out=tmp_path_factory.mktemp("fig6-domain"), quiet=True)
        return studies.run_study("fig6-domain", ctx, figures=True)
    finally:
        module.LAYERS = saved


def test_a_lid_screens_the_flow(result):
    unbounded, lid = result.results["domains"]
    assert (unbounded["kind"], lid["kind"]) == ("unbounded", "lid")
    assert lid["fit"]["b_per_um"] > 1.3 * unbounded["fit"]["b_per_um"]
    assert abs(lid["at_um"]["650"]) < unbounded["at_um"]["650"]
    # the near field is barely touched by a lid five robot heights away: within 25 % at 370 µm
    assert lid["at_um"]["370"] == pytest.approx(unbounded["at_um"]["370"], rel=0.25)


def test_verdict_names_the_domain_closest_to_eq22(result):
    r = result.results
    closest = min(r["domains"], key=lambda c: abs(c["fit"]["b_per_um"] - paper_side()["rate"] * 1e-6))
    assert r["verdict"]["best"] == closest["domain"]
    assert r["verdict"]["unbounded_b_per_um"] == r["domains"][0]["fit"]["b_per_um"]
    assert any("closest to the paper" in line for line in result.summary)
    assert [p.name for p in result.figures] == ["fig6_domain.png"]


def test_reproduce_leaves_the_domain_study_to_be_run_by_name():
    found = studies.discover()
    assert "fig6-domain" in found and "fig6-domain" not in studies.reproduced(found)
    assert "sidepush-curve" in studies.reproduced(found)
