"""Fast paths of the batched closed loop against independent references.

The precomputed :class:`Polygon` against matplotlib's point-in-path test and a per-edge
scalar distance; the sphere block's batched update against running each trial alone.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.path import Path

from magctl.core.errors import ParameterError
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.outline import Polygon
from magctl.plant.sphere import Spheres

GEOM = RobotGeometry.from_params()
FOOT = GEOM.footprint
coord = st.floats(-400e-6, 400e-6)


def _segment_distance(p, a, b):
    """Scalar distance from point ``p`` to segment ``ab`` (textbook projection, no numpy)."""
    abx, aby = b[0] - a[0], b[1] - a[1]
    t = ((p[0] - a[0]) * abx + (p[1] - a[1]) * aby) / (abx * abx + aby * aby)
    t = min(max(t, 0.0), 1.0)
    return math.hypot(p[0] - (a[0] + t * abx), p[1] - (a[1] + t * aby))


@settings(max_examples=300, deadline=None)
@given(coord, coord)
def test_polygon_matches_independent_inside_test_and_edge_distance(x, y):
    poly = Polygon(FOOT)
    d_ref = min(_segment_distance((x, y), FOOT[k], FOOT[(k + 1) % len(FOOT)]) for k in range(len(FOOT)))
    dist, nx, ny = poly.distance(np.array([x]), np.array([y]))
    assert dist[0] == pytest.approx(d_ref, rel=1e-9, abs=1e-15)
    assert math.hypot(x - nx[0], y - ny[0]) == pytest.approx(d_ref, rel=1e-9, abs=1e-15)
    if d_ref > 1e-9:  # matplotlib's boundary convention differs from even-odd exactly on an edge
        assert bool(poly.contains(np.array([x]), np.array([y]))[0]) == Path(FOOT).contains_point((x, y))


def test_polygon_keeps_the_shape_of_the_query():
    poly = Polygon(FOOT)
    x = np.linspace(-3e-4, 3e-4, 12).reshape(3, 4)
    dist, nx, ny = poly.distance(x, x.T.reshape(3, 4))
    assert dist.shape == nx.shape == ny.shape == (3, 4)
    assert poly.contains(x, 0 * x).shape == (3, 4)


@pytest.mark.parametrize("bad", [np.zeros((2, 2)), np.zeros((5, 3)), np.zeros(6)])
def test_polygon_rejects_bad_vertices(bad):
    with pytest.raises(ParameterError, match="vertices"):
        Polygon(bad)


def test_sphere_update_of_a_trial_does_not_depend_on_the_batch():
    """Three trials in one batch (one pushing in contact, one lifted by the flow, one far away)
    give the same next state as each trial run alone."""
    block = Spheres(np.array([[0.0, 0.0], [6e-4, 0.0]]))
    state = block.initial_state(3)
    front = FOOT[:, 0].max()
    state["xy"] = np.array([[[front + 10e-6, 0.0], [front + 500e-6, 1e-4]],
                            [[front + 150e-6, 30e-6], [-8e-4, 0.0]],
                            [[3e-3, 3e-3], [-3e-3, 2e-3]]])
    state["gap"] = np.array([[0.0, 0.0], [2e-7, 0.0], [0.0, 0.0]])
    u = {"position": np.zeros((3, 2)), "heading": np.array([0.0, 0.3, -2.0]),
         "velocity": np.array([[4e-4, 0.0], [3e-4, 1e-4], [0.0, 4e-4]])}
    together = block.update({k: v.copy() for k, v in state.items()}, u)
    assert together["contact"][0]      # the pushing trial touched the robot
    for b in range(3):
        alone = block.update({k: v[b:b + 1].copy() for k, v in state.items()}, {k: v[b:b + 1] for k, v in u.items()})
        for key in ("xy", "gap", "contact"):
            np.testing.assert_array_equal(alone[key][0], together[key][b])
