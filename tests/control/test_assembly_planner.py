"""The multi-sphere assembly planner: arrangements, the casadi problem, its bounds and its convergence.

Independent numbers: bond geometry from trigonometry, the objective's gradient against central finite
differences of the numeric objective, the bounds checked by direct distance computations (not by the planner's
own ``violation``), and the pass map's prediction against the plant's own pass (tests/studies/test_pass_map.py).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magctl.control import assembly_planner
from magctl.control.arrangement import arrangement
from magctl.control.assembly_planner import AssemblyPlanner, GreedyPlanner, PassPlanner, PlanLimits
from magctl.control.pass_model import pass_map
from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.loops import geometry

R = 105 * UM


# --- arrangements -------------------------------------------------------------------------------------------
def test_triangle_of_touching_spheres_is_assembled_and_a_gap_is_not():
    d = 2 * R + 5 * UM
    tri = np.array([[0, 0], [d, 0], [d / 2, d * np.sqrt(3) / 2]])
    t = arrangement("triangle")
    assert t.assembled(tri)
    assert t.error(tri) < 1e-9
    opened = tri.copy()
    opened[2, 1] += 8 * UM   # 2-0 and 2-1 bonds now ≈ 2R + 12 µm > 2R + ε_as
    assert not t.assembled(opened)


@pytest.mark.parametrize("bend_deg, straight", [(0.0, True), (15.0, True), (25.0, False), (60.0, False)])
def test_a_line_counts_as_straight_within_its_bend(bend_deg, straight):
    """Three touching spheres bent by β: ends 4R·cos(β/2) apart; [plan] bend = 20°."""
    d = 2 * R
    b = np.deg2rad(bend_deg)
    p = np.array([[0, 0], [d, 0], [d + d * np.cos(b), d * np.sin(b)]])
    assert arrangement("line", 3).assembled(p) == straight


def test_placement_puts_the_apex_and_the_chain_end_where_the_bonds_say():
    t = arrangement("triangle")
    p = np.array([[0, 0], [2 * R, 0], [1e-4, 9e-4]])
    apex = t.placement(p, 2)
    target = 2 * R + t.eps_as / 2
    assert np.linalg.norm(apex - p[0]) == pytest.approx(target)
    assert np.linalg.norm(apex - p[1]) == pytest.approx(target)
    assert apex[1] > 0   # on sphere 2's side
    line = arrangement("line", 3)
    end = line.placement(p, 2)
    assert end == pytest.approx(np.array([2 * R + target, 0.0]))


@pytest.mark.parametrize("name, n", [("square", 4), ("triangle", 4), ("pair", 3), ("line", 2)])
def test_unknown_arrangements_and_sizes_are_refused(name, n):
    with pytest.raises(MagctlError, match="arrangement"):
        arrangement(name, n)


# --- the problem ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def triangle_planner():
    return AssemblyPlanner(arrangement("triangle"))


def _layout():
    return geometry("assembly-3")["spheres"].copy()


def test_objective_gradient_matches_finite_differences(triangle_planner):
    """casadi's gradient (through the B-spline pass map) against central differences of the objective."""
    pl = triangle_planner
    p = _layout()
    prm = pl._parameters(p, 0.9)
    rng = np.random.default_rng(3)
    for _ in range(4):
        cand, ok = pl.samples(p)
        x = cand[ok][rng.integers(ok.sum())].reshape(4) / 1e-3 + 0.02 * rng.standard_normal(4)
        grad = np.asarray(pl.gradient(x, prm)).ravel()
        h = 1e-6
        fd = np.array([(float(pl.objective(x + h * e, prm)) - float(pl.objective(x - h * e, prm))) / (2 * h)
                       for e in np.eye(4)])
        assert grad == pytest.approx(fd, rel=1e-4, abs=1e-6 * max(1.0, np.abs(fd).max()))


