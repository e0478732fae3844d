"""Iteration-domain analysis against closed forms, python-control and the paper's numbers."""

import importlib.util
import json
import math

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from magctl.cli import build_parser
from magctl.cli.stability_reports import front_report, side_report
from magctl.control.learning import front_push_law, side_push_law
from magctl.control.side_models import ExpSideModel, LinSideModel, side_model
from magctl.core.errors import MagctlError
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.stability import iteration as S


# --- eq 14-15 -------------------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(st.floats(0.01, 3.0))
def test_front_pole_is_one_minus_kc(kc):
    loop = S.front_loop(kc)
    np.testing.assert_allclose(loop.poles, [1 - kc], atol=1e-12)  # eq 15 denominator z − 1 + K_c
    expected = control.tf([kc], [1, -1 + kc], dt=1)
    w = np.exp(1j * np.array([0.2, 1.3, 3.0]))
    np.testing.assert_allclose(loop.closed_loop(w), expected(w), atol=1e-12)
    assert (loop.verdict == "stable") == (0 < kc < 2)


@pytest.mark.parametrize("kc,verdict,damping", [
    (0.0, "marginal", "integrating"), (0.5, "stable", "overdamped"), (1.0, "stable", "critically damped"),
    (1.5, "stable", "underdamped"), (2.0, "marginal", "oscillatory"), (2.1, "unstable", "unstable"),
])
def test_front_damping_classes(kc, verdict, damping):
    loop = S.front_loop(kc)
    assert (loop.verdict, loop.damping) == (verdict, damping)


def test_classify_complex_pair():
    assert S.classify([0.3 + 0.4j, 0.3 - 0.4j]) == ("stable", "underdamped")
    assert S.classify([0.6j, -0.6j, 0.2]) == ("stable", "underdamped")
    assert S.classify([np.exp(1j), np.exp(-1j)]) == ("marginal", "oscillatory")


def test_front_diagram_uses_the_law_block_and_simulates_eq_13():
    kc, d0, dpr = 0.5, 127 * UM, 300 * UM
    law = front_push_law(kc, d0)
    dia = S.front_iteration_diagram(law)
    assert law in dia.blocks.values()
    np.testing.assert_allclose(control.poles(dia.to_control()), [1 - kc])
    res = simulate(dia, 8, inputs={"goal": 0.0, "release": dpr})
    err = res.outputs["error"][0]
    # e(i) = (1 − K_c)^i (D_p,r − δ(0)), from eq 10 and 13 by hand
    np.testing.assert_allclose(err, (1 - kc) ** np.arange(8) * (dpr - d0), atol=1e-15)


# --- eq 19-20 and the loop with its feed-forward path ----------------------------------------
@settings(max_examples=40, deadline=None)
@given(st.floats(0.01, 3.0), st.floats(0.05, 3.0))
def test_side_paper_loop_and_full_loop_poles(ks, rho):
    np.testing.assert_allclose(S.side_loop(ks, rho).poles, [1 - ks * rho], atol=1e-12)  # eq 20
    # two-state loop: z² − (2 − ρ(1+K_s)) z + (1 − ρ), derived by hand from eq 16-18
    ref = np.sort_complex(np.roots([1.0, -(2 - rho * (1 + ks)), 1 - rho]))
    got = np.sort_complex(S.side_full_poles(ks, rho))
    np.testing.assert_allclose(got, ref, atol=1e-7)
    rng = S.side_full_stable_range(rho)
    inside = rng is not None and rng[0] < ks < rng[1]
    assert inside == bool(np.max(np.abs(ref)) < 1 - 1e-9) or abs(np.max(np.abs(ref)) - 1) < 1e-6


def test_side_diagram_simulation_matches_the_recursion():
    ks, rho, goal = 0.9, 0.6, 300 * UM
    dia = S.side_iteration_diagram(side_push_law(ks), rho)
    res = simulate(dia, 12, inputs={"goal": goal})
    e, d = goal, 0.0
    for i in range(12):
        assert res.outputs["error"][0, i] == pytest.approx(e, abs=1e-15)
        act = rho * (e + d)
        e, d = e - act, d - ks * (act - e)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_sweep_matches_eigenvalues(seed):
    rng = np.random.default_rng(seed)
    gains, ratios = rng.uniform(0, 3, 7), rng.uniform(0, 3, 5)
    for loop in ("paper", "full"):
        out = S.sweep(gains, ratios, loop)
        for i, k in enumerate(gains):
            for j, r in enumerate(ratios):
                A = np.array([[1 - k * r]]) if loop == "paper" else np.array([[1 - r, -r], [k * (1 - r), 1 - k * r]])
                rad = np.max(np.abs(np.linalg.eigvals(A)))
                assert out["spectral_radius"][i, j] == pytest.approx(rad, rel=1e-6, abs=1e-9)


