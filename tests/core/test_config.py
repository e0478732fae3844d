"""Parameter files: SI conversion, required sources, errors naming file and key."""

import pytest

from magctl.config import load_file
from magctl.core import MagctlError, ParameterError


def write(tmp_path, text):
    path = tmp_path / "p.toml"
    path.write_text(text)
    return path


def test_units_converted_and_sources_kept(tmp_path):
    text = ('[s]\nradius_um = { value = 105, source = "paper §II" }\n'
            'nu_cSt = { value = 20, source = "paper §II" }\nangle_deg = { value = 180, source = "x" }')
    p = load_file(write(tmp_path, text))
    assert p.s.radius == pytest.approx(105e-6)
    assert p.s.nu == pytest.approx(20e-6)
    assert p.s.angle == pytest.approx(3.141592653589793)
    assert p.s.sources["radius"] == "paper §II"
    assert p.to_dict() == {"s": {"radius_um": 105, "nu_cSt": 20, "angle_deg": 180}}


@pytest.mark.parametrize(
    "text, message",
    [
        ('[s]\nradius_um = 105\n', r"p\.toml:s\.radius_um: write parameters as"),
        ('[s]\nradius_um = { value = 105 }\n', r"s\.radius_um: missing 'source'"),
        ('[s]\nradius = { value = 105, source = "x" }\n', r"s\.radius: numeric parameter needs a unit suffix"),
        ('[s]\nradius_um = { value = "abc", source = "x", colour = 1 }\n', r"unknown fields \['colour'\]"),
        ('[s]\nradius_um = { value = [1, "a"], source = "x" }\n', r"is not a number"),
        ('[paper]\nkp_per_s = { value = "fast", source = "x" }\n', r"paper\.kp_per_s: value 'fast' is not a number"),
        ('[s]\nradius_um = { value = true, source = "x" }\n', r"s\.radius_um: value True is not a number"),
        ('[s\nradius_um = 1', r"not valid TOML"),
    ],
)
def test_malformed_files_name_file_and_key(tmp_path, text, message):
    with pytest.raises(ParameterError, match=message):
        load_file(write(tmp_path, text))


def test_missing_file_and_missing_parameter(tmp_path):
    with pytest.raises(ParameterError, match="not found"):
        load_file(tmp_path / "none.toml")
    p = load_file(write(tmp_path, '[s]\nradius_um = { value = 1, source = "x" }\n'))
    with pytest.raises(ParameterError, match=r"no parameter 'mass'"):
        _ = p.s.mass


def test_camera_file_ranges_name_file_and_key(tmp_path):
    """camera.toml is range-checked like rig.toml: a negative latency names the file, the key and the range."""
    from magctl.config import models_dir

    text = (models_dir() / "camera.toml").read_text()
    bad = tmp_path / "camera.toml"
    bad.write_text(text.replace("latency_frames = { value = 2,", "latency_frames = { value = -2,"))
    with pytest.raises(ParameterError, match=r"camera\.toml: camera\.latency_frames = -2 is out of range"):
        load_file(bad)
    bad.write_text(text.replace("drop_probability_ratio = { value = 0.0,", "drop_probability_ratio = { value = 1.5,"))
    with pytest.raises(ParameterError, match="drop_probability_ratio"):
        load_file(bad)


def test_check_whole_takes_whole_numbers_only():
    """The one whole-number check behind simulate's counts and the root seed: integers and whole floats in range,
    nothing truncated."""
    from magctl.core.checks import check_whole

    assert check_whole("n", 3, 0) == 3 and check_whole("n", 4.0, 0) == 4 and check_whole("n", 2**64 - 1, 0, 2**64)
    for bad in (2.5, -1, True, float("nan"), "3", 2**64):
        with pytest.raises(MagctlError, match="n must be a whole number"):
            check_whole("n", bad, 0, 2**64)