def _bounds_kept(limits: PlanLimits, spheres, a, b) -> None:
    """The bounds measured directly: segment-to-centre distance, end distances, length, field."""
    for c in spheres:
        s = np.linspace(0, 1, 20001)[:, None]
        seg = a + s * (b - a)
        assert np.min(np.linalg.norm(seg - c, axis=1)) >= limits.min_gap - 1e-9
        assert min(np.linalg.norm(a - c), np.linalg.norm(b - c)) >= limits.end_clearance - 1e-9
    length = np.linalg.norm(b - a)
    assert limits.min_length - 1e-9 <= length <= limits.max_length + 1e-9
    x0, y0, x1, y1 = limits.field
    for q in (a, b):
        assert x0 - 1e-9 <= q[0] <= x1 + 1e-9 and y0 - 1e-9 <= q[1] <= y1 + 1e-9


def test_planned_passes_violate_no_bound_and_lower_the_predicted_error(triangle_planner):
    pl = triangle_planner
    rng = np.random.default_rng(11)
    base = _layout()
    for _ in range(5):
        p = base + 60 * UM * rng.standard_normal(base.shape)
        plan = pl.plan(p)
        _bounds_kept(pl.limits, p, plan.start, plan.end)
        assert plan.error < pl.target.error(p)
        # the prediction is the pass map's, and no sampled pass beats the chosen one
        assert plan.predicted == pytest.approx(p + pl.map.displacement(p, plan.start, plan.end), abs=1e-12)
        cand, ok = pl.samples(p)
        best_sample = min(pl.cost(p, c[0], c[1]) for c in cand[ok])
        assert plan.cost <= best_sample + 1e-9


def test_no_feasible_pass_gives_no_plan():
    """Spheres in a corner of a field too small to hold a pass at the end clearance: the planner says so."""
    t = arrangement("pair")
    lim = dataclasses.replace(PlanLimits.default(), field=(0.3e-3, 0.3e-3, 1.2e-3, 1.2e-3))
    pl = AssemblyPlanner(t, limits=lim)
    assert pl.plan(np.array([[0.6e-3, 0.6e-3], [0.9e-3, 0.6e-3]])) is None


@pytest.mark.parametrize("name", ["triangle", "line"])
def test_receding_horizon_assembles_three_on_the_pass_map_in_fewer_passes_than_greedy(name):
    """On the model itself: the planned passes assemble the study's three-sphere layout within 30 passes,
    and the greedy θ_n = 30° baseline needs more (or does not finish)."""
    m = pass_map()
    t = arrangement(name)
    counts = {}
    for kind, pl in (("planned", AssemblyPlanner(t)), ("greedy", GreedyPlanner(t))):
        p, robot, passes = _layout(), geometry("assembly-3")["robot"], 0
        while passes < 30 and not t.assembled(p):
            plan = pl.plan(p) if kind == "planned" else pl.plan(p, robot)
            p, robot, passes = p + m.displacement(p, plan.start, plan.end), plan.end, passes + 1
        counts[kind] = passes if t.assembled(p) else 31
    assert counts["planned"] <= 30
    assert counts["planned"] < counts["greedy"]


def test_greedy_pair_pass_is_the_papers_adjusted_line():
    """Eq 21's geometry: the pass leaves the moved sphere (1, towards sphere 0) at θ_n to its line to the fixed
    one, turned to the robot's side, at the gap eq 17 asks for (exp-fit, bounded at the contact threshold)."""
    t = arrangement("pair")
    g = GreedyPlanner(t)
    p = np.array([[2e-3, 1.8e-3], [2.6e-3, 1.8e-3]])
    robot = np.array([1e-3, 1.9e-3])         # above the line
    plan = g.plan(p, robot)
    u = (plan.end - plan.start) / np.linalg.norm(plan.end - plan.start)
    assert np.degrees(np.arctan2(u[1], u[0])) == pytest.approx(180.0 - 30.0)   # −x turned 30° towards +y
    n = np.array([-u[1], u[0]])
    offset = (plan.start - p[1]) @ n          # the motion line, seen from the moved sphere
    to_close = 600 * UM - 2 * R
    expected = max(float(g.model.gap(min(to_close, g.d_max))), g.min_gap)
    assert abs(offset) == pytest.approx(expected)
    n_v = np.array([0.0, -1.0])              # normal of the line sphere 1 → sphere 0 (direction −x)
    assert np.sign((plan.start + g.behind * u - p[1]) @ n_v) == np.sign((robot - p[1]) @ n_v)  # robot's side
    assert (plan.start - p[1]) @ u == pytest.approx(-g.behind)


