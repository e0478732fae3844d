"""Camera block: latency and quantisation exact, drops seeded and per-trial, field of view, rendering."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.core import Constant, Diagram, Integrator, ParameterError, simulate
from magctl.sensing.camera import Camera, camera_params, principal_axis, render_frame

T = 1.0 / 30.0


def _rig(cam, start=(1.0e-3, 1.0e-3), spheres=((2e-3, 2e-3),)):
    sph = np.asarray(spheres, dtype=float)
    blocks = [Integrator("robot", shape=(2,), in_unit="m/s", out_unit="m", initial=list(start)),
              Constant("h", 0.3, unit="rad"), Constant("s", sph, shape=sph.shape, unit="m"), cam]
    conns = [("robot.y", "camera.position"), ("h.y", "camera.heading"), ("s.y", "camera.spheres")]
    return Diagram("rig", blocks, conns, inputs={"v": "robot.u"})


@settings(max_examples=15, deadline=None)
@given(latency=st.integers(0, 4), pixel_um=st.sampled_from([1.0, 7.5, 10.0]),
       vx=st.floats(-3e-4, 3e-4), vy=st.floats(-3e-4, 3e-4))
def test_latency_and_quantisation_exact(latency, pixel_um, vx, vy):
    s = pixel_um * 1e-6
    cam = Camera("camera", latency_frames=latency, position_noise_px=0.0, heading_noise=0.0,
                 drop_probability=0.0, pixel_size=s)
    x0 = np.array([320.3, 240.6]) * s  # centre of the field of view, off the pixel grid
    res = simulate(_rig(cam, start=x0, spheres=[x0 + 10 * s]), 20, inputs={"v": [vx, vy]})
    x = res["robot.y"][0]
    meas, valid = res["camera.robot_meas"][0], res["camera.valid"][0]
    assert not valid[:latency].any() and valid[latency:].all()
    # independent closed form: x[k] = x0 + k T v, delivered L frames later on the pixel grid
    k = np.arange(latency, 20)
    true = x0 + (k - latency)[:, None] * T * np.array([vx, vy])
    np.testing.assert_allclose(x[:20 - latency], true, atol=1e-15)
    # the frame of step k - L, rounded to the nearest pixel centre
    np.testing.assert_allclose(meas[latency:], s * np.round(x[:20 - latency] / s), atol=1e-12)
    np.testing.assert_allclose(meas[latency:], true, atol=s / 2 + 1e-12)
    assert np.allclose(np.round(meas[latency:] / s) * s, meas[latency:], atol=1e-12)
    np.testing.assert_allclose(res["camera.spheres_meas"][0, latency:, 0],
                               np.broadcast_to(s * np.round(x0 / s + 10), (20 - latency, 2)), atol=1e-12)


def test_latency_makes_block_non_feedthrough():
    assert Camera("c", latency_frames=0).feedthrough
    assert not Camera("c", latency_frames=2).feedthrough


def test_noise_statistics_and_per_trial_streams():
    cam = Camera("camera", latency_frames=1, position_noise_px=2.0, pixel_size=7.5e-6, drop_probability=0.0)
    res = simulate(_rig(cam, start=(1.5e-3, 1.5e-3)), 600, batch=4, seed=3, inputs={"v": [0.0, 0.0]})
    err = (res["camera.robot_meas"][:, 1:] - 1.5e-3) / 7.5e-6
    # quantised Gaussian of σ = 2 px: variance σ² + 1/12
    assert np.std(err) == pytest.approx(np.sqrt(4 + 1 / 12), rel=0.1)
    alone = simulate(_rig(cam, start=(1.5e-3, 1.5e-3)), 600, batch=1, seed=3, trials=[2], inputs={"v": [0.0, 0.0]})
    np.testing.assert_array_equal(alone["camera.robot_meas"][0], res["camera.robot_meas"][2])


def test_dropped_frames_rate_and_hold():
    cam = Camera("camera", latency_frames=0, drop_probability=0.25, position_noise_px=0.0)
    res = simulate(_rig(cam), 4000, seed=1, inputs={"v": [1e-5, 0.0]})
    valid = res["camera.valid"][0]
    # binomial(4000, 0.25): 5 σ bounds
    assert abs((~valid).mean() - 0.25) < 5 * np.sqrt(0.25 * 0.75 / 4000)
    meas = res["camera.robot_meas"][0]
    drops = np.flatnonzero(~valid[1:]) + 1
    np.testing.assert_array_equal(meas[drops], meas[drops - 1])


def test_out_of_view_is_invalid():
    cam = Camera("camera", latency_frames=0, drop_probability=0.0)
    w, h = cam.field_of_view
    assert w == pytest.approx(639 * 7.5e-6) and h == pytest.approx(479 * 7.5e-6)
    res = simulate(_rig(cam, start=(w - 5e-6, 1e-3)), 5, inputs={"v": [3e-4, 0.0]})
    np.testing.assert_array_equal(res["camera.valid"][0], [True, False, False, False, False])


@pytest.mark.parametrize("kw, word", [
    ({"mode": "video"}, "mode"), ({"latency_frames": -1}, "latency"), ({"latency_frames": 1.5}, "latency"),
    ({"drop_probability": 1.0}, "drop_probability"), ({"pixel_size": 0.0}, "pixel_size"),
    ({"n_spheres": -1}, "n_spheres"),
])
def test_bad_parameters_are_named(kw, word):
    with pytest.raises(ParameterError, match=word):
        Camera("camera", **kw)


def test_rendered_frame_shows_objects_where_they_are():
    p = camera_params()
    s = p.camera.pixel_size
    img = render_frame(np.array([1.2e-3, 1.5e-3]), 0.0, np.array([[3.0e-3, 2.0e-3]]), p.render, pixel=s,
                       width=640, height=480)
    assert img.shape == (480, 640)
    assert img[0, 0] == pytest.approx(p.render.background)
    # the sphere: dark disc of radius 105 µm = 14 px, centroid at its centre
    win = img[int(2.0e-3 / s) - 25:int(2.0e-3 / s) + 26, int(3.0e-3 / s) - 25:int(3.0e-3 / s) + 26]
    mass = p.render.background - win
    ii, jj = np.mgrid[-25:26, -25:26]
    assert (mass * jj).sum() / mass.sum() == pytest.approx(3.0e-3 / s - int(3.0e-3 / s), abs=0.05)
    area = mass.sum() / (p.render.background - p.render.sphere_level)
    assert area == pytest.approx(np.pi * (105e-6 / s) ** 2, rel=0.03)
    # the robot: its 310 × 480 µm box minus the circular segments of its concave front, flanks and rear
    rwin = p.render.background - img[200 - 45:200 + 46, 160 - 45:160 + 46]
    robot_area = rwin.sum() / (p.render.background - p.render.robot_level)
    assert robot_area == pytest.approx(star_area_m2() / s**2, rel=0.03)


def star_area_m2() -> float:
    """The outline's area in closed form from models/robot_geometry.toml: the box minus four circular segments
    (chord c, sagitta d: ρ = (c²/4 + d²)/2d, area ρ² acos(1 − d/ρ) − (ρ − d) c/2)."""
    import tomllib

    from magctl.config import models_dir

    with open(models_dir() / "robot_geometry.toml", "rb") as fh:
        o = {k: v["value"] * 1e-6 for k, v in tomllib.load(fh)["outline"].items() if k.endswith("_um")}

    def segment(c, d):
        rho = (c * c / 4 + d * d) / (2 * d)
        return rho**2 * np.arccos(1 - d / rho) - (rho - d) * c / 2

    length, width = o["length_um"], o["width_um"]
    return (length * width - segment(o["front_notch_width_um"], o["front_notch_depth_um"])
            - 2 * segment(length, o["side_notch_depth_um"]) - segment(width, o["rear_notch_depth_um"]))


def test_images_mode_ports_and_drops():
    cam = Camera("camera", mode="images", latency_frames=1, drop_probability=0.0)
    assert cam.outputs["image"].shape == (480, 640)
    res = simulate(_rig(cam), 3, inputs={"v": [0.0, 0.0]})
    assert res["camera.image"].shape == (1, 3, 480, 640)
    np.testing.assert_array_equal(res["camera.valid"][0], [False, True, True])
    assert res["camera.image"][0, 2].min() < 0.3


@pytest.mark.parametrize("angle", [0.0, 0.3, 1.2, -0.7, np.pi / 2])
def test_a_blobs_principal_axis_is_the_drawn_ellipses(angle):
    """An ellipse 40 × 16 px drawn at a known angle and centre: the centroid to 0.1 px and the major axis to 0.5°
    (mod π; the pixel grid's error), exactly as the points' mean and covariance's major eigenvector give them."""
    yy, xx = np.mgrid[0:120, 0:140].astype(float)
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * (xx - 71.3) + s * (yy - 58.6), -s * (xx - 71.3) + c * (yy - 58.6)
    mask = (u / 40) ** 2 + (v / 16) ** 2 <= 1.0
    cx, cy, axis = principal_axis(mask, xx, yy)
    assert (cx, cy) == pytest.approx((71.3, 58.6), abs=0.1)
    assert (cx, cy) == pytest.approx((xx[mask].mean(), yy[mask].mean()), abs=1e-9)
    assert abs((axis - angle + np.pi / 2) % np.pi - np.pi / 2) < np.radians(0.5)
    evals, evecs = np.linalg.eigh(np.cov(np.stack([xx[mask] - cx, yy[mask] - cy])))
    ref = np.arctan2(evecs[1, 1], evecs[0, 1])
    assert abs((axis - ref + np.pi / 2) % np.pi - np.pi / 2) < 1e-9
