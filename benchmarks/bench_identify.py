"""``magctl identify`` on the default identification experiment of a simulated rig whose parameters differ from the
model's (tests/identify/test_round_trip.py's rig): how long the identification takes, and what it recovers.

Targets (issue: fit the model to a rig): identification ≤ 30 s on one core with the flow maps cached (the wall
time of ``magctl identify LOGS --out DIR --no-report`` in a fresh process pinned to one core, second run — the
first solves the flow grid); every perturbed value within 10 % of the truth (the oil depth within 0.1 mm, the lag
exact). The report's stability analyses (``magctl stability`` subprocesses) are timed separately.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rows import fmt, row

ROOT = Path(__file__).resolve().parents[1]
TIME_TARGET_S = 30.0
SEEDS = (3, 5, 7)
"""Seeds of the simulated rig: 3 is the round-trip test's; the others show how far one experiment's depth strays."""
RIG = {("fluid.toml", "domain", "depth_mm"): 0.95, ("robot.toml", "robot", "slip_efficiency_1"): 0.9,
       ("sphere.toml", "variability", "mobility_ratio"): 0.8, ("camera.toml", "camera", "latency_frames"): 3,
       ("camera.toml", "camera", "position_noise_px"): 0.6}
NEAR = RIG | {("robot.toml", "robot", "slip_efficiency_1"): 0.58 * 480 / 310}
"""The 0.2.0 round trip's rig (slip efficiency 0.58 with the length along the 480 µm side, the same step scale on
today's 310 µm one): RIG's robot 0.2 % slower, everything else equal. How far the depth moves between the two is
how much one experiment's depth can be trusted beyond its own σ."""


def _magctl(*args: str, one_core: bool = False) -> tuple[float, subprocess.CompletedProcess]:
    pin = (lambda: os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})) if one_core else None
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "magctl", *args], capture_output=True, text=True, cwd=ROOT,
                          preexec_fn=pin, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"magctl {' '.join(args[:2])} failed: {done.stderr.strip()[-300:]}")
    return time.perf_counter() - t0, done


def _experiment(tmp: Path, rig: Path, seed: int) -> list[str]:
    from rig_helpers import ServerProcess

    srv = ServerProcess("--lockstep", "--seed", str(seed), env={"MAGCTL_MODELS": str(rig)}, ready_timeout=600)
    try:
        _, done = _magctl("rig", "experiment", "--rig", srv.address, "--out", str(tmp / f"logs-{seed}"), "--json")
    finally:
        srv.kill()
    return json.loads(done.stdout)["logs"]


