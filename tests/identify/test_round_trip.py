"""Round trip: a simulated rig with perturbed parameters, driven through the identification experiment over its
wire protocol and logged by ``magctl rig run``'s runtime, then ``magctl identify`` on the logs — the perturbed
values come back.

The server runs in lock-step (one plant frame per read: simulated time, seeded), so the logs and the identified
values are the same on every run. The client's own parameters are the shipped defaults, as on a lab computer
whose rig differs from the model.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
from rig_helpers import ROOT, ServerProcess, magctl_cmd

from magctl.identify.folder import copy_with

pytestmark = pytest.mark.slow

PHYSICS = {  # the rig's values; the shipped ones are 1.05 mm, 0.754, 1, 2 frames, 0.3 px
    ("fluid.toml", "domain", "depth_mm"): 0.95,
    ("robot.toml", "robot", "slip_efficiency_1"): 0.9,
    ("sphere.toml", "variability", "mobility_ratio"): 0.8,
    ("camera.toml", "camera", "latency_frames"): 3,
    ("camera.toml", "camera", "position_noise_px"): 0.6,
}
STANDIN = {("push.toml", "release", "mean_um"): 200.0, ("push.toml", "release", "std_um"): 40.0}
"""The stand-in plant's release D_p,r ~ N(200, 40²) µm (shipped: N(300, 75²)): the physical plant has no
release parameter of its own (its release follows from the flow and the contact), the stand-in draws it."""
WHY = "the simulated rig of tests/identify/test_round_trip.py"


def name(key) -> str:
    return f"{key[0]}:{key[1]}.{key[2]}"


def run(*args: str, timeout: float = 900) -> dict:
    done = subprocess.run(magctl_cmd(*args), capture_output=True, text=True, cwd=ROOT, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def experiment(tmp: Path, values: dict, *server_args: str) -> list[Path]:
    rig = copy_with(tmp / "rig-models", values, WHY)
    server = ServerProcess("--lockstep", *server_args, env={"MAGCTL_MODELS": str(rig)}, ready_timeout=600)
    try:
        doc = run("rig", "experiment", "--rig", server.address, "--out", str(tmp / "logs"), "--json")
    finally:
        server.kill()
    return [Path(p) for p in doc["logs"]]


@pytest.fixture(scope="module")
def physics_logs(tmp_path_factory):
    return experiment(tmp_path_factory.mktemp("physics"), PHYSICS, "--seed", "3")


def check_recovered(identified: dict, truth: dict, tolerance: dict) -> list[str]:
    """Each true value within 2σ of the estimate (a 95 % band; one σ holds the truth only 68 % of the time) and
    within its tolerance."""
    found = {e["parameter"]: e for e in identified["identified"]}
    misses = []
    for key, value in truth.items():
        e = found.get(name(key))
        if e is None:
            misses.append(f"{name(key)} not identified: {identified['not_identified']}")
            continue
        err = abs(e["value"] - value)
        if err > 2 * e["uncertainty"] + 1e-12 or err > tolerance[key]:
            misses.append(f"{name(key)} = {e['value']:.4g} ± {e['uncertainty']:.2g}, true {value}")
    return misses


def test_the_physical_plant_is_recovered_from_the_default_experiment(physics_logs, tmp_path):
    out = tmp_path / "identified"
    doc = run("identify", *map(str, physics_logs), "--out", str(out), "--no-report", "--json")
    identified = json.loads((out / "identified.json").read_text())
    tolerance = {k: (0.1 if k[2] == "depth_mm" else 0.0 if k[2] == "latency_frames" else 0.1 * v)
                 for k, v in PHYSICS.items()}
    assert check_recovered(identified, PHYSICS, tolerance) == []
    # the folder speaks for that rig: its files carry the identified values and say so
    camera = (out / "camera.toml").read_text()
    assert re.search(r"^latency_frames = \{ value = 3, source = \"identified: 3 ", camera, flags=re.M)
    assert doc["identified"]["camera.toml:camera.latency_frames"]["value"] == 3


def test_the_report_recommends_gains_on_the_identified_rig_and_checks_held_out_runs(physics_logs, tmp_path):
    # held out: the last front push of 750 µm and the passes at 440 µm
    held = [[p for p in physics_logs if "front-750um" in p.name][-1],
            next(p for p in physics_logs if "side-440um" in p.name)]
    fit = [p for p in physics_logs if p not in held]
    out = tmp_path / "identified"
    doc = run("identify", *map(str, fit), "--holdout", *map(str, held), "--out", str(out), "--json")
    recs, val = doc["recommendations"], doc["validation"]
    # the analyses ran on the identified folder: the servo saw the identified lag, not the shipped 2 frames
    assert recs["servo"]["delay_frames"] == 3
    assert recs["front"]["stable_gain_range"] == [0.0, 2.0]          # eq 15: 0 < K_c < 2 on any rig
    # held-out side passes at 440 µm: the identified plant (fitted without them) predicts their displacement
    # within a pass's scatter (10 % and 3 µm, models/identify.toml [side])
    sp = val["side_passes"]
    assert sp["compared"] >= 4 and sp["z_rms"] < 2.0
    assert val["front_attempts"]["runs"] == 1
    report = (out / "report.md").read_text()
    assert "## On this rig" in report and "## Held-out runs" in report
    assert (out / "identify-side.png").stat().st_size > 1000


def test_the_stand_in_release_is_recovered(tmp_path):
    logs = experiment(tmp_path, STANDIN, "--plant", "standin", "--seed", "4")
    out = tmp_path / "identified"
    run("identify", *map(str, logs), "--out", str(out), "--no-report", "--json")
    identified = json.loads((out / "identified.json").read_text())
    mean, std = ("push.toml", "release", "mean_um"), ("push.toml", "release", "std_um")
    assert check_recovered(identified, {mean: 200.0}, {mean: 20.0}) == []
    # the scatter: within 2σ only — a dozen attempts pin a standard deviation to ±20 % (1σ), not 10 %
    assert check_recovered(identified, {std: 40.0}, {std: 40.0}) == []
