"""``magctl --models DIR``: every command reads its parameter files from DIR, as with ``$MAGCTL_MODELS``; a folder
that is not one is a one-line error."""

from __future__ import annotations

import json
import shutil

from test_bad_input import ROOT, _assert_one_line, _run


def _release(tmp_path, *models) -> float:
    done = _run([*models, "fluid", "release", "--json"], tmp_path)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)["release_displacement_um"]


def test_a_folder_of_parameter_files_replaces_the_shipped_one(tmp_path):
    """A copy of models/ with a smaller sphere changes the release the fluid model predicts, and only under
    --models; the copy left as shipped gives the shipped answer."""
    folder = tmp_path / "rig"
    shutil.copytree(ROOT / "models", folder)
    shipped = _release(tmp_path)
    assert _release(tmp_path, "--models", str(folder)) == shipped
    sphere = folder / "sphere.toml"
    sphere.write_text(sphere.read_text().replace("radius_um = { value = 105.0,", "radius_um = { value = 80.0,"))
    smaller = _release(tmp_path, "--models", str(folder))
    assert smaller != shipped
    assert _release(tmp_path) == shipped


def test_a_folder_that_is_not_a_parameter_set_is_one_line(tmp_path):
    _assert_one_line(_run(["--models", str(tmp_path / "missing"), "fluid", "release"], tmp_path), "--models")
    (tmp_path / "empty").mkdir()
    line = _assert_one_line(_run(["--models", str(tmp_path / "empty"), "fluid", "release"], tmp_path), "--models")
    assert "no parameter files" in line
    broken = tmp_path / "broken"
    shutil.copytree(ROOT / "models", broken)
    (broken / "sphere.toml").unlink()
    _assert_one_line(_run(["--models", str(broken), "fluid", "release"], tmp_path), "sphere.toml")
