"""``magctl rig calibrate coils`` on the simulated lab (lock-step) whose coils are not the model's (each in-plane
coil's field scaled and turned: ``[simulation] coil_gain``, ``coil_angle_deg``): the gains and directions are
recovered; with ``[coils] calibration`` a commanded heading is reached, without it not; the vertical coils are
reported as not calibrated; a Hall-probe reading sets the scale; bad input is one line."""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from magctl.config import load_file
from magctl.core.errors import MagctlError
from magctl.rig.calibrate import CalibrationError, hall_scale, load_coil_calibration
from magctl.rig.devices.tracking import PixelCalibration
from magctl.rig.interface import Command
from magctl.rig.lab import LabConfigError, build_station, load_lab

NAMES = ["xp", "xn", "yp", "yn", "zp", "zn"]
# the x coils stronger than the y coils and turned the other way: uncalibrated, a commanded heading is off by ~3°
GAIN = np.array([1.06, 1.04, 0.95, 0.97, 1.2, 0.8])  # (the vertical coils' perturbation must not matter)
ANGLE = np.array([3.0, 2.0, -1.5, -4.0, 0.0, 0.0])
PLANE = slice(0, 4)


def write_lab(folder, *, coil_calibration: str | None = None, name: str = "lab.toml", perturbed: bool = True):
    # the camera is turned 3° (its true geometry in the calibration file the lab uses)
    camera = PixelCalibration(7.5e-6, math.radians(3.0), False, (60e-6, -100e-6))
    camera.save(folder / "camera.toml")
    coils = f'calibration = "{coil_calibration}"\n' if coil_calibration else ""
    sim = (f"coil_gain = {GAIN.tolist()}\ncoil_angle_deg = {ANGLE.tolist()}\n" if perturbed else "")
    path = folder / name
    path.write_text(f"""
[lab]
name = "coil calibration test"

[camera]
adapter = "sim"
pixel_size_um = 7.5
rotation_deg = 3.0
origin_x_um = 60.0
origin_y_um = -100.0

[tracker]
n_spheres = 1
calibration = "camera.toml"

[coils]
adapter = "sim-board"
deadline_s = 0.1
{coils}
[simulation]
plant = "physics"
seed = 5
{sim}""", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def result(calibrate, tmp_path_factory):
    folder = tmp_path_factory.mktemp("coils")
    lab = write_lab(folder)
    out = folder / "coils-calibration.toml"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert calibrate("coils", "--config", str(lab), "--out", str(out), "--json") == 0
    return folder, json.loads(buf.getvalue()), out


def test_each_in_plane_coil_is_recovered(result):
    _, doc, _ = result
    coils = doc["coils"]
    gains = np.array([coils[n]["gain"] for n in NAMES[PLANE]])
    angles = np.array([coils[n]["angle_deg"] for n in NAMES[PLANE]])
    true_rel = GAIN[PLANE] / np.exp(np.mean(np.log(GAIN[PLANE])))  # the scale is not observable: the model's
    assert np.exp(np.mean(np.log(gains))) == pytest.approx(1.0, abs=1e-9)
    assert np.max(np.abs(gains / true_rel - 1)) < 0.02, (gains, true_rel)
    assert np.max(np.abs(angles - ANGLE[PLANE])) < 1.0, angles
    for n in NAMES[PLANE]:  # the check against models/coils.toml: direction and field of 1 A, measured vs model
        c = coils[n]
        assert abs(math.remainder(c["direction_deg"] - c["model_direction_deg"] - c["angle_deg"], 360)) < 1e-6
        assert c["field_at_1A_mT"] == pytest.approx(c["gain"] * c["model_field_at_1A_mT"])
        assert 0 < c["gain_se"] < 0.01 and 0 < c["angle_se_deg"] < 0.3
    assert doc["residual_rms_deg"] < 0.5 and doc["settings"] >= 16
    assert "not observable" in doc["scale"] or "does not show" in doc["scale"]


def test_the_vertical_coils_are_not_calibrated(result):
    _, doc, out = result
    for n in ("zp", "zn"):
        assert doc["coils"][n] == {"calibrated": False, "gain": 1.0, "gain_se": 0.0, "angle_deg": 0.0,
                                   "angle_se_deg": 0.0}
    params = load_file(out)  # a parameter file: units in the keys, a source for every value
    assert "not calibrated" in params.coil.zp.sources["gain"]
    assert params.coil.xp.sources["gain"].startswith("measured:")
    assert params.coil.xp.field_at_1A == pytest.approx(doc["coils"]["xp"]["field_at_1A_mT"] * 1e-3)
    gain, angle = load_coil_calibration(out, NAMES)
    assert gain[4:].tolist() == [1.0, 1.0] and angle[4:].tolist() == [0.0, 0.0]


def _heading_errors(lab, directions_deg) -> list[float]:
    """Command the static field (2 mT, coils only) in each direction through the lab's coil map; the settled
    true heading's error, degrees."""
    station = build_station(load_lab(lab), lockstep=True)
    errors = []
    try:
        k = 0
        for phi in np.radians(directions_deg):
            cmd = Command(2e-3 * np.array([math.cos(phi), math.sin(phi)]), 0.0, 0.0)
            for _ in range(8):
                k += 1
                station.apply(cmd, k * station.period)
                station.step(k * station.period)
            errors.append(math.degrees(abs(math.remainder(station.camera.world.heading - phi, 2 * math.pi))))
    finally:
        station.close()
    return errors


DIRECTIONS = [0.0, 40.0, 80.0, 120.0, 160.0, 200.0, 240.0, 280.0, 320.0, 0.0]


def test_with_the_calibration_a_commanded_heading_is_reached(result):
    folder, _, out = result
    calibrated = write_lab(folder, coil_calibration=out.name, name="lab-calibrated.toml")
    errors = _heading_errors(calibrated, DIRECTIONS)
    assert max(errors) < 1.0, errors
    # without it, the coils as built turn the robot elsewhere
    assert max(_heading_errors(write_lab(folder, name="lab-model.toml"), DIRECTIONS)) > 2.0


def test_a_hall_probe_reading_sets_the_scale():
    per_ampere = np.array([0.60, 0.54, 0.59, 0.55, 1.0, 1.0]) * 1e-3
    factor, scale = hall_scale(per_ampere, NAMES, {"xp": 0.66})
    assert factor == pytest.approx(1.1) and "Hall-probe reading of xp 0.66 mT/A" in scale
    factor, scale = hall_scale(per_ampere, NAMES, {"xp": 0.66, "yp": 0.59 * 1.2})
    assert factor == pytest.approx(math.sqrt(1.1 * 1.2))
    assert hall_scale(per_ampere, NAMES, {}) == (1.0, hall_scale(per_ampere, NAMES, None)[1])


@pytest.mark.parametrize("reading, needle", [("zp=1.0", "a vertical coil"), ("xq=0.5", "no such coil")])
def test_a_hall_reading_of_a_coil_it_cannot_scale_is_one_line(calibrate, tmp_path, reading, needle):
    lab = write_lab(tmp_path, perturbed=False)
    with pytest.raises(MagctlError) as err:
        calibrate("coils", "--config", str(lab), "--out", str(tmp_path / "c.toml"), "--field-mT-per-A", reading)
    assert "\n" not in str(err.value) and needle in str(err.value)
    assert not (tmp_path / "c.toml").exists()


def test_a_malformed_hall_reading_is_a_parse_error(calibrate, tmp_path, capsys):
    lab = write_lab(tmp_path, perturbed=False)
    with pytest.raises(SystemExit) as done:
        calibrate("coils", "--config", str(lab), "--out", str(tmp_path / "c.toml"), "--field-mT-per-A", "xp:0.5")
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "COIL=VALUE" in err


def test_a_bad_coil_calibration_file_is_named_by_the_lab(tmp_path):
    (tmp_path / "bad.toml").write_text("[coil.xp]\ngain_ratio = { value = -1.0, source = \"x\" }\nangle_deg = 0.0\n",
                                       encoding="utf-8")
    lab = write_lab(tmp_path, coil_calibration="bad.toml")
    with pytest.raises(LabConfigError) as err:
        load_lab(lab)
    msg = str(err.value)
    assert "\n" not in msg and "[coils] calibration" in msg and "[coil.xp] gain_ratio" in msg
    lab = write_lab(tmp_path, coil_calibration="missing.toml", name="lab2.toml")
    with pytest.raises(LabConfigError, match="no such file"):
        load_lab(lab)
    with pytest.raises(CalibrationError, match=r"\[coil.xq\]: no such coil"):
        (tmp_path / "unknown.toml").write_text("[coil.xq]\ngain_ratio = 1.0\nangle_deg = 0.0\n", encoding="utf-8")
        load_coil_calibration(tmp_path / "unknown.toml", NAMES)


def test_the_simulated_coils_as_built_are_checked(tmp_path):
    lab = write_lab(tmp_path, perturbed=False)
    text = lab.read_text(encoding="utf-8")
    lab.write_text(text + "coil_gain = [1.0, 1.0, 1.0]\n", encoding="utf-8")
    with pytest.raises(LabConfigError, match=r"\[simulation\] coil_gain: expected 6 numbers"):
        load_lab(lab)
