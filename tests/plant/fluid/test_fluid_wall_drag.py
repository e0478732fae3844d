"""eq 4-5 as printed, and the accurate near-wall mode against published tables."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.plant.fluid.wall_drag import (
    accurate_coefficients,
    accurate_mobility,
    far_coefficients,
    mobility,
    paper_coefficients,
    paper_force,
    paper_mobility,
    paper_rotation_ratio,
)

R, EPS = 105e-6, 25e-9


def test_paper_coefficients_by_hand_at_contact():
    # delta = 0: ln(eps/R) = ln(25e-9/105e-6) = -8.3428
    lg = np.log(25e-9 / 105e-6)
    fs, ft, fr = paper_coefficients(R, 0.0, EPS)
    assert fs == pytest.approx(1 + 0.7005 * 105 / (105 + 0.025))
    assert ft == pytest.approx(8 / 15 * lg - 0.9588)
    assert fr == pytest.approx(-2 / 15 * lg - 0.2526)
    assert ft == pytest.approx(-5.4083, abs=1e-3)
    assert fr == pytest.approx(0.8598, abs=1e-3)


def test_paper_bounds_as_printed():
    fs, ft, fr = paper_coefficients(R, 5 * R, EPS)
    assert ft == -1.0 and fr == 0.0
    h = np.array([R * 1.0001, 3 * R, 30 * R])
    w = paper_rotation_ratio(R, h)
    assert np.all((w >= 0) & (w <= 0.5676))
    # eq 5 at R/h = 1: -2.375e-6 e^12.05 + 1.025 e^-0.1438
    assert paper_rotation_ratio(R, R) == pytest.approx(-2.375e-6 * np.exp(12.05) + 1.025 * np.exp(-0.1438))


@settings(deadline=None)
@given(st.floats(0, 50e-6), st.floats(-1e-3, 1e-3))
def test_paper_mobility_zeroes_the_force(gap, u):
    k = paper_mobility(R, gap, EPS)
    f = paper_force(R, 0.019, np.array([u, 0.0]), np.array([k * u, 0.0]), gap, EPS)
    assert abs(f[0]) <= 1e-12 * max(abs(u), 1e-12) * 6 * np.pi * 0.019 * R + 1e-30


# Goldman, Cox & Brenner (1967b): sphere fixed in wall shear flow, F*_s at h/a
GCB_SHEAR = [(10.0677, 1.0587), (3.7622, 1.1671), (2.3524, 1.2780), (1.5431, 1.4391), (1.1276, 1.6160),
             (1.0453, 1.6682), (1.005004, 1.6969), (1.003202, 1.6982)]


@pytest.mark.parametrize("ha, fs", GCB_SHEAR)
def test_accurate_shear_force_matches_gcb_table(ha, fs):
    assert accurate_coefficients(ha - 1.0)[4] == pytest.approx(fs, rel=0.02)


@pytest.mark.parametrize("ha, ft", [(10.0677, -1.0591), (3.7622, -1.1738), (2.3524, -1.3079)])
def test_accurate_translation_matches_oneill(ha, ft):
    assert accurate_coefficients(ha - 1.0)[0] == pytest.approx(ft, rel=0.005)


def test_accurate_mode_limits():
    # far field: Faxen's 1 - 9/16 a/h (+...) for translation, 1 + 9/16 a/h for the shear force
    d = np.array([40.0, 100.0])
    for a, b in zip(accurate_coefficients(d), far_coefficients(d), strict=True):
        assert np.allclose(a, b)
    # near contact: Goldman, Cox & Brenner lubrication (F*_t = 8/15 ln(d) - 0.9588)
    d = 1e-3
    assert accurate_coefficients(d)[0] == pytest.approx(8 / 15 * np.log(d) - 0.9588)
    # a free sphere far from the wall moves with the fluid
    assert accurate_mobility(R, 200 * R, EPS) == pytest.approx(1.0, abs=0.01)


def test_accurate_mode_is_smooth():
    d = np.geomspace(1e-4, 50, 400)
    for c in accurate_coefficients(d):
        jumps = np.abs(np.diff(c))
        assert jumps.max() < 0.05


def test_modes_agree_at_contact_and_bad_mode():
    # at rest on the glass both give V/U ~ 0.34 (eq 4-5 vs exact lubrication)
    assert mobility("paper", R, 0.0, EPS) == pytest.approx(mobility("accurate", R, 0.0, EPS), rel=0.03)
    with pytest.raises(ValueError, match="drag mode"):
        mobility("comsol", R, 0.0, EPS)
    with pytest.raises(ValueError, match="gap"):
        paper_coefficients(R, -1e-6, EPS)


@pytest.mark.parametrize("ha, fs", GCB_SHEAR)
def test_paper_shear_coefficient_against_gcb_table(ha, fs):
    # eq 4's F*_shear = 1 + 0.7005 R/h, with h = R + delta + eps, against Goldman, Cox & Brenner (1967b)
    gap = (ha - 1.0) * R - EPS
    if gap < 0:
        pytest.skip("gap below the roughness")
    assert paper_coefficients(R, gap, EPS)[0] == pytest.approx(fs, rel=0.02)
