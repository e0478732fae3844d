"""The stand-in plant's sphere rules against the paper's numbers (eq 22, §IV-D)."""

from __future__ import annotations

import numpy as np
import pytest

from magctl.core.random import TrialStreams
from magctl.plant.standin import StandinSpheres

UM = 1e-6


def run(block, path, seed=0):
    """Step the block along a robot path ``(T, 2)``; returns sphere 0's position after each step."""
    state = block.initial_state(1, TrialStreams.for_block(seed, [0], "spheres"))
    out = []
    for r in path:
        state = block.update(state, {"position": np.array([r]), "heading": np.zeros(1), "velocity": np.zeros((1, 2))})
        out.append(state["s"][0, 0].copy())
    return np.array(out)


@pytest.mark.parametrize("gap_um", [300.0, 400.0, 600.0])
def test_a_straight_side_pass_displaces_the_sphere_by_eq_22(gap_um):
    block = StandinSpheres("spheres", [[0.0, gap_um * UM]], 250 * UM, side_range=800 * UM,
                           start_robot=(-2e-3, 0.0))
    path = np.stack([np.linspace(-2e-3, 2e-3, 201), np.zeros(201)], axis=1)
    s = run(block, path)
    expected = 1755 * np.exp(-0.009042 * gap_um) * UM  # eq 22, D_s in µm with D_g in µm
    np.testing.assert_allclose(s[-1], [expected, gap_um * UM], rtol=1e-12, atol=1e-15)


def test_no_displacement_beyond_the_side_range():
    block = StandinSpheres("spheres", [[0.0, 900 * UM]], 250 * UM, side_range=800 * UM, start_robot=(-2e-3, 0.0))
    path = np.stack([np.linspace(-2e-3, 2e-3, 201), np.zeros(201)], axis=1)
    np.testing.assert_array_equal(run(block, path)[-1], [0.0, 900 * UM])


@pytest.mark.parametrize("offset", [(0.0, 0.0), (1.0e-3, 1.8e-3), (3.7e-3, -2.1e-3)])
def test_retreating_robot_pulls_the_sphere_by_the_release_distance(offset):
    """Wherever the scene is: a sphere following the retreating robot sits at contact distance up to
    rounding, which must neither count as a new contact nor cut the release short."""
    contact = 250 * UM
    o = np.asarray(offset)
    block = StandinSpheres("spheres", [o + (1e-3, 0.0)], contact, release_mean=300 * UM, release_std=75 * UM,
                           start_robot=o)
    push = np.stack([np.linspace(0.0, 1.2e-3, 61), np.zeros(61)], axis=1)
    back = np.stack([np.linspace(1.2e-3, 0.2e-3, 51)[1:], np.zeros(50)], axis=1)
    s = run(block, np.concatenate([push, back]) + o, seed=3) - o
    after_push = s[60]
    assert after_push[0] == pytest.approx(1.2e-3 + contact, rel=1e-9)
    pulled = after_push[0] - s[-1][0]
    # the draw of the step when the retreat started: N(300, 75²) µm
    streams = TrialStreams.for_block(3, [0], "spheres")
    draws = [streams.standard_normal(())[0] for _ in range(62)]
    assert pulled == pytest.approx(300 * UM + 75 * UM * draws[61], rel=1e-9)
