"""eq 1-3: work of adhesion and JKR pull-off against closed forms and the paper's quoted range."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.core.errors import ParameterError
from magctl.plant.fluid.surface import jkr_pull_off, pull_off_range, work_of_adhesion, work_of_adhesion_pair

energy = st.floats(1e-3, 1.0)


@settings(deadline=None)
@given(energy, energy, energy)
def test_eq2_equals_the_factored_closed_form(g1, g2, g3):
    # eq 1 in eq 2 factorises: W132 = 2 (sqrt g1 - sqrt g3)(sqrt g2 - sqrt g3)
    expected = 2 * (np.sqrt(g1) - np.sqrt(g3)) * (np.sqrt(g2) - np.sqrt(g3))
    assert work_of_adhesion(g1, g2, g3) == pytest.approx(expected, rel=1e-9, abs=1e-15)


def test_same_medium_gives_no_adhesion_and_sign_conventions():
    assert work_of_adhesion(0.04, 0.08, 0.04) == pytest.approx(0.0, abs=1e-15)
    assert work_of_adhesion(0.033, 0.0834, 0.021) > 0          # attract
    assert work_of_adhesion(0.015, 0.0834, 0.021) < 0          # 1 between 2 and 3: repel


def test_jkr_hand_value():
    # P = 1.5 pi R W: R = 105 um, W = 10 mJ/m2 -> 4.948 uN
    assert jkr_pull_off(105e-6, 0.010) == pytest.approx(1.5 * np.pi * 105e-6 * 0.010)
    assert jkr_pull_off(105e-6, 0.010) * 1e6 == pytest.approx(4.948, abs=1e-3)


def test_paper_pull_off_range_for_r_105um():
    r = pull_off_range(105e-6)
    # paper §IV-A: 5.2 uN < P < 23 uN
    assert r.p_min * 1e6 == pytest.approx(5.2, abs=0.06)
    assert r.p_max * 1e6 == pytest.approx(23.0, abs=0.1)
    assert r.p_min < r.p_max


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="radius"):
        jkr_pull_off(-1e-6, 0.01)
    with pytest.raises(ValueError, match="non-negative"):
        work_of_adhesion_pair(-0.01, 0.02)


def test_bad_material_file(tmp_path):
    from magctl.config import load_file

    bad = tmp_path / "materials.toml"
    bad.write_text('[polystyrene]\nsurface_energy_mJ_m2 = { value = -3.0, source = "x" }\n'
                   '[glass]\nsurface_energy_min_mJ_m2 = { value = 80.0, source = "x" }\n'
                   'surface_energy_max_mJ_m2 = { value = 90.0, source = "x" }\n'
                   '[silicone_oil]\nsurface_energy_min_mJ_m2 = { value = 20.0, source = "x" }\n'
                   'surface_energy_max_mJ_m2 = { value = 21.0, source = "x" }\n')
    with pytest.raises(ParameterError, match="surface energies"):
        pull_off_range(105e-6, load_file(bad))
