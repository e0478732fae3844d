"""``magctl fluid``: JSON output and clear errors."""

import json

import pytest

from magctl.cli import main


def test_pulloff_json(capsys):
    assert main(["fluid", "pulloff", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["pull_off_min_uN"] == pytest.approx(5.2, abs=0.06)
    assert doc["pull_off_max_uN"] == pytest.approx(23.0, abs=0.1)


def test_sidepush_json_and_inverse(capsys):
    assert main(["fluid", "sidepush", "--gap-um", "400", "550", "--ds-um", "40", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [p["gap_um"] for p in doc["points"]] == pytest.approx([400.0, 550.0])
    d = [p["displacement_um"] for p in doc["points"]]
    assert d[0] > 40 > d[1] > 0          # so the inverse of the two-point fit lies between the gaps
    assert 400 < doc["gap_for_ds_um"] < 550


@pytest.mark.parametrize("argv, msg", [
    (["fluid", "pulloff", "--radius-um", "-1"], "radius-um"),
    (["fluid", "sidepush", "--gap-um", "-5"], "gap-um"),
    (["fluid", "release", "--roughness-nm", "0"], "roughness-nm"),
])
def test_bad_arguments_exit_2(capsys, argv, msg):
    assert main(argv) == 2
    assert msg in capsys.readouterr().err