# --- how a pass is planned fast: the batched first stage, generated code, fewer starts, ties ---------------------
STUDY = (("pair", "assembly"), ("line", "assembly-3"), ("triangle", "assembly-3"), ("line", "assembly-4"))


def _assembly(pl: AssemblyPlanner, kind: str) -> list[tuple]:
    """The study layout assembled on the pass map itself, pass after pass (the benchmark's receding horizon):
    each pass with the IPOPT solves it took."""
    p, out = geometry(kind)["spheres"].copy(), []
    for _ in range(30):
        plan = pl.plan(p)
        out.append((plan, pl.profile["ipopt_solves"]))
        p = plan.predicted
        if pl.target.assembled(p):
            break
    return out


def _same_plans(got, want) -> None:
    assert len(got) == len(want)
    for (g, _), (w, _) in zip(got, want, strict=True):
        assert g.start == pytest.approx(w.start, abs=1e-9) and g.end == pytest.approx(w.end, abs=1e-9)
        assert g.cost == pytest.approx(w.cost, rel=1e-9) and g.solver == w.solver


@pytest.fixture(scope="module")
def study_assemblies():
    """Each study layout assembled by the default planner (generated code when a C compiler is found)."""
    out = {}
    for name, kind in STUDY:
        pl = AssemblyPlanner(arrangement(name, len(geometry(kind)["spheres"])))
        out[name, kind] = (pl, _assembly(pl, kind))
    return out


@pytest.mark.parametrize("compiled", [None, False])
def test_batched_sample_costs_are_the_per_sample_objective_and_the_bounds(compiled):
    """One mapped evaluation gives every sample's cost — the objective evaluated pass by pass — where the
    bounds are kept, and infinity exactly where :meth:`PlanLimits.violations` finds one broken (both paths)."""
    rng = np.random.default_rng(5)
    for name, kind in STUDY:
        base = geometry(kind)["spheres"].copy()
        pl = AssemblyPlanner(arrangement(name, len(base)), compiled=compiled)
        for k in range(3):
            p = base + (0.0 if k == 0 else 150 * UM) * rng.standard_normal(base.shape)
            mobility = 1.0 if k == 0 else rng.uniform(0.5, 1.5)
            cand, costs, ok = pl.sample_costs(p, mobility)
            assert cand.shape == (len(base) * 24 * 2 * 5, 2, 2)
            kept = pl.limits.violations(p, cand[:, 0], cand[:, 1]) <= assembly_planner.FEASIBLE_TOL
            assert ok.tolist() == kept.tolist() and kept.any()
            assert np.isinf(costs[~ok]).all()
            each = np.array([pl.cost(p, c[0], c[1], mobility) for c in cand[ok]])
            assert costs[ok] == pytest.approx(each, rel=1e-12, abs=1e-12)
            # the samples: round every sphere at the sampled gaps, 2 mm long
            for c in cand[:: 37]:
                mid = (c[0] + c[1]) / 2
                assert np.linalg.norm(c[1] - c[0]) == pytest.approx(2 * pl.behind)
                assert np.min(np.abs(np.linalg.norm(mid - p, axis=1)[:, None] - pl.sample_gaps)) < 1e-12


@pytest.mark.skipif(assembly_planner.c_compiler() is None, reason="no C compiler: only casadi's virtual machine")
@pytest.mark.parametrize("name, kind", STUDY)
def test_the_generated_code_plans_what_casadi_itself_plans(name, kind, study_assemblies):
    pl, compiled = study_assemblies[name, kind]
    assert pl.compiled
    plain = AssemblyPlanner(pl.target, compiled=False)
    assert not plain.compiled
    _same_plans(compiled, _assembly(plain, kind))


def test_every_start_is_refined_and_the_study_layouts_assemble(study_assemblies):
    """Each plan refines all its ``starts`` samples with IPOPT; the pair, the line of three and the triangle
    assemble on the pass map within the 30-pass budget (the four in a line may use all 30)."""
    for (name, _), (pl, passes) in study_assemblies.items():
        assert all(solves == pl.starts for _, solves in passes)
        assert len(passes) <= 30
        if name != "line" or pl.target.n < 4:
            assert pl.target.assembled(passes[-1][0].predicted), name


