"""constraints.txt pins every run-time dependency (and the view extra) to one version, and this environment holds
exactly those versions (make demo and make test install with ``-c constraints.txt``)."""

from __future__ import annotations

import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]


def pins(text: str) -> dict[str, str]:
    out = {}
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep and version, f"constraints.txt: {line!r} is not NAME==VERSION"
            out[name.lower().replace("_", "-")] = version
    return out


def test_every_runtime_dependency_is_pinned_and_installed_at_its_pin():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["view"]]
    pinned = pins((ROOT / "constraints.txt").read_text())
    for req in wanted:
        key = req.name.lower().replace("_", "-")
        assert key in pinned, f"constraints.txt does not pin {req.name} (run .ci/constraints.py)"
        assert req.specifier.contains(pinned[key]), f"{req.name}=={pinned[key]} is outside pyproject's {req}"
    drift = {name: (version, metadata.version(name)) for name, version in pinned.items()
             if metadata.version(name) != version}
    assert drift == {}, f"installed versions differ from constraints.txt: {drift}"


def test_a_bad_pin_line_is_caught():
    import pytest

    with pytest.raises(AssertionError, match="is not NAME==VERSION"):
        pins("numpy>=2\n")
    assert pins("# c\nNumPy==2.0  # x\n") == {"numpy": "2.0"}
