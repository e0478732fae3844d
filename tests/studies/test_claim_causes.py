"""The computed causes of two §VI claims (analysis/front_push.py, analysis/robustness.py): each branch's sentence
carries the numbers it was given, and its check holds or fails with them."""

from __future__ import annotations

import math

import pytest

from magctl.studies import runner


@pytest.fixture(scope="module")
def modules():
    found = runner.discover()
    return found["front-push"], found["robustness"]


def test_landing_probability_is_the_normal_mass_inside_the_band(modules):
    front, _ = modules
    phi = lambda x: 0.5 * (1 + math.erf(x / math.sqrt(2)))  # noqa: E731
    assert front.landing_probability(55.0, 61.0, 75.0) == pytest.approx(phi(20 / 61) - phi(-130 / 61), rel=1e-12)


def test_model_only_cause_reads_which_side_of_the_band_delta0_falls(modules):
    front, _ = modules
    inside = front.model_only_cause(151.0, 96.0, 61.0, 2.0, 2.3)
    assert inside.holds and "+55 µm" in inside.sentence and "inside ε_p" in inside.sentence
    assert not front.model_only_cause(151.0, 96.0, 61.0, 3.0, 2.3).holds      # slower than K_c = 1: not this cause
    beyond = front.model_only_cause(524.0, 121.0, 76.0, 9.0, 2.8)
    assert beyond.holds and "beyond ε_p" in beyond.sentence and "+403 µm" in beyond.sentence


def test_dirt_cause_separates_compensation_from_a_faster_clean_law(modules):
    _, robust = modules
    model, learn = robust.LAWS

    def summary(clean_model, clean_learn, conv=1.0):
        return {model: {"mean_attempts_all": clean_model, "converged_fraction": conv},
                learn: {"mean_attempts_all": clean_learn, "converged_fraction": 1.0}}

    compensates = robust.dirt_cause(summary(7.1, 9.7), {learn: 0.7, model: 1.9})
    assert compensates.holds and "learning does compensate" in compensates.sentence
    assert "7.1 vs 9.7" in compensates.sentence
    assert not robust.dirt_cause(summary(9.7, 7.1), {learn: 0.7, model: 1.9}).holds
    costs_more = robust.dirt_cause(summary(7.1, 9.7), {learn: 2.0, model: 0.5})
    assert costs_more.holds and "+2.0" in costs_more.sentence
    hidden = robust.dirt_cause(summary(30.0, 9.7, conv=0.0), {learn: 0.7, model: 0.0})
    assert hidden.holds and "100%" in hidden.sentence
