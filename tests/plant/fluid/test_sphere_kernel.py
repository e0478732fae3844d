"""The compiled sphere frame against the array form it replaces (magctl.plant.sphere_kernel)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magctl.plant.fluid.bispherical import stagnation_flow
from magctl.plant.fluid.params import sphere_params
from magctl.plant.sphere import Spheres

UM = 1e-6


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


@pytest.mark.parametrize("n_spheres", [1, 3])
def test_compiled_frame_matches_the_array_form(n_spheres):
    """Same frame, same numbers: positions to 1e-15 m, gaps to 1e-18 m, identical contact flags,
    over trials that push, lift, collide and turn."""
    block = Spheres(np.zeros((n_spheres, 2)))
    state, u = _random_frame(block, 400, seed=n_spheres)
    reference = block._update_arrays({k: v.copy() for k, v in state.items()}, u)
    compiled, covered = block.compiled_frame({k: v.copy() for k, v in state.items()}, u)
    assert covered.mean() > 0.95                 # the kernel did the work, not the fallback
    assert reference["contact"][covered].mean() > 0.3
    assert (reference["gap"][covered] > 0).any()
    np.testing.assert_allclose(compiled["xy"][covered], reference["xy"][covered], rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"][covered], reference["gap"][covered], rtol=0, atol=1e-18)
    np.testing.assert_array_equal(compiled["contact"][covered], reference["contact"][covered])
    # and the block's own update (kernel plus fallback) equals the array form on every trial
    full = block.update({k: v.copy() for k, v in state.items()}, u)
    np.testing.assert_allclose(full["xy"], reference["xy"], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(full["contact"], reference["contact"])


def test_spheres_off_the_map_are_summed_directly():
    """Beyond the 1.5 mm flow map the kernel sums the Stokeslets as the array form does, and the
    flow it finds there still moves the sphere."""
    block = Spheres(np.zeros((2, 2)))
    state, u = _random_frame(block, 40, seed=5, spread=4e-3)
    off_map = (np.abs(state["xy"] - u["position"][:, None]).max(axis=-1) > 1.6e-3).any(axis=1)
    assert off_map.sum() > 20
    reference = block._update_arrays({k: v.copy() for k, v in state.items()}, u)
    compiled, covered = block.compiled_frame({k: v.copy() for k, v in state.items()}, u)
    assert covered.all()
    np.testing.assert_allclose(compiled["xy"], reference["xy"], rtol=0, atol=1e-15)
    moved = np.abs(compiled["xy"] - state["xy"]).max(axis=(1, 2))
    assert (moved[off_map] > 1e-12).all()


def test_kernel_hands_back_lifted_spheres_in_the_accurate_mode():
    """The accurate drag mode's tabulated mobility is not compiled: a trial with a lifted sphere is
    left for the array form (its row returned untouched) and the block's update still gives the
    array form's numbers."""
    block = Spheres(np.zeros((1, 2)), drag_mode="accurate")
    state, u = _random_frame(block, 3, seed=7, spread=3e-4)
    u["velocity"] *= 0.05           # a slow robot: its flow lifts no sphere off the glass in this frame
    state["gap"][:] = 0.0
    state["gap"][1] = 1e-7
    before = state["xy"].copy()
    new, covered = block.compiled_frame(state, u)
    assert covered.tolist() == [True, False, True]
    np.testing.assert_array_equal(new["xy"][1], before[1])
    full = block.update(state, u)
    reference = block._update_arrays(state, u)
    np.testing.assert_array_equal(full["xy"][1], reference["xy"][1])
    np.testing.assert_allclose(full["xy"], reference["xy"], rtol=0, atol=1e-15)


def test_kernel_uses_the_adhesion_and_substeps_of_the_parameters():
    """A changed parameter set reaches the kernel: adhesion P holds a sphere the flow would lift, and
    the sub-step count changes the path exactly as it does in the array form."""
    plain = Spheres(np.zeros((1, 2)))
    state, u = _random_frame(plain, 200, seed=11)
    default = plain.compiled_frame({k: v.copy() for k, v in state.items()}, u)[0]
    for params in (dataclasses.replace(sphere_params(), adhesion=True),
                   dataclasses.replace(sphere_params(), substeps=7)):
        block = Spheres(np.zeros((1, 2)), params=params)
        reference = block._update_arrays({k: v.copy() for k, v in state.items()}, u)
        compiled, covered = block.compiled_frame({k: v.copy() for k, v in state.items()}, u)
        assert covered.mean() > 0.95
        np.testing.assert_allclose(compiled["xy"][covered], reference["xy"][covered], rtol=0, atol=1e-15)
        np.testing.assert_allclose(compiled["gap"][covered], reference["gap"][covered], rtol=0, atol=1e-18)
        if params.adhesion:     # P keeps most spheres the flow lifts without it on the glass
            assert (compiled["gap"] > 0).sum() < 0.5 * (default["gap"] > 0).sum()
        else:
            assert np.abs(compiled["xy"] - default["xy"]).max() > 1e-9


def test_accurate_mode_vertical_law_same_in_kernel_and_arrays():
    """The accurate mode's gap balance is (g U_z − settling)/λ at (δ + ε)/R: the kernel (spheres on the
    glass) and the array form give the same numbers; on the glass λ(ε/R) = 1/δ* − ln(δ*)/5 + 0.971
    (Cox & Brenner 1967), about 4200 at ε = 25 nm, and g is the exact stagnation-flow series."""
    paper = Spheres(np.zeros((2, 2)))
    accurate = Spheres(np.zeros((2, 2)), drag_mode="accurate")
    state, u = _random_frame(accurate, 300, seed=13)
    state["gap"][:] = 0.0
    reference = accurate._update_arrays({k: v.copy() for k, v in state.items()}, u)
    compiled, covered = accurate.compiled_frame({k: v.copy() for k, v in state.items()}, u)
    assert covered.mean() > 0.5 and (~covered).any()      # some trials lift a sphere and go back
    np.testing.assert_allclose(compiled["xy"][covered], reference["xy"][covered], rtol=0, atol=1e-15)
    np.testing.assert_allclose(compiled["gap"][covered], reference["gap"][covered], rtol=0, atol=1e-18)
    full = accurate.update({k: v.copy() for k, v in state.items()}, u)
    np.testing.assert_allclose(full["gap"], reference["gap"], rtol=0, atol=1e-18)
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
