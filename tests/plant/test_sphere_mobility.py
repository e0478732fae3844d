"""The mean sphere mobility ``models/sphere.toml [variability] mobility_ratio`` (SphereParams.mobility).

A sphere's velocity is ``min(k(δ)·m, 1)·U`` (eq 4 with the per-sphere multiplier ``m``), so to first order the
side-push displacement D_s (Fig 6) is proportional to ``m``. It is not exactly proportional: the passing
robot pushes the sphere up to ~22 µm away from its line (at D_g = 450 µm, default oil layer) into weaker
flow (decay length 1/b ≈ 110 µm, eq 22), and a less mobile sphere strays less, so it sees relatively more flow:
``D_s(m)/m`` grows as ``m`` falls, up to the linear response of a sphere that does not move the flow it sees.
The excursion lowers the flow by at most ``exp(−b·22 µm) ≈ 0.82``, so at ``m = 0.5`` the ratio of displacements
lies between 0.5 (linear) and ``0.5 / 0.82 ≈ 0.61``.
"""

import dataclasses

import numpy as np
import pytest

from magctl.core.errors import ParameterError
from magctl.plant.fluid.params import sphere_params
from magctl.plant.fluid.scenarios import sidepush_curve
from magctl.plant.sphere import Spheres

GAPS = np.array([400e-6, 450e-6, 500e-6])


def test_default_mobility_is_one_and_reproduces_the_model():
    sp = sphere_params()
    assert sp.mobility == 1.0
    default = sidepush_curve(GAPS)
    same = sidepush_curve(GAPS, params=dataclasses.replace(sp, mobility=1.0))
    np.testing.assert_array_equal(same.displacement, default.displacement)


def test_half_mobility_halves_the_side_push_within_the_excursion_band():
    sp = sphere_params()
    full = sidepush_curve(GAPS, params=sp)
    half = sidepush_curve(GAPS, params=dataclasses.replace(sp, mobility=0.5))
    ratio = half.displacement[1] / full.displacement[1]          # D_g = 450 µm
    assert 0.5 < ratio < 0.61, ratio
    # the less mobile sphere strays less from its line (the excursion argument above)
    assert 0.5 * full.across[1] < half.across[1] < 0.61 * full.across[1]
    assert not half.contact.any() and not full.contact.any()


def test_initial_state_starts_at_the_mean_mobility():
    sp = dataclasses.replace(sphere_params(), mobility=0.7, release_scatter=0.0, sticky_probability=0.0)
    block = Spheres(np.zeros((2, 2)) + [[0.0, 0.0], [1e-3, 0.0]], params=sp)
    state = block.initial_state(3)
    np.testing.assert_array_equal(state["mobility"], np.full((3, 2), 0.7))


def test_mobility_must_be_positive(tmp_path):
    from magctl.config import load_file, models_dir

    text = (models_dir() / "sphere.toml").read_text()
    assert "mobility_ratio = { value = 1.0" in text
    bad = tmp_path / "sphere.toml"
    bad.write_text(text.replace("mobility_ratio = { value = 1.0", "mobility_ratio = { value = 0.0"))
    with pytest.raises(ParameterError, match=r"sphere\.toml: variability\.mobility_ratio"):
        sphere_params(load_file(bad))
