"""The side push as the algorithm runs it: the switched attempt map against closed forms, the attempt map,
the 30 Hz task and ``magctl stability side``."""

import json

import numpy as np
import pytest

from magctl.cli import build_parser
from magctl.cli.stability_reports import side_report
from magctl.control.learning import LearningLaw, side_push_law
from magctl.control.push.side import SidePushTask
from magctl.control.status import Status
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.plant.standin import KinematicRobot, StandinSpheres, StandinTracker, StraightToTarget, standin_params
from magctl.stability import iteration as S
from magctl.stability import switched as W

RATIOS = np.round(np.arange(0.05, 3.51, 0.05), 2)
"""ρ grid of the boundary checks (step 0.05)."""
GRID_KS = (0.0, 0.5, 0.9, 1.5)
GRID_RATIOS = (0.5, 1.4, 1.8, 2.6, 3.0)
"""The (K_s, ρ) grid on which the command, the attempt map and the 30 Hz task are compared."""
TIGHT_EPS = 0.05 * UM
"""A tolerance far below ε_p: no trial lands inside it by chance while oscillating."""
MAX_ATTEMPTS = 60


# --- the branches against hand-derived closed forms ---------------------------------------------------
@pytest.mark.parametrize("ks,rho", [(0.9, 1.4), (1.5, 0.7), (0.3, 2.6)])
def test_branch_polynomials(ks, rho):
    m = W.branch_matrices(ks, rho)
    # under-push: the signed model; over-push: λ² − ρ(1 − K_s)λ + (ρ − 1), derived from eq 16-18 by hand
    np.testing.assert_allclose(np.poly(m[W.UNDER]), [1, -(2 - rho * (1 + ks)), 1 - rho], atol=1e-12)
    np.testing.assert_allclose(np.poly(m[W.OVER]), [1, -rho * (1 - ks), rho - 1], atol=1e-12)
    np.testing.assert_allclose(m[W.NO_PUSH], [[1, 0], [ks, 1]])


def test_switched_step_is_the_attempt_map_with_a_linear_plant():
    # eq 22 model against eq 22 scaled by ρ: D_s,act = ρ (D_s,des + Δ) exactly, through the algorithm's own code
    rng = np.random.default_rng(1)
    ks, rho = 0.9, 1.7
    e0 = rng.uniform(1, 50, 40) * UM
    d0 = rng.uniform(-60, 40, 40) * UM
    law = LearningLaw("side_law", -ks, initial=d0)
    run = S.side_attempt_map(np.full(40, ks), e0, model="exp", plant=W.ScaledSideModel(scale=rho), eps=0.0,
                             max_attempts=3, min_gap=-np.inf, law=law)
    x = np.stack([e0, d0], axis=1)
    for i in range(3):
        np.testing.assert_allclose(np.abs(run["error"][:, i]), x[:, 0], rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(run["correction"][:, i], x[:, 1], rtol=1e-9, atol=1e-18)
        x, branch = W.switched_step(x, ks, rho)
    assert {0, 1, 2} >= set(np.unique(branch))


def test_jsr_bounds_of_a_known_pair():
    # {[[0,1],[0,0]], [[0,0],[1,0]]}: each nilpotent, the product has spectral radius 1, so the JSR is 1
    a, b = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [1.0, 0.0]])
    lo, hi = W.jsr_bounds([a, b], depth=6)
    assert lo == pytest.approx(1.0) and hi == pytest.approx(1.0)
    lo, hi = W.jsr_bounds([np.diag([0.5, -0.8])], depth=4)
    assert lo == pytest.approx(0.8) and hi == pytest.approx(0.8)


def test_neutral_two_cycle_when_ks_rho_reaches_2():
    # no push then over-push returns (|e|, Δ₀) with Δ₀ = |e|(2/ρ − 1 − K_s) whenever K_s ρ ≥ 2 (Δ₀ ≤ −|e|)
    ks, rho = 1.5, 1.4
    x0 = np.array([1.0, 2 / rho - 1 - ks])
    x1, b1 = W.switched_step(x0, ks, rho)
    x2, b2 = W.switched_step(x1, ks, rho)
    assert (int(b1), int(b2)) == (W.NO_PUSH, W.OVER)
    np.testing.assert_allclose(x2, x0, atol=1e-12)
    v = W.switched_verdict(ks, rho)
    assert v.verdict == "marginal" and v.growing_ray["multiplier_per_attempt"] == pytest.approx(1.0)