def run(quick: bool = False) -> dict:
    sys.path.insert(0, str(ROOT / "tests" / "rig"))
    from magctl.identify.folder import copy_with

    tmp = Path(tempfile.mkdtemp(prefix="bench-identify-"))
    rig = copy_with(tmp / "rig-models", RIG, "the simulated rig of benchmarks/bench_identify.py")
    seeds = SEEDS[:1] if quick else SEEDS
    t0 = time.perf_counter()
    logs = _experiment(tmp, rig, seeds[0])
    t_exp = time.perf_counter() - t0
    flows = Path(os.environ.get("MAGCTL_CACHE") or Path.home() / ".cache" / "magctl") / "robot_flow"
    before = len(list(flows.glob("*.npz")))
    t_first, _ = _magctl("identify", *logs, "--out", str(tmp / "first"), "--no-report", "--json", one_core=True)
    solved = len(list(flows.glob("*.npz"))) - before
    t_cached, done = _magctl("identify", *logs, "--out", str(tmp / "id"), "--no-report", "--json", one_core=True)
    doc = json.loads(done.stdout)
    t_report, _ = _magctl("identify", *logs, "--out", str(tmp / "report"), "--json")
    found = doc["identified"]
    out = {"logs": len(logs), "seed": seeds[0], "experiment_s": t_exp, "identify_first_s": t_first,
           "identify_cached_s": t_cached, "flow_maps_solved_by_first_run": solved,
           "identify_with_report_s": t_report, "fit_timings_s": doc["timings_s"],
           "recovered": {}, "depth_by_seed": {}}
    rows = [row("magctl identify, default experiment's logs, one core, flow maps cached", t_cached, "s",
                le=TIME_TARGET_S, note=f"the run before it {fmt(t_first)} s, solving {solved} flow map(s) "
                                       f"(the rest were on disk); with the report's stability analyses "
                                       f"{fmt(t_report)} s on two cores")]
    for (file, table, key), truth in RIG.items():
        name = f"{file}:{table}.{key}"
        e = found.get(name)
        value = None if e is None else e["value"]
        err = None if e is None else abs(value - truth)
        tol = 0.1 if key == "depth_mm" else 0.0 if key == "latency_frames" else 0.1 * truth
        out["recovered"][name] = {"truth": truth, "value": value, "uncertainty": None if e is None else
                                  e["uncertainty"], "error": err, "tolerance": tol}
        unit = "mm" if key == "depth_mm" else "frames" if key == "latency_frames" else "% of the truth"
        shown = err if key in ("depth_mm", "latency_frames") or err is None else 100 * err / truth
        bound = tol if key in ("depth_mm", "latency_frames") else 10.0
        rows.append(row(f"magctl identify round trip (seed {seeds[0]}): {name} error (true {truth})", shown, unit,
                        le=bound, note="not identified" if e is None else
                        f"{fmt(value)} ± {fmt(e['uncertainty'])} (1σ)"))
    depth = "fluid.toml:domain.depth_mm"
    out["depth_by_seed"][seeds[0]] = found.get(depth)
    out["depth_by_seed"] |= _depths(tmp, rig, seeds[1:], "rig")
    rows.append(_worst_depth_row(out["depth_by_seed"], f"worst of {len(seeds)} experiments"))
    if not quick:
        near = copy_with(tmp / "near-models", NEAR, "the 0.2.0 round trip's rig, benchmarks/bench_identify.py")
        out["depth_by_seed_near_rig"] = _depths(tmp, near, seeds, "near")
        rows.append(_worst_depth_row(out["depth_by_seed_near_rig"], f"worst of {len(seeds)} experiments, the rig's "
                                     f"robot 0.2 % slower (the 0.2.0 round trip's rig)"))
        shifts = [abs(out["depth_by_seed"][s]["value"] - out["depth_by_seed_near_rig"][s]["value"]) for s in seeds
                  if out["depth_by_seed"][s] and out["depth_by_seed_near_rig"][s]]
        out["depth_shift_mm"] = shifts
        out["depth_shift_in_sigma"] = [
            abs(out["depth_by_seed"][s]["value"] - out["depth_by_seed_near_rig"][s]["value"])
            / max(out["depth_by_seed"][s]["uncertainty"], out["depth_by_seed_near_rig"][s]["uncertainty"])
            for s in seeds if out["depth_by_seed"][s] and out["depth_by_seed_near_rig"][s]]
    out["rows"] = rows
    return out


def _depths(tmp: Path, rig: Path, seeds, tag: str) -> dict:
    """The oil depth ``magctl identify`` finds from one default experiment per seed on the rig in ``rig``."""
    found = {}
    for seed in seeds:
        logs = _experiment(tmp / tag, rig, seed)
        _, done = _magctl("identify", *logs, "--out", str(tmp / f"id-{tag}-{seed}"), "--no-report", "--json")
        found[seed] = json.loads(done.stdout)["identified"].get("fluid.toml:domain.depth_mm")
    return found


def _worst_depth_row(by_seed: dict, what: str) -> dict:
    truth = RIG[("fluid.toml", "domain", "depth_mm")]
    errs = [abs(e["value"] - truth) if e else None for e in by_seed.values()]
    worst = None if None in errs else max(errs)
    shown = ", ".join(f"seed {s}: {fmt(e['value'])} ± {fmt(e['uncertainty'])}" if e else f"seed {s}: not identified"
                      for s, e in by_seed.items())
    return row(f"magctl identify round trip: oil depth error, {what}", worst, "mm", le=0.1, note=shown)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    print(json.dumps(run(), indent=1, ensure_ascii=False))
