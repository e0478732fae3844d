"""GIF animations of pushes: frame count, timing, size, what is drawn, and clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from magctl.core.errors import MagctlError
from magctl.plant.outline import robot_outline
from magctl.studies.animate import AnimationError, animate_push

FRAME_S = 1 / 30


def _push(T: int, n_spheres: int = 1):
    """A robot driving +x at 90 µm/s past spheres lined up ahead of it."""
    t = np.arange(T) * FRAME_S
    robot = np.c_[-600e-6 + 90e-6 * t, np.zeros(T)]
    heading = np.zeros(T)
    spheres = np.zeros((T, n_spheres, 2))
    spheres[:, :, 0] = 300e-6 + 250e-6 * np.arange(n_spheres)
    return t, robot, heading, spheres


def _frames(path):
    with Image.open(path) as im:
        assert im.format == "GIF"
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append((np.asarray(im.convert("RGB")), im.info.get("duration")))
        return out


def test_stride_gives_expected_frames(tmp_path):
    t, robot, heading, spheres = _push(50)
    path = animate_push(t, robot, heading, spheres, tmp_path / "a.gif", goal=[750e-6, 0], stride=4, fps=10)
    frames = _frames(path)
    # steps 0, 4, …, 48 (13 frames) and the last step 49
    assert len(frames) == 14
    assert all(d == 100 for _, d in frames)  # 10 fps → 100 ms per frame
    assert frames[0][0].shape == (360, 360, 3)


def test_default_is_real_time_at_fps(tmp_path):
    t, robot, heading, spheres = _push(90)
    path = animate_push(t, robot, heading, spheres, tmp_path / "b.gif", fps=15)
    # 30 Hz trajectory shown at 15 fps: every 2nd step, 0 … 88, plus the last step
    assert len(_frames(path)) == 46


def test_long_runs_are_capped_and_small(tmp_path):
    t, robot, heading, spheres = _push(3000, n_spheres=2)
    heading = 0.4 * np.sin(t)
    path = animate_push(t, robot, heading, spheres, tmp_path / "c.gif", goal=np.c_[robot[:, 0], robot[:, 1] + 1e-4])
    with Image.open(path) as im:
        assert 100 <= im.n_frames <= 150
    assert path.stat().st_size < 2_000_000


def _mask(rgb, colour, tol=12):
    return (np.abs(rgb.astype(int) - np.array(colour)).max(axis=2) <= tol)


def test_robot_and_spheres_are_drawn_where_they_are(tmp_path):
    t, robot, heading, spheres = _push(60)
    frames = _frames(animate_push(t, robot, heading, spheres, tmp_path / "d.gif", stride=59))
    assert len(frames) == 2
    robot_grey, sphere_fill = (0x55, 0x55, 0x55), (0xD9, 0xE7, 0xF5)
    first, last = frames[0][0], frames[-1][0]
    x0 = np.nonzero(_mask(first, robot_grey))[1].mean()
    x1 = np.nonzero(_mask(last, robot_grey))[1].mean()
    assert x1 > x0  # the robot moved right on screen
    # the sphere does not move: same pixels in both frames, and present
    assert _mask(first, sphere_fill).sum() > 100
    assert (_mask(first, sphere_fill) == _mask(last, sphere_fill)).mean() > 0.99


def test_no_spheres_is_allowed(tmp_path):
    t, robot, heading, _ = _push(10)
    frames = _frames(animate_push(t, robot, heading, np.zeros((10, 0, 2)), tmp_path / "e.gif", stride=5))
    assert len(frames) == 3
    assert _mask(frames[0][0], (0xD9, 0xE7, 0xF5)).sum() == 0


def test_default_outline_is_the_papers_310_by_480_star():
    star = robot_outline().vertices
    extent = star.max(axis=0) - star.min(axis=0)
    np.testing.assert_allclose(extent, [310e-6, 480e-6], rtol=1e-12)
    # concave front face: just behind the front edge, straight ahead is outside the robot, beside it inside
    from matplotlib.path import Path as Outline

    inside = Outline(star).contains_points([[star[:, 0].max() - 20e-6, 0.0], [star[:, 0].max() - 20e-6, 200e-6]])
    assert list(inside) == [False, True]


T = 20
GOOD = _push(T)


@pytest.mark.parametrize(("change", "message"), [
    ({"robot_xy": np.zeros((T, 3))}, r"robot_xy must have shape \(T, 2\) = \(20, 2\) in m, got \(20, 3\)"),
    ({"robot_xy": np.zeros((T - 1, 2))}, r"robot_xy must have shape .* got \(19, 2\)"),
    ({"robot_heading": np.zeros((T, 1))}, r"robot_heading must have shape \(T,\) = \(20,\) in rad, got \(20, 1\)"),
    ({"spheres_xy": np.zeros((T, 2))}, r"spheres_xy must have shape \(T, N, 2\) = \(20, N, 2\) in m, got \(20, 2\)"),
    ({"goal": [1e-4, 2e-4, 3e-4]}, r"goal must have shape \(2,\) or \(T, 2\)"),
    ({"goal": np.zeros((3, 2))}, r"goal must have shape .* got \(3, 2\)"),
    ({"t": np.zeros(T)}, "t must be strictly increasing"),
    ({"t": np.zeros((T, 1))}, r"t must have shape \(T,\) in s"),
    ({"t": []}, "t is empty"),
    ({"robot_xy": np.full((T, 2), np.nan)}, "robot_xy holds NaN"),
    ({"spheres_xy": np.full((T, 1, 2), 300.0)}, "spheres_xy must be in metres"),
    ({"outline": [[0, 0], [1e-4, 0]]}, "outline needs at least 3 vertices, got 2"),
    ({"fps": 0}, "fps must be a positive number, got 0"),
    ({"stride": 0}, "stride must be a positive integer, got 0"),
    ({"stride": 1.5}, "stride must be a positive integer, got 1.5"),
    ({"robot_heading": "north"}, "robot_heading must be a numeric array"),
])
def test_bad_input_is_named(tmp_path, change, message):
    args = dict(zip(("t", "robot_xy", "robot_heading", "spheres_xy"), GOOD))
    opts = {}
    for key, value in change.items():
        (args if key in args else opts)[key] = value
    with pytest.raises(AnimationError, match=message) as info:
        animate_push(**args, path=tmp_path / "bad.gif", **opts)
    assert isinstance(info.value, MagctlError)
    assert not (tmp_path / "bad.gif").exists()


def test_bad_sphere_radius(tmp_path):
    with pytest.raises(AnimationError, match="sphere_radius must be a positive length in metres, got 105"):
        animate_push(*GOOD, path=tmp_path / "r.gif", sphere_radius=105)
    assert not (tmp_path / "r.gif").exists()