def test_ks_zero_is_one_state():
    for rho, verdict in ((0.5, "stable"), (1.9, "stable"), (2.0, "marginal"), (2.4, "unstable")):
        v = W.switched_verdict(0.0, rho)
        assert v.verdict == verdict and v.growth_rate == pytest.approx(abs(1 - rho))


def test_switched_verdict_rejects_bad_input():
    with pytest.raises(MagctlError, match="ratio"):
        W.switched_verdict(0.9, -1.0)
    with pytest.raises(MagctlError, match="plant scale"):
        W.ScaledSideModel(scale=0.0)


# --- the stable region: switched vs the growth rate of the nonlinear map -----------------------------
@pytest.mark.parametrize("ks", [0.0, 0.5, 0.9, 1.2, 1.5, 2.0, 3.0])
def test_switched_boundary_matches_the_attempt_map_growth_rate(ks):
    switched = W.switched_stable(ks, RATIOS)
    from_map = W.map_growth_rate(ks, RATIOS) < 1 - 1e-3
    b_sw, b_map = W.boundary(RATIOS, switched), W.boundary(RATIOS, from_map)
    assert (b_sw is None) == (b_map is None)
    if b_sw is not None:
        assert abs(b_sw - b_map) <= 0.05 + 1e-9  # to the grid step
    # for K_s ≥ 0.9 the boundary is the neutral 2-cycle's K_s ρ = 2 (closed form above); K_s = 0: |1 − ρ| = 1
    expected = {0.0: 2.0, 0.5: None}.get(ks, None if ks < 0.9 else float(RATIOS[np.argmax(RATIOS * ks >= 2 - 1e-9)]))
    assert b_sw == expected


def test_region_differs_from_the_signed_model_and_eq_20():
    # the command's example: K_s = 0.9, ρ = 1.4 is unstable in the signed model, stable as run and by eq 20
    assert W.switched_verdict(0.9, 1.4).verdict == "stable"
    assert S.classify(S.side_full_poles(0.9, 1.4))[0] == "unstable"
    # "for ρ ≥ 2 no K_s stabilises" (signed model) is false for the algorithm: K_s = 0.5 at ρ = 3
    assert S.side_full_stable_range(3.0) is None
    assert W.switched_verdict(0.5, 3.0).verdict == "stable"


# --- the command against the attempt map and the 30 Hz task -------------------------------------------
PAPER_MIN_GAP = 370 * UM
"""The grid below is laid out for the paper's bound (eq 22's plant, where the paper's robot touched)."""


def _cli(argv, capsys):
    args = build_parser().parse_args(["stability", "side", *argv, "--json"])
    assert args.func(args) == 0
    return json.loads(capsys.readouterr().out)