def test_costs_equal_but_for_rounding_rank_in_sample_order():
    costs = np.array([3.0, 1.0 + 2e-16, 1.0, 2.0, 1.0 + 4e-16, 0.5])
    assert AssemblyPlanner.ranked(costs).tolist() == [5, 1, 2, 4, 3, 0]
    assert np.argsort(costs).tolist()[1:4] != [1, 2, 4]           # what rounding alone would have put first
    big = np.array([1e3 * (1 + 1e-15), 1e3, 1e3 * (1 + 1e-6)])
    assert AssemblyPlanner.ranked(big).tolist() == [0, 1, 2]


def test_the_pairs_mirrored_samples_tie_and_the_first_sampled_leads(study_assemblies):
    """The pair's layout is symmetric about the line through its centres: its best samples come in mirrored
    pairs of equal cost (to rounding), and the planner refines the first sampled of each pair first."""
    pl, _ = study_assemblies["pair", "assembly"]
    p = geometry("assembly")["spheres"].copy()
    cand, costs, ok = pl.sample_costs(p)
    idx = np.flatnonzero(ok)
    order = idx[pl.ranked(costs[idx])]
    lead, second = order[:2]
    assert costs[second] == pytest.approx(costs[lead], rel=1e-12) and lead < second
    mirror = cand[second].copy()
    mirror[:, 1] = 2 * p[0, 1] - mirror[:, 1]
    assert mirror == pytest.approx(cand[lead], abs=1e-12)


def test_the_generated_code_is_built_once_into_the_cache(tmp_path, monkeypatch):
    """Built under ``$MAGCTL_CACHE/casadi``, keyed by a hash of the source; a second planner loads it. With a
    compiler that fails (a warning) or none, the planner keeps casadi's virtual machine; ``compiled=True`` then
    says why it cannot."""
    monkeypatch.setenv("MAGCTL_CACHE", str(tmp_path))
    target = arrangement("pair")
    if assembly_planner.c_compiler() is not None:
        first = AssemblyPlanner(target)
        libs = sorted((tmp_path / "casadi").iterdir())
        assert first.compiled and len(libs) == 1 and libs[0].suffix == ".so"
        stamp = libs[0].stat().st_mtime_ns
        assert AssemblyPlanner(target).compiled
        assert sorted((tmp_path / "casadi").iterdir()) == libs and libs[0].stat().st_mtime_ns == stamp
    monkeypatch.setenv("MAGCTL_CACHE", str(tmp_path / "other"))
    monkeypatch.setattr(assembly_planner, "c_compiler", lambda: "/bin/false")   # a compiler that fails
    with pytest.warns(RuntimeWarning, match="did not build"):
        assert not AssemblyPlanner(target).compiled
    assert not (tmp_path / "other" / "casadi").exists() or not any((tmp_path / "other" / "casadi").iterdir())
    monkeypatch.setattr(assembly_planner, "c_compiler", lambda: None)
    assert not AssemblyPlanner(target).compiled
    with pytest.raises(MagctlError, match="compiled=True"):
        AssemblyPlanner(target, compiled=True)


# --- the block --------------------------------------------------------------------------------------------------
def test_the_block_learns_a_slow_slide_from_the_passes_it_measures():
    """Measured displacements at half the predicted ones pull the mobility towards 0.5 (least squares)."""
    block = PassPlanner(arrangement("pair"))
    st = block.initial_state(2)
    p = np.array([[[2e-3, 1.8e-3], [2.6e-3, 1.8e-3]]] * 2)
    robot = np.array([[1e-3, 1.8e-3]] * 2)
    st = block.update_where(st, {"spheres": p, "robot": robot}, np.array([True, False]))
    assert np.isfinite(st["start"][0]).all() and np.isnan(st["start"][1]).all()
    assert st["passes"].tolist() == [1, 0]
    for _ in range(6):
        half = st["before"] + 0.5 * (st["predicted"] - st["before"])
        st = block.update_where(st, {"spheres": np.where(np.isnan(half), p, half), "robot": robot},
                                np.array([True, False]))
    assert 0.5 <= st["mobility"][0] < 0.65
    assert st["mobility"][1] == 1.0


def test_the_block_refuses_an_unknown_planner():
    with pytest.raises(MagctlError, match="planner"):
        PassPlanner(arrangement("pair"), planner="annealing")
