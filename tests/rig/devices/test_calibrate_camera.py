"""``magctl rig calibrate camera`` on the simulated lab (lock-step): a camera with a known, non-default geometry
(7.0 µm pixels, turned 4°, mirrored) is recovered from the spheres and the robot's heading; with the calibration
applied the tracker finds the robot where the world has it; a lab without spheres, a target that is not in view
and a robot the camera does not see are one-line errors."""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from magctl.config import load_file
from magctl.core.errors import MagctlError
from magctl.rig.devices.tracking import PixelCalibration
from magctl.rig.interface import Command
from magctl.rig.lab import build_station, load_lab

NOMINAL = 7.5e-6
CENTRE_PX = np.array([319.5, 239.5])
CENTRE_GLASS = CENTRE_PX * NOMINAL  # the camera turns about its optical axis, over the nominal image centre


def true_geometry(pixel_um: float = 7.0, rotation_deg: float = 4.0, mirror: bool = True,
                  shift_um=(0.0, 0.0)) -> PixelCalibration:
    linear = PixelCalibration(pixel_um * 1e-6, math.radians(rotation_deg), mirror)
    origin = CENTRE_GLASS + np.asarray(shift_um) * 1e-6 - linear.to_glass(CENTRE_PX)
    return PixelCalibration(linear.pixel_size, linear.rotation, mirror, tuple(origin))


def write_lab(folder, geometry: PixelCalibration, *, spheres: bool = True, calibration: str | None = None,
              name: str = "lab.toml"):
    cam = geometry.to_params()
    tracker = f'calibration = "{calibration}"\n' if calibration else ""
    spheres_um = "[[2000.0, 1800.0], [3000.0, 1800.0]]" if spheres else "[]"
    path = folder / name
    path.write_text(f"""
[lab]
name = "calibration test"

[camera]
adapter = "sim"
encoding = "png"
pixel_size_um = {cam['pixel_size_um']!r}
rotation_deg = {cam['rotation_deg']!r}
mirror = {'true' if cam['mirror'] else 'false'}
origin_x_um = {cam['origin_x_um']!r}
origin_y_um = {cam['origin_y_um']!r}

[tracker]
n_spheres = {2 if spheres else 0}
{tracker}
[coils]
adapter = "sim-board"
deadline_s = 0.1

[simulation]
plant = "physics"
seed = 3
robot_um = [1000.0, 1800.0]
spheres_um = {spheres_um}
""", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("camera")
    truth = true_geometry()
    lab = write_lab(folder, truth)
    return folder, truth, lab


@pytest.fixture(scope="module")
def result(calibrate, calibrated):
    folder, _, lab = calibrated
    out = folder / "calibration.toml"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert calibrate("camera", "--config", str(lab), "--out", str(out), "--json") == 0
    return json.loads(buf.getvalue()), out


def test_the_camera_geometry_is_recovered(calibrated, result):
    _, truth, _ = calibrated
    doc, out = result
    cal = PixelCalibration.load(out)
    assert cal.mirror is True
    assert cal.pixel_size == pytest.approx(truth.pixel_size, rel=5e-3)
    assert math.degrees(abs(cal.rotation - truth.rotation)) < 0.5
    # the origin is pinned at the nominal image centre, where this camera's axis is
    assert np.allclose(cal.to_glass(CENTRE_PX), CENTRE_GLASS, atol=1e-9)
    assert np.allclose(cal.origin, truth.origin, atol=15e-6)
    # the stated uncertainties are small and honest about the error
    assert doc["pixel_size_se_um"] < 0.01 and doc["rotation_se_deg"] < 0.1
    assert abs(doc["pixel_size_um"] - 7.0) < 0.035
    assert doc["targets"] == 2 and doc["target_images"] >= 8 * 3 * 2 - 4
    assert doc["residual_rms_deg"] < 0.3 and doc["other_mirror_rms_deg"] > 30


def test_the_file_is_a_parameter_file_with_sources(result):
    _, out = result
    params = load_file(out)  # every value has its source and its unit (magctl.config rules)
    table = params.calibration
    assert table.pixel_size == pytest.approx(7.0e-6, rel=5e-3)
    assert table.sources["pixel_size"].startswith("measured:") and "210 µm spheres" in table.sources["pixel_size"]
    assert table.sources["rotation"].startswith("measured:") and "8 directions" in table.sources["rotation"]
    assert "against the field" in table.sources["mirror"]
    assert table.sources["origin_x"].startswith("assumed:")


def test_with_the_calibration_the_tracker_finds_the_robot_where_it_is(calibrated, result):
    folder, _, _ = calibrated
    _, out = result
    lab = write_lab(folder, true_geometry(), calibration=out.name, name="lab-calibrated.toml")
    station = build_station(load_lab(lab), lockstep=True)
    try:
        errors, heading_errors = [], []
        for k in range(40):
            # walk, turning the field 0 → 0.6 rad over 12 frames (the tracker follows a few degrees a frame)
            phi = 0.6 * min(k, 12) / 12
            walk = Command(2e-3 * np.array([math.cos(phi), math.sin(phi)]), 1.45e-3, 9.0)
            station.apply(walk, (k + 1) * station.period)
            obs = station.step((k + 1) * station.period)
            world = station.camera.world
            assert not obs.lost, f"frame {k}: tracking lost"
            errors.append(np.hypot(*(obs.robot_est - world.robot)))
            heading_errors.append(abs(math.remainder(obs.heading_est - world.heading, 2 * math.pi)))
        travelled = np.hypot(*(station.camera.world.robot - np.array([1e-3, 1.8e-3])))
    finally:
        station.close()
    assert travelled > 200e-6  # the robot walked and turned, and was followed
    assert max(errors) < 10e-6, f"largest position error {max(errors) * 1e6:.1f} µm"
    assert math.degrees(max(heading_errors)) < 3.0


def test_a_lab_without_spheres_needs_a_target_size(calibrate, tmp_path):
    lab = write_lab(tmp_path, true_geometry(), spheres=False)
    with pytest.raises(MagctlError) as err:
        calibrate("camera", "--config", str(lab), "--out", str(tmp_path / "c.toml"))
    msg = str(err.value)
    assert "\n" not in msg and "no spheres" in msg and "--target-diameter-um" in msg
    assert not (tmp_path / "c.toml").exists()


def test_a_target_size_that_nothing_in_view_has_is_named(calibrate, tmp_path):
    lab = write_lab(tmp_path, true_geometry())
    with pytest.raises(MagctlError) as err:
        calibrate("camera", "--config", str(lab), "--out", str(tmp_path / "c.toml"), "--target-diameter-um", "600",
                  "--quiet")
    msg = str(err.value)
    assert "\n" not in msg and "no round targets of 600 µm" in msg


def test_a_robot_out_of_view_is_one_line(calibrate, tmp_path):
    # the camera looks 3 mm to the side of the robot
    lab = write_lab(tmp_path, true_geometry(mirror=False, shift_um=(3000.0, 0.0)))
    with pytest.raises(MagctlError) as err:
        calibrate("camera", "--config", str(lab), "--out", str(tmp_path / "c.toml"), "--quiet")
    msg = str(err.value)
    assert "\n" not in msg and "robot not found" in msg
    assert not (tmp_path / "c.toml").exists()
