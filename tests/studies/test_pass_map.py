"""The pass map (models/pass_map.toml): regenerated from the plant, and against the plant's own passes."""

from __future__ import annotations

import numpy as np
import pytest

from magctl.control.pass_model import PassMap, pass_map
from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.plant.fluid.scenarios import sidepush_curve
from magctl.studies import pass_map as PM


def test_stored_map_is_what_the_plant_gives_now():
    """The identification is deterministic: rerun it and compare with the stored table (4 decimals in µm)."""
    fresh = PM.identify()
    stored = pass_map()
    assert stored.positions == pytest.approx(fresh["positions_um"] * UM)
    assert stored.gaps == pytest.approx(fresh["gaps_um"] * UM)
    assert stored.along == pytest.approx(fresh["along_um"] * UM, abs=1e-10)
    assert stored.away == pytest.approx(fresh["away_um"] * UM, abs=1e-10)


@pytest.mark.parametrize("behind_um, ahead_um", [(1000, 1000), (600, 1500), (1500, 300)])
def test_a_pass_read_from_the_map_is_the_pass_itself(behind_um, ahead_um):
    """Superposition along the path against a separate simulation of the pass (Fig 6's scenario, shifted so the
    robot runs from ``−behind`` to ``ahead``): within 7 % of the displacement or 0.5 µm, beyond the contact bound.
    (Superposing the pass's profile is exact for the flow alone; the face film within a radius of the robot makes
    the sphere's motion depend on where it already is, which costs up to 6 % at 370-390 µm.)"""
    gaps = np.array([390.0, 490.0, 700.0, 1200.0]) * UM
    m = pass_map()
    for g in gaps:
        pred = m.displacement(np.array([[0.0, g]]), np.array([-behind_um * UM, 0.0]), np.array([ahead_um * UM, 0.0]))
        travel = (behind_um + ahead_um) / 2 * UM
        # sidepush_curve runs −travel → +travel past a sphere at x = 0: shift the sphere instead of the robot
        shift = (ahead_um - behind_um) / 2 * UM
        direct = _pass(g, shift, travel)
        assert pred[0, 0] == pytest.approx(direct[0], rel=0.07, abs=0.5 * UM)
        assert pred[0, 1] == pytest.approx(direct[1], rel=0.05, abs=0.5 * UM)   # across: ≤ 2 µm, film-bent


def _pass(gap, shift, travel):
    """Displacement (along, away) of a sphere at (−shift, gap) when the robot runs −travel → +travel along x."""
    from magctl.plant.fluid.scenarios import _run, _spheres

    block = _spheres(np.array([[[-shift, gap]]]))
    step = 0.4e-3 * block.dt
    n = int(np.ceil(2 * travel / step))
    pos = np.zeros((n, 1, 2))
    pos[:, 0, 0] = -travel - shift + step * np.arange(n)   # robot relative to the sphere as in the map
    pos[:, 0, 0] += shift                                  # back to the lab frame
    vel = np.zeros((n, 1, 2))
    vel[:, :, 0] = 0.4e-3
    path, _ = _run(block, 1, pos, 0.0, vel)
    d = path[-1, 0, 0] - path[0, 0, 0]
    return d


def test_the_map_reads_fig6_as_the_side_push_curve_does():
    gaps = np.array([370.0, 450.0, 600.0, 900.0]) * UM
    # within 5 %: the face film makes the superposed profile differ from one whole pass near the bound
    assert pass_map().side_curve(gaps) == pytest.approx(sidepush_curve(gaps).along, rel=0.05)


def test_mirror_image_sphere_moves_the_same_along_and_opposite_across():
    m = pass_map()
    a, b = np.array([0.0, 0.0]), np.array([2.4e-3, 0.9e-3])
    n = np.array([-0.9e-3, 2.4e-3]) / np.hypot(2.4e-3, 0.9e-3)
    u = (b - a) / np.linalg.norm(b - a)
    c = a + 1.1e-3 * u
    up, down = c + 500 * UM * n, c - 500 * UM * n
    d = m.displacement(np.stack([up, down]), a, b)
    assert d[0] @ u == pytest.approx(d[1] @ u, rel=1e-9)
    assert d[0] @ n == pytest.approx(-(d[1] @ n), rel=1e-9)
    assert d[0] @ u > 10 * UM        # a pass at 500 µm moves the sphere ≈ 20 µm (Fig 6, eq 22: 19 µm)


def test_a_malformed_map_is_refused():
    m = pass_map()
    with pytest.raises(MagctlError, match="increase"):
        PassMap(m.positions[::-1], m.gaps, m.along, m.away, m.min_gap)
    bad = m.along.copy()
    bad[3, 4] = np.nan
    with pytest.raises(MagctlError, match="finite"):
        PassMap(m.positions, m.gaps, bad, m.away, m.min_gap)