def test_sweep_rejects_unknown_loop():
    with pytest.raises(MagctlError, match="'bogus'"):
        S.sweep([1.0], [1.0], "bogus")


# --- stochastic front convergence ------------------------------------------------------------
def test_front_markov_matches_closed_forms():
    # K_c = 1, δ(0) = 0: attempt 1 converges iff |D_p,r| < ε; attempt 2 iff |D2 − D1| < ε, D2 − D1 ~ N(0, 2σ²)
    p = S.front_attempts_markov(1.0, 0.0)
    p1 = norm.cdf(75, 300, 75) - norm.cdf(-75, 300, 75)
    assert p[0] == pytest.approx(p1, rel=2e-2)
    p2 = 2 * norm.cdf(75 / (75 * math.sqrt(2))) - 1
    assert p[1] == pytest.approx(p2 * (1 - p1), rel=2e-2)
    # K_c = 0, δ(0) = 127 µm: independent attempts, geometric law
    q = norm.cdf(127 + 75, 300, 75) - norm.cdf(127 - 75, 300, 75)
    p = S.front_attempts_markov(0.0, 127 * UM)
    np.testing.assert_allclose(p[:-1], q * (1 - q) ** np.arange(10), rtol=2e-2)
    assert p.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("kc,d0", [(0.5, 0.0), (1.0, 127 * UM), (1.5, 0.0)])
def test_front_markov_agrees_with_monte_carlo(kc, d0):
    p = S.front_attempts_markov(kc, d0)
    mc = S.front_attempts_monte_carlo(kc, d0, trials=40000, seed=3)
    assert np.max(np.abs(p - mc)) < 0.012


def test_front_naive_steady_error_is_release_minus_overshoot():
    # §VI-A: K_c = 0, δ(0) = 0 gives ~200 µm = 300 µm release − 100 µm servo overshoot
    res = S.front_attempt_map(0.0, 0.0, np.full((1, 10), 300 * UM), overshoot=100 * UM)
    np.testing.assert_allclose(res["error"][0], 200 * UM)
    assert res["attempts"][0] == -1


def test_front_unstable_gain_diverges_in_the_map():
    res = S.front_attempt_map(2.1, 0.0, np.full((1, 10), 300 * UM))
    e = np.abs(res["error"][0])
    assert res["attempts"][0] == -1 and e[-1] > e[0]


# --- side-push models and the nonlinear map --------------------------------------------------
def test_side_models_are_eq_22_and_23():
    exp, lin = ExpSideModel(), LinSideModel()
    assert exp.displacement(370 * UM) / UM == pytest.approx(1755 * math.exp(-0.009042 * 370))
    assert exp.gap(100 * UM) / UM == pytest.approx(-math.log(100 / 1755) / 0.009042)
    assert lin.gap(20 * UM) / UM == pytest.approx(-5.29 * 20 + 621)
    assert lin.displacement(lin.gap(33 * UM)) == pytest.approx(33 * UM)
    with pytest.raises(MagctlError, match="'cubic'"):
        side_model("cubic")


def test_local_ratio_of_lin_against_exp():
    d = np.array([5.0, 20.0, 60.0]) * UM
    np.testing.assert_allclose(S.local_ratio(d), 5.29 * 0.009042 * np.array([5.0, 20.0, 60.0]), rtol=1e-9)


def test_side_ks_09_lin_model_converges_against_exp_plant_from_300um():
    res = S.side_attempt_map(0.9, 300 * UM, model="lin")
    assert 0 < res["attempts"][0] <= 10  # Fig 14: every side push within ε_p after 10 attempts
    last = res["error"][0][np.isfinite(res["error"][0])][-1]
    assert abs(last) < 7.5 * UM


def test_printed_eq_18_sign_does_not_converge():
    res = S.side_attempt_map(np.array([0.5, 0.9]), 300 * UM, model="lin", printed_sign=True)
    assert np.all(res["attempts"] == -1)


def test_naive_fixed_gaps_behave_as_reported():
    # §VI-B: D_g = 370 µm over-pushes and oscillates; D_g = 500 µm converges slowly within 30
    r370 = S.side_attempt_map(0.0, 300 * UM, fixed_gap=370 * UM)
    r500 = S.side_attempt_map(0.0, 300 * UM, fixed_gap=500 * UM)
    assert r370["attempts"][0] == -1
    assert 10 < r500["attempts"][0] <= 30


