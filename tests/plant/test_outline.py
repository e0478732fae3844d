"""The robot's one outline (magctl.plant.outline): its area, centroid and principal axes against a pixel count of
the same polygon by matplotlib's point-in-path test, its orientation against the paper, and its errors."""

import os
import shutil

import numpy as np
import pytest
from matplotlib.path import Path

from magctl.config import models_dir
from magctl.core.errors import ParameterError
from magctl.plant.outline import RobotOutline, robot_outline
from magctl.sensing.camera import seen_shapes


def grid_moments(vertices, step=1e-6):
    """Area, centroid and the major axis' angle of a polygon by counting grid cells inside it."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    xs = np.arange(lo[0], hi[0], step) + step / 2
    ys = np.arange(lo[1], hi[1], step) + step / 2
    xx, yy = np.meshgrid(xs, ys)
    inside = Path(vertices).contains_points(np.c_[xx.ravel(), yy.ravel()])
    x, y = xx.ravel()[inside], yy.ravel()[inside]
    area = inside.sum() * step * step
    cx, cy = x.mean(), y.mean()
    cov = np.cov(np.stack([x - cx, y - cy]))
    evals, evecs = np.linalg.eigh(cov)
    major = np.mod(np.arctan2(evecs[1, 1], evecs[0, 1]), np.pi)
    return area, np.array([cx, cy]), major


def test_the_robot_is_310_along_its_heading_and_480_across_with_its_concave_face_ahead():
    o = robot_outline()
    assert (o.length, o.width, o.thickness) == pytest.approx((310e-6, 480e-6, 130e-6), rel=1e-12)
    assert np.ptp(o.vertices, axis=0) == pytest.approx([310e-6, 480e-6], rel=1e-12)
    # the side push's contact threshold (paper §IV-D: D_g ≈ 370 µm, "larger than half the robot's width"):
    # half the extent across the heading plus the sphere radius lies below it
    assert np.ptp(o.vertices[:, 1]) / 2 + 105e-6 < 370e-6 < np.ptp(o.vertices[:, 1]) / 2 + 105e-6 + 50e-6
    # the notch: straight ahead, just behind the front edge, is outside the robot
    assert not o.polygon.contains(np.array([o.length / 2 - 20e-6]), np.array([0.0]))[0]
    assert o.signed_distance(0.0, 0.0) < 0 < o.signed_distance(o.length, 0.0)


def test_area_centroid_and_major_axis_match_a_grid_count():
    o = robot_outline()
    area, centre, major = grid_moments(np.asarray(o.vertices))
    assert o.area == pytest.approx(area, rel=2e-3)
    assert o.centroid == pytest.approx(centre, abs=0.5e-6)
    assert o.centroid[0] < 0        # the deeper front notch moves the centroid backwards
    assert o.major_axis == pytest.approx(major, abs=1e-3)
    assert o.major_axis == pytest.approx(np.pi / 2)
    long = RobotOutline(480e-6, 310e-6, 130e-6, 90e-6, 200e-6, 30e-6, 30e-6)
    assert long.major_axis == pytest.approx(grid_moments(np.asarray(long.vertices))[2], abs=1e-3)
    assert min(long.major_axis, np.pi - long.major_axis) == pytest.approx(0.0, abs=1e-9)


def test_scaled_outlines_are_the_same_shape():
    o = robot_outline()
    px = o.scaled(1 / 7.5e-6)
    np.testing.assert_allclose(px.vertices * 7.5e-6, o.vertices, rtol=1e-12, atol=1e-18)
    assert px.area == pytest.approx(o.area / 7.5e-6**2, rel=1e-12)


@pytest.mark.parametrize(("kw", "word"), [
    ({"length": -1e-4}, "length"), ({"width": float("nan")}, "width"), ({"thickness": 0.0}, "thickness"),
    ({"front_notch_width": 600e-6}, "front notch width"), ({"front_notch_depth": 200e-6}, "front notch depth"),
    ({"arc_points": 1}, "arc_points"),
])
def test_impossible_outlines_are_named(kw, word):
    args = {"length": 310e-6, "width": 480e-6, "thickness": 130e-6, "front_notch_depth": 90e-6,
            "front_notch_width": 260e-6, "side_notch_depth": 30e-6, "rear_notch_depth": 30e-6} | kw
    with pytest.raises(ParameterError, match=word):
        RobotOutline(**args)


def test_the_outline_and_what_the_camera_sees_follow_the_parameter_folder_and_its_edits(tmp_path, monkeypatch):
    folder = tmp_path / "models"
    shutil.copytree(models_dir(), folder)
    shipped = robot_outline()
    monkeypatch.setenv("MAGCTL_MODELS", str(folder))
    assert robot_outline().length == shipped.length                  # another folder, the same values
    geometry = folder / "robot_geometry.toml"
    geometry.write_text(geometry.read_text().replace("length_um = { value = 310.0", "length_um = { value = 300.0"))
    os.utime(geometry, ns=(0, 10**18))                               # a new version even on a coarse clock
    assert robot_outline().length == pytest.approx(300e-6, rel=1e-12)
    assert seen_shapes().robot.length == pytest.approx(300e-6, rel=1e-12)
    sphere = folder / "sphere.toml"
    assert seen_shapes().sphere_radius == pytest.approx(105e-6, rel=1e-12)
    sphere.write_text(sphere.read_text().replace("radius_um = { value = 105.0", "radius_um = { value = 100.0"))
    os.utime(sphere, ns=(0, 10**18))
    assert seen_shapes().sphere_radius == pytest.approx(100e-6, rel=1e-12)
    monkeypatch.delenv("MAGCTL_MODELS")
    assert robot_outline().length == shipped.length
