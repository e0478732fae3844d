"""Wavefront planner: never inside the inflated spheres, clear errors, replanning block, servo follows it."""

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from magctl.control.planner import Planner, PlanningError, plan_path, planner_defaults, wavefront
from magctl.control.servo import Servo
from magctl.core import Constant, Diagram, simulate
from magctl.stability.servo import KinematicRobot

KEEP_OUT_M = planner_defaults().keep_out   # models/push.toml [common] clearance_um
BOUNDS = (0.0, 0.0, 4.8e-3, 3.6e-3)


def _min_distance_dense(path, centres, n=200):
    """Independent check: sample every segment densely and measure point–centre distances."""
    t = np.linspace(0, 1, n)[:, None]
    pts = np.concatenate([a + t * (b - a) for a, b in zip(path[:-1], path[1:], strict=True)])
    return np.min(np.linalg.norm(pts[:, None, :] - centres[None], axis=2))


def test_defaults_are_the_files_values_bit_for_bit():
    """models/push.toml: the keep-out is [common] clearance_um (paper §VI), the cell and the block's
    tolerances [planner]; each the same double as the literal the code had (a changed bit can change the grid)."""
    d = planner_defaults()
    assert (d.keep_out, d.cell, d.waypoint_tol, d.replan_tol) == (650e-6, 25e-6, 50e-6, 15e-6)
    block = Planner(bounds=BOUNDS)
    assert (block.keep_out, block.cell, block.waypoint_tol, block.replan_tol) == (650e-6, 25e-6, 50e-6, 15e-6)
    assert np.array_equal(plan_path([0.5e-3, 1.8e-3], [4.2e-3, 1.8e-3], [[2.4e-3, 1.8e-3]], bounds=BOUNDS),
                          plan_path([0.5e-3, 1.8e-3], [4.2e-3, 1.8e-3], [[2.4e-3, 1.8e-3]], bounds=BOUNDS,
                                    keep_out=650e-6, cell=25e-6))


def test_wavefront_counts_8_connected_steps():
    free = np.ones((5, 7), dtype=bool)
    free[1:4, 3] = False
    d = wavefront(free, (2, 0))
    assert d[2, 0] == 0 and d[2, 2] == 2
    # around the wall (rows 1-3 of column 3 blocked): via row 0 or 4 — Chebyshev steps
    assert d[2, 6] == 6
    assert d[1, 3] == -1


def test_wavefront_equals_a_plain_breadth_first_search_on_random_grids():
    """Against a queue-based BFS written here: the same step count in every cell, −1 where unreachable."""
    from collections import deque

    rng = np.random.default_rng(7)
    for _ in range(25):
        free = rng.random((int(rng.integers(4, 30)), int(rng.integers(4, 30)))) > 0.35
        goal = (int(rng.integers(free.shape[0])), int(rng.integers(free.shape[1])))
        free[goal] = True
        ref = np.full(free.shape, -1)
        ref[goal] = 0
        queue = deque([goal])
        while queue:
            i, j = queue.popleft()
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    n = (i + di, j + dj)
                    if (0 <= n[0] < free.shape[0] and 0 <= n[1] < free.shape[1] and free[n] and ref[n] < 0):
                        ref[n] = ref[i, j] + 1
                        queue.append(n)
        assert (wavefront(free, goal) == ref).all()


def _reachable_with_margin(start, goal, centres, margin, step=10e-6):
    """Independent of the planner: a path from ``start`` to ``goal`` that keeps ``KEEP_OUT_M + margin`` from every
    centre and ``margin`` inside ``BOUNDS``, looked for on a ``step`` grid of its own (its nodes with that clearance,
    8-connected components by scipy.ndimage.label); start and goal must have that clearance and join their nearest
    nodes. A path found here keeps ``KEEP_OUT_M + margin − step/√2`` (less a sagitta of 0.04 µm) everywhere."""
    from scipy import ndimage

    x0, y0, x1, y1 = BOUNDS
    xs = np.arange(x0 + margin, x1 - margin + step / 2, step)
    ys = np.arange(y0 + margin, y1 - margin + step / 2, step)
    x, y = np.meshgrid(xs, ys)
    free = np.ones(x.shape, dtype=bool)
    for cx, cy in centres:
        free &= np.hypot(x - cx, y - cy) >= KEEP_OUT_M + margin
    labels, _ = ndimage.label(free, structure=np.ones((3, 3)))

    def component(p):
        clear = np.hypot(*(centres - p).T).min() >= KEEP_OUT_M + margin
        inside = x0 + margin <= p[0] <= x1 - margin and y0 + margin <= p[1] <= y1 - margin
        return labels[np.abs(ys - p[1]).argmin(), np.abs(xs - p[0]).argmin()] if clear and inside else 0

    a = component(start)
    return bool(a) and a == component(goal)