def test_nonlinear_gain_range_contains_paper_gains():
    # at the paper's 370 µm bound (the paper's gains are stated for its plant)
    out = S.side_nonlinear_gain_range("lin", gains=np.arange(0, 6.01, 0.1), min_gap=370e-6)
    lo, hi = out["range"]
    assert lo == 0.0 and 0.9 < hi < 6.0


# --- command line ----------------------------------------------------------------------------
def _run(argv, capsys):
    args = build_parser().parse_args(["stability", *argv])
    assert args.func(args) == 0
    return json.loads(capsys.readouterr().out)


def test_cli_front_verdicts(capsys):
    d = _run(["front", "--kc", "1", "--json"], capsys)
    assert d["verdict"] == "stable" and d["damping"] == "critically damped"
    assert d["poles"][0]["abs"] == pytest.approx(0.0, abs=1e-12)
    d = _run(["front", "--kc", "2.1", "--json"], capsys)
    assert d["verdict"] == "unstable"
    assert d["poles"][0]["re"] == pytest.approx(-1.1)


def test_cli_side(capsys):
    d = _run(["side", "--ks", "0.9", "--model", "lin", "--min-gap-um", "370", "--json"], capsys)
    assert d["nonlinear_map"]["converged"] and d["paper_analysis"]["verdict"] == "stable"
    assert d["operating_range"]["local_ratio_max"] == pytest.approx(5.29 * 0.009042 * 1755 * math.exp(-0.009042 * 370),
                                                                     rel=1e-6)


def test_cli_errors_are_magctl_errors():
    with pytest.raises(MagctlError, match="--kc"):
        front_report(float("nan"))
    with pytest.raises(MagctlError, match="--min-gap-um"):
        side_report(0.9, "lin", min_gap_um=-1)


@pytest.mark.skipif(importlib.util.find_spec("magctl.cli.stability") is None,
                    reason="the magctl stability command module is not there yet")
def test_through_magctl_main(capsys):
    from magctl.cli import main

    assert main(["stability", "front", "--kc", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["damping"] == "critically damped"
    assert main(["stability", "front", "--kc", "nan", "--json"]) == 2


def test_tabulated_plant_reproduces_eq_22_and_rejects_bad_tables():
    from magctl.control.side_models import TabulatedSideModel

    exp = ExpSideModel()
    g = np.linspace(300, 900, 7) * UM
    table = TabulatedSideModel(tuple(g), tuple(exp.displacement(g)))
    a = S.side_attempt_map(np.array([0.0, 0.5, 0.9]), 300 * UM, model="lin", plant=table)
    b = S.side_attempt_map(np.array([0.0, 0.5, 0.9]), 300 * UM, model="lin")
    np.testing.assert_array_equal(a["attempts"], b["attempts"])
    np.testing.assert_allclose(table.slope(np.array([5e-6, 50e-6])), exp.slope(np.array([5e-6, 50e-6])))
    with pytest.raises(MagctlError, match="decreasing"):
        TabulatedSideModel((1e-4, 2e-4), (1e-5, 2e-5))
    with pytest.raises(MagctlError, match="--plant"):
        side_report(0.9, "lin", plant="cfd")


def test_the_stable_gain_ranges_are_where_python_controls_poles_lie_inside_the_unit_circle():
    """The front loop's (0, 2) and the side loop's (0, 2/ρ) against the closed-loop poles python-control computes
    on a grid of gains, not against the closed form they state."""
    import control

    from magctl.control.learning import front_push_law, side_push_law

    def stable(law_tf, sign, ratio):
        cl = control.feedback(law_tf * (sign * ratio), 1)
        return bool(np.all(np.abs(cl.poles()) < 1 - 1e-12))

    for ratio, make, sign, loop in ((1.0, front_push_law, 1.0, lambda g, r: S.front_loop(g)),
                                    (1.4, side_push_law, -1.0, S.side_loop), (0.6, side_push_law, -1.0, S.side_loop)):
        lo, hi = loop(1.0, ratio).stable_gain_range
        for g in np.linspace(lo - 0.5, hi + 0.5, 41):
            inside = lo < g < hi
            if min(abs(g - lo), abs(g - hi)) < 1e-6:
                continue
            assert stable(make(float(g)).to_control(), sign, ratio) == inside, (ratio, g)
