"""What a wheel promises: dependencies exactly as imported, the version in the changelog, the
parameter files and studies found both in a checkout and as package data."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

import magctl
from magctl.config import data_dir, models_dir
from magctl.studies.runner import studies_dir

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

# import name → distribution name, where they differ
DIST = {"zmq": "pyzmq", "PIL": "pillow", "skfem": "scikit-fem", "cv2": "opencv-python-headless",
        "serial": "pyserial"}
# optional imports, each behind its extra and a clear error when missing
OPTIONAL = {"distributed": "dask", "pyarrow": "export", "h5py": "export", "xarray": "xarray",
            "skfem": "fem", "pyamg": "fem", "cv2": "hardware", "serial": "hardware", "pyvisa": "hardware",
            "plotly": "view", "starlette": "view", "uvicorn": "view", "websockets": "view"}


def _imports(folders) -> set[str]:
    names = set()
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in ("magctl", "__future__")}


def _dist(requirement: str) -> str:
    return re.split(r"[<>=!\[ ;]", requirement, maxsplit=1)[0].lower()


def test_runtime_dependencies_are_exactly_what_magctl_and_the_studies_import():
    imported = _imports(["magctl", "analysis"])
    required = {_dist(r) for r in PYPROJECT["project"]["dependencies"]}
    runtime = {DIST.get(n, n).lower() for n in imported - set(OPTIONAL)}
    assert runtime == required, (sorted(runtime - required), sorted(required - runtime))


def test_optional_imports_are_declared_in_their_extra():
    extras = PYPROJECT["project"]["optional-dependencies"]
    imported = _imports(["magctl", "analysis"])
    for name, extra in OPTIONAL.items():
        assert name in imported, name
        assert DIST.get(name, name).lower() in {_dist(r) for r in extras[extra]}, (name, extra)
    dev = " ".join(extras["dev"])
    assert all(e in dev for e in ("dask", "export", "xarray", "docs", "fem"))


def test_version_is_the_newest_changelog_release_and_there_is_a_license():
    text = (ROOT / "CHANGELOG.md").read_text()
    releases = re.findall(r"^## \[(\d+\.\d+\.\d+)\]", text, flags=re.M)
    assert releases and releases[0] == magctl.__version__
    assert "## [Unreleased]" in text
    assert "MIT License" in (ROOT / "LICENSE").read_text()
    assert PYPROJECT["project"]["license"] == {"text": "MIT"}


def test_the_package_says_it_is_typed_and_classifies_itself():
    """PEP 561's marker sits in the package (the wheel check finds it in the wheel), and the classifiers name the
    licence and the Python versions the project requires."""
    assert (ROOT / "magctl" / "py.typed").is_file()
    classifiers = PYPROJECT["project"]["classifiers"]
    assert "Typing :: Typed" in classifiers and "License :: OSI Approved :: MIT License" in classifiers
    low = PYPROJECT["project"]["requires-python"].removeprefix(">=")
    assert f"Programming Language :: Python :: {low}" in classifiers


def test_the_wheel_carries_models_analysis_and_firmware_as_package_data():
    include = PYPROJECT["tool"]["hatch"]["build"]["targets"]["wheel"]["force-include"]
    assert include == {"models": "magctl/_data/models", "analysis": "magctl/_data/analysis",
                       "firmware": "magctl/_data/firmware"}


def test_a_checkout_reads_the_folders_at_the_top_of_the_repository(monkeypatch):
    monkeypatch.delenv("MAGCTL_MODELS", raising=False)
    monkeypatch.delenv("MAGCTL_STUDIES", raising=False)
    assert models_dir() == ROOT / "models" == data_dir("models")
    assert studies_dir() == ROOT / "analysis"


def test_installed_layout_reads_package_data(tmp_path, monkeypatch):
    """Without a pyproject.toml beside the package (an installed wheel), the package's _data is used."""
    import magctl.config as config

    site = tmp_path / "site-packages"
    (site / "magctl").mkdir(parents=True)
    (site / "magctl" / "_data" / "models").mkdir(parents=True)
    fake = site / "magctl" / "config.py"
    monkeypatch.setattr(config, "__file__", str(fake))
    monkeypatch.setattr(config.resources, "files", lambda pkg: site / pkg)
    assert config.data_dir("models") == site / "magctl" / "_data" / "models"
    monkeypatch.setenv("MAGCTL_MODELS", str(tmp_path / "mine"))
    assert config.models_dir() == tmp_path / "mine"      # a user's own parameter folder wins
