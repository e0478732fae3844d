"""Contact geometry: frame transforms, non-penetration against the star outline (the array form's push-out,
``tests/reference/plant_blocks.py``; the kernel is checked against that form), sphere separation."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.plant_blocks import push_out_of_outline

from magctl.plant.fluid.geometry import RobotGeometry, points_in_polygon, polygon_distance
from magctl.plant.sphere import separate_spheres, to_body, to_world

R = 105e-6
GEOM = RobotGeometry.from_params()
coord = st.floats(-600e-6, 600e-6)


@settings(deadline=None)
@given(coord, coord, st.floats(-np.pi, np.pi), coord, coord)
def test_body_frame_round_trip(x, y, heading, px, py):
    pts = np.array([[[x, y]]])
    origin = np.array([[px, py]])
    rel = to_body(pts, origin, np.array([heading]))
    back = origin[:, None, :] + to_world(rel, np.array([heading]))
    assert np.allclose(back, pts, atol=1e-15)
    assert np.isclose(np.linalg.norm(rel), np.linalg.norm(pts - origin[:, None, :]))


@settings(max_examples=200, deadline=None)
@given(coord, coord)
def test_pushed_out_spheres_do_not_overlap_the_outline(x, y):
    fixed, touched = push_out_of_outline(np.array([[x, y]]), GEOM.footprint, R, iterations=6)
    dist, _ = polygon_distance(fixed, GEOM.footprint)
    assert not points_in_polygon(fixed, GEOM.footprint)[0]
    assert dist[0] >= R * (1 - 1e-6) - 1e-9
    if touched[0]:
        assert np.linalg.norm(fixed - [x, y]) > 0


def test_sphere_in_the_concave_face_touches_both_sides():
    # a sphere pushed deep into the notch settles where it touches the arc, centred on the axis
    fixed, touched = push_out_of_outline(np.array([[100e-6, 0.0]]), GEOM.footprint, R, iterations=6)
    assert touched[0] and abs(fixed[0, 1]) < 1e-9
    front = GEOM.footprint[:, 0].max()
    assert fixed[0, 0] < front + R          # it sits inside the notch, not in front of the face


@settings(deadline=None)
@given(st.lists(st.tuples(coord, coord), min_size=2, max_size=5))
def test_separated_spheres_do_not_overlap(points):
    xy = np.array(points)[None] * 0.3
    out = separate_spheres(xy, R, iterations=30)
    n = xy.shape[1]
    i, j = np.triu_indices(n, 1)
    d = np.linalg.norm(out[0, i] - out[0, j], axis=-1)
    coincident = np.linalg.norm(xy[0, i] - xy[0, j], axis=-1) == 0
    assert np.all((d >= 2 * R * (1 - 1e-3)) | coincident)
