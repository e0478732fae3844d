"""The push tasks' parameter records: defaults from models/push.toml, validation naming the parameter, the rig's
option spec, the log round trip and the kernels' packed parameters."""

from __future__ import annotations

import tomllib
from dataclasses import fields
from pathlib import Path

import pytest

from magctl.control.push_params import AssemblyParams, DirtParams, FrontParams, SideParams, TaskParams
from magctl.core.errors import MagctlError

PUSH_TOML = tomllib.loads((Path(__file__).parents[2] / "models" / "push.toml").read_text())
RECORDS = [FrontParams, SideParams, AssemblyParams, DirtParams]


def test_every_default_is_the_file_value_in_si():
    """Read straight from the TOML (µm → m, mm → m, deg → rad), not through magctl's loader."""
    front = FrontParams.resolve()
    assert front.eps == pytest.approx(PUSH_TOML["front"]["eps_um"]["value"] * 1e-6, rel=1e-15)
    assert front.workspace == pytest.approx(PUSH_TOML["common"]["workspace_mm"]["value"] * 1e-3, rel=1e-15)
    assert front.settle_frames == PUSH_TOML["common"]["settle_frames"]["value"]
    assert isinstance(front.max_attempts, int)
    assert front.max_attempts == PUSH_TOML["front"]["max_attempts_count"]["value"]
    side = SideParams.resolve()
    assert side.min_gap == pytest.approx(PUSH_TOML["side"]["min_gap_um"]["value"] * 1e-6, rel=1e-15)
    assembly = AssemblyParams.resolve()
    assert assembly.ks == PUSH_TOML["assembly"]["ks_1"]["value"]
    assert assembly.theta_n == pytest.approx(PUSH_TOML["assembly"]["theta_n_deg"]["value"] * 3.141592653589793 / 180)
    assert assembly.min_gap == side.min_gap      # [side] under [assembly]


@pytest.mark.parametrize("given, message", [
    ({"eps": -75e-6}, r"front push 'f': eps=-7.5e-05 must be a positive number"),
    ({"eps": float("nan")}, r"eps=nan must be a positive number"),
    ({"eps": "far"}, r"eps='far' must be a positive number"),
    ({"max_attempts": 2.5}, r"max_attempts=2.5 must be an integer ≥ 1"),
    ({"max_attempts": 0}, r"max_attempts=0 must be an integer ≥ 1"),
    ({"settle_frames": True}, r"settle_frames=True must be an integer ≥ 0"),
    ({"learning": "eq99"}, r"learning='eq99' is not one of eq13, release"),
    ({"kc": float("inf")}, r"kc=inf must be a finite number"),
    ({"speed": 1.0}, r"unknown parameter\(s\) speed; it takes approach, arrive_tol"),
])
def test_a_bad_value_is_one_line_naming_the_task_and_the_parameter(given, message):
    with pytest.raises(MagctlError, match=message):
        FrontParams.resolve("front push 'f'", **given)


def test_none_takes_the_default_and_replace_validates():
    side = SideParams.resolve(eps=None, ks=0.5)
    assert side.ks == 0.5 and side.eps == SideParams.resolve().eps
    assert side.replace(ks=None).ks == 0.5 and side.replace(ks=0.7).ks == 0.7
    with pytest.raises(MagctlError, match="push_out_weight=1.5 must be a number in"):
        side.replace(push_out_weight=1.5)


@pytest.mark.parametrize("record", RECORDS)
def test_the_spec_and_the_log_round_trip(record):
    spec = record.spec()
    assert list(spec) == [f.name for f in fields(record)]
    resolved = record.resolve()
    assert {k: v for k, (v, _unit) in spec.items()} == {f.name: getattr(resolved, f.name) for f in fields(record)}
    assert record.from_log(resolved.to_log()) == resolved
    assert spec.get("eps", (0, "m"))[1] == "m"


def test_the_kernels_read_the_record_by_name():
    front = FrontParams.resolve(push_tol=42e-6, max_attempts=7)
    packed = front.packed(i0=1, r0=1e-4)
    assert isinstance(packed, TaskParams)
    assert packed.push_tol == 42e-6 and packed.max_attempts == 7 and packed.i0 == 1 and packed.r0 == 1e-4
    assert type(packed.max_attempts) is int and type(packed.eps) is float
    assert packed.min_gap == TaskParams._field_defaults["min_gap"]     # a side field the front record has not
    with pytest.raises(MagctlError, match=r"\['nonsense'\] are not fields of TaskParams"):
        front.packed(nonsense=1.0)