def _task_runs(ks, rho):
    """The 30 Hz SidePushTask (eq 22 model) round the stand-in plant with eq 22 scaled by ρ per trial.

    Composition of tests/control/test_push.py's ideal loop (ideal servo, kinematic robot, stand-in spheres and
    tracker). Geometry widened so that the only sphere motion is the passes': repositioning round a 2.5 mm
    circle outside the 2.4 mm side-pass range, passes from 3 mm behind to 3 mm ahead (at 2.4 mm eq 22 gives
    7e-7 µm, so the range cut-off does not shape the curve).
    """
    p = standin_params()
    task = SidePushTask(goal=(300 * UM, 0.0), law=side_push_law(ks), model="exp", clearance=2.5e-3, behind=3e-3,
                        ahead=3e-3, pass_speed=3e-3, travel_speed=3e-3, arrive_tol=0.1 * UM, eps=TIGHT_EPS,
                        max_attempts=MAX_ATTEMPTS, min_gap=PAPER_MIN_GAP)
    r0, s0 = (-1e-3, 0.0), np.array([[0.0, 0.0]])
    n = task.name
    dia = Diagram("loop", [
        task, StraightToTarget("servo", v_max=3e-3), KinematicRobot("robot", start=r0),
        StandinSpheres("spheres", s0, p.contact_distance, side_range=2.4e-3, sphere_radius=p.sphere_radius,
                       start_robot=r0, side_scale=rho),
        StandinTracker("tracker", 1, p.workspace_half, None, r0, 0.0, s0),
    ], [
        ("tracker.robot_est", f"{n}.robot_est"), ("tracker.spheres_est", f"{n}.spheres_est"),
        ("tracker.lost", f"{n}.lost"), (f"{n}.target", "servo.target"), (f"{n}.speed_cap", "servo.speed_cap"),
        ("robot.position", "servo.position"), ("servo.speed", "robot.speed"), ("servo.heading", "robot.heading"),
        ("robot.position", "spheres.position"), ("robot.position", "tracker.position"),
        ("robot.heading", "tracker.heading"), ("spheres.spheres", "tracker.spheres"),
    ])
    res = simulate(dia, 12000, batch=len(ks), record=[f"{n}.status", f"{n}.attempt"])
    return res[f"{n}.status"][:, -1], res[f"{n}.attempt"][:, -1]


def test_command_verdict_agrees_with_the_attempt_map_and_the_30hz_task(capsys):
    ks = np.repeat(GRID_KS, len(GRID_RATIOS))
    rho = np.tile(GRID_RATIOS, len(GRID_KS))
    status, task_attempts = _task_runs(ks, rho)
    verdicts = []
    for i, (k, r) in enumerate(zip(ks, rho, strict=True)):
        d = _cli(["--ks", f"{k:g}", "--model", "exp", "--plant-scale", f"{r:g}", "--min-gap-um", "370"], capsys)
        assert d["ratio"] == pytest.approx(r) and d["ratio_source"].startswith("exact")
        assert d["verdict"] == d["switched"]["verdict"]
        verdicts.append(d["verdict"])
        run = S.side_attempt_map(k, 300 * UM, model="exp", plant=W.ScaledSideModel(scale=r), eps=TIGHT_EPS,
                                 max_attempts=MAX_ATTEMPTS, min_gap=PAPER_MIN_GAP)
        map_ok = run["attempts"][0] >= 0
        task_ok = status[i] == Status.CONVERGED
        assert (d["verdict"] == "stable") == map_ok == task_ok, (k, r, d["verdict"], run["attempts"][0], status[i])
        if task_ok:  # same algorithm, same plant: the attempt counts agree to one
            assert abs(int(task_attempts[i]) - int(run["attempts"][0])) <= 1
        else:
            assert status[i] == Status.ATTEMPT_LIMIT
    # the grid holds every kind, with ρ > 1 on both sides
    assert {"stable", "marginal", "unstable"} <= set(verdicts)
    assert any(v == "stable" and r > 2 for v, r in zip(verdicts, rho, strict=True))


def test_command_reports_three_labelled_analyses(capsys):
    d = _cli(["--ks", "0.9", "--ratio", "1.4"], capsys)
    assert d["verdict"] == "stable"
    assert d["paper_analysis"]["verdict"] == "stable" and d["with_feedforward"]["verdict"] == "unstable"
    for key in ("paper_analysis", "with_feedforward", "switched", "nonlinear_map"):
        assert d[key]["label"]
    assert d["switched"]["growth_rate_attempt_map"] == pytest.approx(d["switched"]["growth_rate"], rel=1e-3)
    d = _cli(["--ks", "0.9", "--plant-gap-scale", "1.7"], capsys)
    assert "gaps x1.7" in d["plant"] and d["ratio_source"].startswith("assumed")


def test_command_rejects_bad_plant_scales():
    with pytest.raises(MagctlError, match="--plant-gap-scale"):
        side_report(0.9, "lin", plant_gap_scale=0.0)
