"""The sphere frame's kernel (magctl.plant.sphere_kernel), the block's only implementation, against the numpy
array form it replaced (``RefSpheres``, tests/reference/plant_blocks.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from reference import reference_of

import magctl.loops
from magctl.core.units import UM
from magctl.plant.fluid import wall_drag
from magctl.plant.fluid.bispherical import stagnation_flow
from magctl.plant.fluid.params import sphere_params
from magctl.plant.sphere import Spheres
from magctl.plant.sphere_kernel import accurate_state, wall_functions
from magctl.studies.release_calibration import in_task_release

MODES = ("paper", "accurate")


def _random_frame(block: Spheres, batch: int, seed: int, spread: float = 1.0e-3):
    """Sphere states round a robot at the origin: many touching its footprint or each other, some lifted."""
    rng = np.random.default_rng(seed)
    state = block.initial_state(batch)
    foot = block.footprint
    # half the spheres start on or just outside a footprint vertex (contact), the rest anywhere near
    vertex = foot[rng.integers(len(foot), size=(batch, block.n))]
    near_edge = vertex + rng.normal(0.0, 60 * UM, size=(batch, block.n, 2))
    anywhere = rng.uniform(-spread, spread, size=(batch, block.n, 2))
    state["xy"] = np.where(rng.random((batch, block.n, 1)) < 0.5, near_edge, anywhere)
    state["gap"] = np.where(rng.random((batch, block.n)) < 0.2, rng.uniform(0, 300e-9, (batch, block.n)), 0.0)
    state["mobility"] = rng.lognormal(0.0, 0.3, (batch, block.n))
    speed = rng.uniform(0, 1e-3, batch)
    direction = rng.uniform(-np.pi, np.pi, batch)
    u = {"position": rng.normal(0, 20 * UM, (batch, 2)), "heading": rng.uniform(-np.pi, np.pi, batch),
         "velocity": np.column_stack([speed * np.cos(direction), speed * np.sin(direction)])}
    return state, u


def _both_forms(block: Spheres, state, u):
    """One frame by the array form (the reference) and by the block (its kernel), from copies of the same
    state."""
    reference = reference_of(block).update({k: v.copy() for k, v in state.items()}, u)
    compiled = block.update({k: v.copy() for k, v in state.items()}, u)
    return reference, compiled


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("n_spheres", [1, 3])
def test_compiled_frame_matches_the_array_form(mode, n_spheres):
    """Same frame, same numbers in either drag mode: positions to 1e-15 m, gaps to 1e-18 m,
    identical contact flags, over trials that push, lift, collide and turn — lifted spheres
    included (the accurate mode's tabulated functions are compiled too)."""
    block = Spheres(np.zeros((n_spheres, 2)), drag_mode=mode)
    state, u = _random_frame(block, 400, seed=n_spheres)
    reference, compiled = _both_forms(block, state, u)
    assert reference["contact"].mean() > 0.3
    assert (state["gap"] > 0).sum() > 50 and (reference["gap"] > 0).sum() > 20    # lifted, before and after
    np.testing.assert_allclose(compiled["xy"], reference["xy"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"], reference["gap"], rtol=0, atol=1e-18)
    np.testing.assert_array_equal(compiled["contact"], reference["contact"])
    # the block's update (its kernel, trial by trial) is the kernel module's batch frame, sphere_frame
    from magctl.plant.sphere_kernel import sphere_frame

    xy = np.array(state["xy"], float).reshape(len(state["xy"]), -1)
    gap = state["gap"].copy()
    pos, vel = (u[k][:, 0] + 1j * u[k][:, 1] for k in ("position", "velocity"))
    turn = np.cos(u["heading"]) + 1j * np.sin(u["heading"])
    contact = sphere_frame(xy, gap, state["mobility"], pos, vel, turn, *block._frame_args(), block._wall)
    np.testing.assert_allclose(compiled["xy"], xy.reshape(compiled["xy"].shape), rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"], gap, rtol=0, atol=1e-18)
    np.testing.assert_array_equal(compiled["contact"], contact)


@pytest.mark.parametrize("mode", MODES)
def test_spheres_off_the_map_are_summed_directly(mode):
    """Beyond the 1.5 mm flow map the kernel sums the Stokeslets as the array form does, and the
    flow it finds there still moves the sphere, lifted or not."""
    block = Spheres(np.zeros((2, 2)), drag_mode=mode)
    state, u = _random_frame(block, 40, seed=5, spread=4e-3)
    off_map = (np.abs(state["xy"] - u["position"][:, None]).max(axis=-1) > 1.6e-3).any(axis=1)
    assert off_map.sum() > 20 and (state["gap"][off_map] > 0).any()
    reference, compiled = _both_forms(block, state, u)
    np.testing.assert_allclose(compiled["xy"], reference["xy"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"], reference["gap"], rtol=0, atol=1e-18)
    moved = np.abs(compiled["xy"] - state["xy"]).max(axis=(1, 2))
    assert (moved[off_map] > 1e-12).all()


def test_lifted_spheres_over_many_frames_in_the_accurate_mode():
    """Spheres lifted from the glass to a radius and more, driven for 20 frames in the accurate mode:
    every frame of the kernel follows the array form to 1e-15 m, while the gaps cross the
    table's whole range and the lower and upper blends (δ/a from below 2e-6 to above 67; a roughness
    ε of 10 pm lets the gap reach the near-contact expansions)."""
    block = Spheres(np.zeros((3, 2)), drag_mode="accurate", roughness=1e-11)
    state, u = _random_frame(block, 60, seed=17)
    rng = np.random.default_rng(17)
    ratio = rng.permutation(np.geomspace(2e-7, 300.0, state["gap"].size)).reshape(state["gap"].shape)
    state["gap"] = ratio * block.radius - block.roughness
    ratio = (state["gap"] + block.roughness) / block.radius
    assert (ratio < 2e-6).sum() > 5 and (ratio > 67).sum() > 5
    ref, comp = state, {k: v.copy() for k, v in state.items()}
    array_form = reference_of(block)
    for _ in range(20):
        ref = array_form.update(ref, u)
        comp = block.update(comp, u)
        np.testing.assert_allclose(comp["xy"], ref["xy"], rtol=0, atol=1e-15)
        # the gap within 1e-17 m: it reads the flow at centres that agree to 1e-15 m, and the lubrication's
        # Newton steps (exp and log) differ between numba's and numpy's maths by an ulp
        np.testing.assert_allclose(comp["gap"], ref["gap"], rtol=1e-13, atol=1e-17)
        np.testing.assert_array_equal(comp["contact"], ref["contact"])
    assert (np.abs(ref["xy"] - state["xy"]) > 1e-7).any()


# Brenner (1961), Table 1: λ at h/a = cosh α; Goldman, Cox & Brenner (1967b): F*_s (= f_s) at h/a
BRENNER_NORMAL = [(np.cosh(0.5), 9.2517663), (np.cosh(1.0), 3.0360641), (np.cosh(3.0), 1.1252465)]
GCB_SHEAR = [(3.7622, 1.1671), (1.5431, 1.4391), (1.1276, 1.6160), (1.005004, 1.6969)]


def test_compiled_wall_functions_equal_the_array_form():
    """The compiled accurate-mode functions against ``wall_drag`` at 2001 gaps 1e-4 ≤ δ/a ≤ 100
    (and 1e-8 … 1e4, through both blends and beyond the table) to 1e-12 relative, the free-sphere
    mobility and the vertical factors λ, g with them; and against published values: Brenner's
    (1961) λ and Goldman, Cox & Brenner's (1967b) shear force."""
    table = tuple(wall_drag.wall_table())
    out = np.empty(8)

    def compiled(d):
        got = np.empty((8, len(d)))
        for m, x in enumerate(d):
            wall_functions(x, table, out)
            got[:, m] = out
        return got

    d = np.concatenate([np.geomspace(1e-4, 100.0, 2001), np.geomspace(1e-8, 1e4, 301)])
    got = compiled(d)
    want = np.array([*wall_drag.accurate_coefficients(d), wall_drag.normal_resistance(d),
                     wall_drag.stagnation_factor(d)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    radius, eps = 105e-6, 25e-9
    gaps = radius * d[:2001]
    state = np.array([accurate_state(radius, g, eps, table, out) for g in gaps])
    lam, g_stag = wall_drag.normal_factors("accurate", radius, gaps, eps)
    np.testing.assert_allclose(state[:, 0], wall_drag.accurate_mobility(radius, gaps, eps), rtol=1e-12, atol=0)
    np.testing.assert_allclose(state[:, 1], lam, rtol=1e-12, atol=0)
    np.testing.assert_allclose(state[:, 2], g_stag, rtol=1e-12, atol=0)
    for h, lam_brenner in BRENNER_NORMAL:
        np.testing.assert_allclose(compiled([h - 1.0])[6, 0], lam_brenner, rtol=1e-6)
    for h, f_s in GCB_SHEAR:
        np.testing.assert_allclose(compiled([h - 1.0])[4, 0], f_s, atol=1.5e-4)


def test_closed_loop_release_identical_in_both_forms(monkeypatch):
    """Eight closed-loop front pushes in the accurate drag mode with a robot–sphere contact gap of 15.86 µm
    (in_task_release's argument), where spheres lift near the robot in more than 50 frames (asserted): the
    kernel and the array form give the same pull-back, overshoot, stop gap and retract per trial to 1e-12 m."""
    accurate = dataclasses.replace(sphere_params(), drag_mode="accurate")
    monkeypatch.setattr(magctl.loops, "sphere_params", lambda: accurate)
    monkeypatch.setenv("MAGCTL_ENGINE", "interpreted")   # Spheres.update: the kernel, then the reference
    lifted = []
    compiled_update = Spheres.update

    def counted(self, state, u):
        lifted.append(bool((state["gap"] > 0).any()))
        return compiled_update(self, state, u)

    monkeypatch.setattr(Spheres, "update", counted)
    fast = in_task_release(15.86e-6, trials=8)
    assert sum(lifted) > 50                     # frames with a lifted sphere, all by the kernel
    monkeypatch.setattr(Spheres, "update", lambda self, state, u: reference_of(self).update(state, u))
    slow = in_task_release(15.86e-6, trials=8)
    for name in ("pull_back", "overshoot", "stop_gap", "retract"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=0, atol=1e-12)
    # the accurate mode with its exact vertical law releases differently from the paper mode
    paper_mode = dataclasses.replace(sphere_params(), drag_mode="paper")
    monkeypatch.setattr(magctl.loops, "sphere_params", lambda: paper_mode)
    monkeypatch.setattr(Spheres, "update", compiled_update)
    paper = in_task_release(15.86e-6, trials=8)
    assert np.abs(paper.pull_back - fast.pull_back).max() > 1e-6


def test_kernel_uses_the_adhesion_and_substeps_of_the_parameters():
    """A changed parameter set reaches the kernel: adhesion P holds a sphere the flow would lift, and
    the sub-step count changes the path exactly as it does in the array form."""
    base = dataclasses.replace(sphere_params(), drag_mode="paper")   # eq 9: the flow lifts freely
    plain = Spheres(np.zeros((1, 2)), params=base)
    state, u = _random_frame(plain, 200, seed=11)
    default = plain.update({k: v.copy() for k, v in state.items()}, u)
    for params in (dataclasses.replace(base, adhesion=True), dataclasses.replace(base, substeps=7)):
        block = Spheres(np.zeros((1, 2)), params=params)
        reference, compiled = _both_forms(block, state, u)
        np.testing.assert_allclose(compiled["xy"], reference["xy"], rtol=0, atol=1e-15)
        np.testing.assert_allclose(compiled["gap"], reference["gap"], rtol=0, atol=1e-18)
        if params.adhesion:     # P keeps most spheres the flow lifts without it on the glass
            assert (compiled["gap"] > 0).sum() < 0.5 * (default["gap"] > 0).sum()
        else:
            assert np.abs(compiled["xy"] - default["xy"]).max() > 1e-9


def test_accurate_mode_vertical_law_same_in_kernel_and_arrays():
    """The accurate mode's gap balance is (g U_z − settling)/λ at (δ + ε)/R: from spheres all on the
    glass, some of which the flow lifts within the frame, the kernel and the array form give the same
    numbers; on the glass λ(ε/R) = 1/δ* − ln(δ*)/5 + 0.971
    (Cox & Brenner 1967), about 4200 at ε = 25 nm, and g is the exact stagnation-flow series."""
    paper = Spheres(np.zeros((2, 2)), drag_mode="paper")
    accurate = Spheres(np.zeros((2, 2)), drag_mode="accurate")
    state, u = _random_frame(accurate, 300, seed=13)
    state["gap"][:] = 0.0
    reference, compiled = _both_forms(accurate, state, u)
    assert (reference["gap"] > 0).any()                   # the flow lifts some spheres in the frame
    np.testing.assert_allclose(compiled["xy"], reference["xy"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"], reference["gap"], rtol=0, atol=1e-18)
    # the rate itself: eq 9 as printed in the paper mode, (g U_z − W_b/ζ)/λ in the accurate mode
    uz = np.array([[1e-3, -1e-3]])
    sink = accurate.buoyant_weight / accurate.zeta
    gap = np.zeros((1, 2))
    np.testing.assert_allclose(paper._gap_rate(uz, gap), uz - sink, rtol=1e-12)
    d = accurate.roughness / accurate.radius
    lam = 1 / d - 0.2 * np.log(d) + 0.971264
    g = float(stagnation_flow(d))
    np.testing.assert_allclose(accurate._gap_rate(uz, gap), (g * uz - sink) / lam, rtol=1e-6)
    # at h/a = cosh 1 the sphere feels Brenner's (1961) Table 1 value λ = 3.0360641
    d = 0.5430806348152437
    gap = np.full((1, 2), d * accurate.radius - accurate.roughness)
    g = float(stagnation_flow(d))
    np.testing.assert_allclose(accurate._gap_rate(uz, gap), (g * uz - sink) / 3.0360641, rtol=1e-6)


def test_the_lubrication_acts_in_the_compared_frames():
    """The frames compared above exercise the robot–sphere lubrication: with both laws cut off (the block's
    ``film_cutoff`` and ``edge_cutoff`` 0) the same frame ends elsewhere for many trials."""
    block = Spheres(np.zeros((1, 2)))
    state, u = _random_frame(block, 400, seed=1)
    with_film = block.update({k: v.copy() for k, v in state.items()}, u)
    dry = Spheres(np.zeros((1, 2)))
    dry.film_cutoff = dry.edge_cutoff = 0.0
    without = dry.update({k: v.copy() for k, v in state.items()}, u)
    moved = np.linalg.norm(with_film["xy"] - without["xy"], axis=-1).max(axis=-1)
    assert (moved > 1e-6).sum() > 20