UNREACHABLE_MARGIN = 2 * planner_defaults().cell
"""A path clearing the keep-out by this (less the check's 7 µm grid) passes the planner's grid, whose cells keep
half a diagonal more and lie half a diagonal off the path: 50 µm > 2 x 17.7 µm. The planner must find such a path."""


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(0.8e-3, 4.0e-3), st.floats(0.3e-3, 3.3e-3)), min_size=1, max_size=3),
       st.floats(0.1e-3, 0.5e-3), st.floats(0.2e-3, 3.4e-3), st.floats(4.3e-3, 4.7e-3), st.floats(0.2e-3, 3.4e-3))
@example([(2.4e-3, 0.6e-3), (2.4e-3, 1.8e-3), (2.4e-3, 3.0e-3)], 0.3e-3, 1.8e-3, 4.5e-3, 1.8e-3)  # a wall: unreachable
@example([(2.4e-3, 0.6e-3), (2.4e-3, 2.6e-3)], 0.3e-3, 1.8e-3, 4.5e-3, 1.8e-3)  # a 700 µm gap between two discs
def test_path_never_enters_inflated_spheres(spheres, sx, sy, gx, gy):
    """A path keeps out of every inflated sphere and inside the workspace; "unreachable" only where no path clears
    the keep-out by :data:`UNREACHABLE_MARGIN` (checked on a grid of the test's own)."""
    centres = np.array(spheres)
    start, goal = np.array([sx, sy]), np.array([gx, gy])
    assume(np.linalg.norm(centres - start, axis=1).min() > KEEP_OUT_M)
    assume(np.linalg.norm(centres - goal, axis=1).min() > KEEP_OUT_M)
    try:
        path = plan_path(start, goal, centres, bounds=BOUNDS)
    except PlanningError as err:
        assert "unreachable" in str(err)
        assert not _reachable_with_margin(start, goal, centres, UNREACHABLE_MARGIN), \
            "the planner calls the goal unreachable, but a path clearing the keep-out by 50 µm exists"
        return
    np.testing.assert_allclose(path[0], start)
    np.testing.assert_allclose(path[-1], goal)
    assert _min_distance_dense(path, centres) >= KEEP_OUT_M * (1 - 1e-9)
    assert np.all(path >= -1e-12) and np.all(path[:, 0] <= 4.8e-3) and np.all(path[:, 1] <= 3.6e-3)


def test_straight_line_when_nothing_in_the_way():
    path = plan_path([0.5e-3, 0.5e-3], [4e-3, 3e-3], np.zeros((0, 2)), bounds=BOUNDS)
    np.testing.assert_allclose(path, [[0.5e-3, 0.5e-3], [4e-3, 3e-3]])


def test_detour_is_short():
    """Around one disc the shortest path is tangent–arc–tangent; the planner stays within 5 % of it."""
    c, r = np.array([2.4e-3, 1.8e-3]), KEEP_OUT_M
    start, goal = np.array([0.6e-3, 1.8e-3]), np.array([4.2e-3, 1.8e-3])
    path = plan_path(start, goal, c[None], bounds=BOUNDS)
    d = np.linalg.norm(start - c)
    tangent = np.sqrt(d**2 - r**2)
    arc = r * (np.pi - 2 * np.arccos(r / d))
    shortest = 2 * tangent + arc
    length = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))
    assert shortest <= length < 1.05 * shortest


def test_unreachable_goal_is_a_clear_error():
    wall = np.array([[2.4e-3, y] for y in np.arange(0.0, 3.7e-3, 0.6e-3)])
    with pytest.raises(PlanningError, match="unreachable.*keep-out"):
        plan_path([0.5e-3, 1.8e-3], [4.2e-3, 1.8e-3], wall, bounds=BOUNDS)


