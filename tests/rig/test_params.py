"""Parameter files are checked for type and range; bad ones are one-line errors naming file and key."""

from __future__ import annotations

import re

import pytest
from rig_helpers import ROOT

from magctl.cli import main
from magctl.config import load_model
from magctl.core.errors import ParameterError
from magctl.plant.coils import load_coils


@pytest.fixture
def models(tmp_path, monkeypatch):
    for f in (ROOT / "models").glob("*.toml"):
        (tmp_path / f.name).write_bytes(f.read_bytes())
    monkeypatch.setenv("MAGCTL_MODELS", str(tmp_path))
    return tmp_path


def _replace(folder, name, old, new):
    path = folder / name
    text = path.read_text()
    assert text.count(old) >= 1, old
    path.write_text(text.replace(old, new))


@pytest.mark.parametrize("name, old, new, words", [
    ("rig.toml", "rate_Hz = { value = 30.0,", "rate_Hz = { value = 0,", "runtime.rate_Hz = 0 is out of range"),
    ("rig.toml", "rate_Hz = { value = 30.0,", "rate_Hz = { value = true,",
     "runtime.rate_Hz: value True is not a number"),
    ("rig.toml", "timeout_ms = { value = 100.0,", "timeout_ms = { value = 1e9,",
     "watchdog.timeout_ms = 1000000000.0 is out of range (allowed: >= 10 and <= 1000)"),
    ("rig.toml", "timeout_ms = { value = 100.0,", "timeout_ms = { value = 0.5,", "watchdog.timeout_ms = 0.5"),
    ("rig.toml", "b_static_max_mT = { value = 3.0,", "b_static_max_mT = { value = -3.0,", "limits.b_static_max_mT"),
    ("rig.toml", "b_osc_max_mT = { value = 6.0,", "b_osc_max_mT = { value = inf,", "not finite"),
    ("rig.toml", "request_timeout_ms = { value = 500.0,", "request_timeout_ms = { value = \"fast\",",
     "runtime.request_timeout_ms: value 'fast' is not a number"),
    ("rig.toml", "robot_steps = { value = true,", "robot_steps = { value = 1,", "physics.robot_steps"),
    ("rig.toml", "takeover_interval_s = { value = 1.0,", "takeover_interval_s = { value = -1.0,",
     "session.takeover_interval_s = -1.0 is out of range"),
    ("rig.toml", "max_mb_1 = { value = 100.0,", "max_mb_1 = { value = \"big\",",
     "log.max_mb_1: value 'big' is not a number"),
    ("rig.toml", "timeout_ms = { value = 100.0, source", "grace_ms = { value = 100.0, source",
     "missing parameter watchdog.timeout_ms"),
    ("coils.toml", "current_limit_A = { value = 3.0,", "current_limit_A = { value = -3.0,",
     "key 'current_limit' = -3.0 must be positive"),
    ("coils.toml", "current_limit_A = { value = 3.0,", "current_limit_A = { value = nan,", "not finite"),
])
def test_bad_parameters_are_named_with_their_file_and_key(models, capsys, name, old, new, words):
    _replace(models, name, old, new)
    with pytest.raises(ParameterError, match=None) as err:
        load_coils() if name == "coils.toml" else load_model(name.removesuffix(".toml"))
    assert name in str(err.value) and words in str(err.value)
    # the commands that read them say the same in one line and exit 2
    for args in (["rig", "run", "--rig", "sim", "--fast", "--plant", "standin", "--task", "goto", "--target-um",
                  "1100", "1800", "--max-ticks", "3", "--quiet"],
                 ["rig", "serve-sim", "--bind", "tcp://127.0.0.1:1", "--plant", "standin"]):
        code = main(args)
        err_lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err_lines) == 1 and words in err_lines[0] and name in err_lines[0], (args, err_lines)


def test_a_binary_parameter_file_is_one_line(models):
    (models / "rig.toml").write_bytes(b"\xff\xfe[limits]\n")
    with pytest.raises(ParameterError, match="rig.toml: not UTF-8|rig.toml: not valid TOML"):
        load_model("rig")


SHIPPED = {"camera", "coils", "fluid", "front_release", "identify", "materials", "pass_map", "push", "rig", "robot",
           "robot_geometry", "servo", "sphere", "wall_resistance"}
"""The parameter files models/ holds, by name: a file missing, or one added without a line here, fails below."""


def test_the_shipped_files_pass():
    """Exactly the parameter files :data:`SHIPPED` are in models/ (a missing one fails here, it is not skipped),
    every file magctl's code loads by name is one of them, and each loads and passes its checks."""
    from magctl.config import models_dir

    shipped = {p.stem for p in models_dir().glob("*.toml")}
    assert sorted(SHIPPED - shipped) == [], "parameter files missing from models/"
    assert sorted(shipped - SHIPPED) == [], "parameter files in models/ this test does not know: add them to SHIPPED"
    code = "\n".join(p.read_text(encoding="utf-8") for p in (ROOT / "magctl").rglob("*.py"))
    loaded = set(re.findall(r"load_model\(\s*[\"'](\w+)[\"']", code))
    assert {"push", "rig", "servo", "sphere"} <= loaded                   # the search finds the code's loads …
    assert sorted(loaded - SHIPPED) == [], "magctl loads parameter files models/ does not ship"   # … all shipped
    for name in sorted(SHIPPED):
        load_model(name)
    load_coils()
