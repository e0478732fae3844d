"""The pushes through the full simulated hardware path against the studies' simulated rig, same tasks, same seed.

Each task runs twice in simulated time (lock-step): on ``SimRig`` — the studies' plant with its camera model and
Kalman tracker — and on the lab of ``examples/lab-sim.toml`` — the same plant filmed (rendered frames sent through
OpenCV, tracked by the image tracker) and driven through the serial adapter by the host-compiled firmware behind a
pseudo-terminal. Reported per task and path: the exit, the task's status, attempts and ticks, and the wall time.

Targets (issue #29): the front push, side push and planned assembly converge through the full path as in the
studies (converged on both paths). ``run(quick=True)`` runs the front push only.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from rows import row

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "examples" / "lab-sim.toml"
TASKS = {"front-push": ({}, 1), "side-push": ({}, 1), "assemble": ({"n_spheres": 3}, 3)}
MAX_TICKS = 30000


def _lab(folder: Path, n_spheres: int) -> Path:
    path = folder / f"lab-{n_spheres}.toml"
    path.write_text(LAB.read_text().replace("n_spheres = 1", f"n_spheres = {n_spheres}"))
    return path


def _one(rig, task: str, options: dict) -> dict:
    from magctl.rig.runtime import Runtime

    t0 = time.perf_counter()
    try:
        report = Runtime(rig, task, options, realtime=False, max_ticks=MAX_TICKS, quiet=True).run()
    finally:
        rig.close()
    stats = report.stats()
    return {"exit_status": stats["exit_status"], "status": stats.get("status"), "ticks": stats["ticks"],
            "attempt": (stats.get("outputs") or {}).get("attempt", stats.get("attempt")),
            "wall_s": time.perf_counter() - t0}


def run(quick: bool = False) -> dict:
    from magctl.rig.lab import build_station, load_lab
    from magctl.rig.sim import SimRig
    from magctl.rig.station import StationRig

    out, rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for task, (options, n) in TASKS.items():
            if quick and task != "front-push":
                continue
            cfg = load_lab(_lab(Path(tmp), n))
            lab = _one(StationRig(lambda cfg=cfg: build_station(cfg, lockstep=True), limits=cfg.limits,
                                  watchdog=cfg.watchdog), task, options)
            sim = _one(SimRig(n_spheres=n, seed=0), task, options)
            out[task] = {"lab": lab, "simrig": sim}
            ok = float(lab["status"] == "converged" and sim["status"] == "converged")
            rows.append(row(f"{task} through the full simulated hardware path (examples/lab-sim.toml) converges "
                            f"as on the studies' SimRig", ok, "(1 = both converged)", ge=1.0,
                            note=f"lab: {lab['status']}, {lab['ticks']} ticks, attempt {lab['attempt']}, "
                                 f"{lab['wall_s']:.0f} s; SimRig: {sim['status']}, {sim['ticks']} ticks, attempt "
                                 f"{sim['attempt']}"))
    met = {r["name"]: r["met"] for r in rows}
    return {"tasks": out, "rows": rows, "met": met, "all_met": all(met.values())}