@pytest.mark.parametrize("goal, word", [([5.0e-3, 1e-3], "outside the workspace"),
                                        ([2.5e-3, 1.8e-3], "from sphere 0, inside its 650 µm keep-out")])
def test_bad_goals(goal, word):
    with pytest.raises(PlanningError, match=word):
        plan_path([0.5e-3, 0.5e-3], goal, np.array([[2.4e-3, 1.8e-3]]), bounds=BOUNDS)


def test_bad_bounds():
    with pytest.raises(PlanningError, match="bounds"):
        plan_path([0, 0], [1e-3, 1e-3], np.zeros((0, 2)), bounds=(1e-3, 0, 0, 1e-3))


def test_start_inside_keep_out_escapes_radially():
    c = np.array([2.4e-3, 1.8e-3])
    start = c + [0.0, -0.4e-3]
    path = plan_path(start, [4.2e-3, 1.8e-3], c[None], bounds=BOUNDS)
    # first move is straight away from the sphere, then the rest stays out
    away = (path[1] - start) / np.linalg.norm(path[1] - start)
    np.testing.assert_allclose(away, [0.0, -1.0], atol=1e-9)
    assert _min_distance_dense(path[1:], c[None]) >= KEEP_OUT_M * (1 - 1e-9)


def _follow(c0, c1, switch, steps):
    sph0 = c0
    robot = KinematicRobot("robot", start=(0.5e-3, 1.8e-3))
    spheres = Constant("spheres", sph0, shape=sph0.shape, unit="m")
    planner = Planner("planner", n_spheres=len(sph0), bounds=BOUNDS)
    servo = Servo("servo", kp=3.0, ki=0.0, speed_max=400e-6, arrive_tol=7.5e-6)
    d = Diagram("follow", [robot, spheres, planner, servo],
                [("robot.position", "planner.robot_est"), ("planner.target", "servo.target"),
                 ("robot.position", "servo.robot_est"), ("servo.speed", "robot.speed"),
                 ("servo.heading", "robot.heading")],
                inputs={"goal": "planner.goal", "sph": "planner.spheres_est"},
                outputs={"target": "planner.target"})
    sph = np.stack([c0 if k < switch else c1 for k in range(steps)])
    return simulate(d, steps, inputs={"goal": [4.2e-3, 1.8e-3], "sph": sph})


def test_servo_follows_waypoints_around_sphere_and_replans_when_it_moves():
    c0 = np.array([[2.4e-3, 1.8e-3]])
    route = plan_path([0.5e-3, 1.8e-3], [4.2e-3, 1.8e-3], c0, bounds=BOUNDS)
    side = np.sign(route[1:-1, 1].mean() - c0[0, 1])
    c1 = c0 - [[0.0, side * 300e-6]]  # pushed 300 µm away from the route while the robot travels
    res = _follow(c0, c1, 150, 700)
    pos = res["robot.position"][0]
    assert np.linalg.norm(pos[-1] - [4.2e-3, 1.8e-3]) < 10e-6
    assert res["planner.final"][0, -1] and res["planner.feasible"][0].all()
    assert res["planner.replans"][0, -1] == 2
    # the robot trajectory keeps clear of the sphere where it was at each step (the servo cuts
    # corners slightly at waypoint switches, so allow 5 % of the keep-out)
    before = np.linalg.norm(pos[:150] - c0, axis=1).min()
    after = np.linalg.norm(pos[150:] - c1, axis=1).min()
    assert min(before, after) > 0.95 * KEEP_OUT_M


def test_planner_block_reports_infeasible_and_holds():
    wall = np.array([[2.4e-3, y] for y in np.arange(0.0, 3.7e-3, 0.6e-3)])
    planner = Planner("planner", n_spheres=len(wall), bounds=BOUNDS)
    st_ = planner.initial_state(1)
    u = {"goal": np.array([[4.2e-3, 1.8e-3]]), "robot_est": np.array([[0.5e-3, 1.8e-3]]), "spheres_est": wall[None]}
    out = planner.output(st_, u)
    assert not out["feasible"][0]
    np.testing.assert_allclose(out["target"][0], [0.5e-3, 1.8e-3])
