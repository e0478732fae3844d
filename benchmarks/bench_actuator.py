"""Cost per 30 Hz frame of the plant front half (drive → coils → robot).

Measured both as the three-block diagram and as the fused ``ActuatedRobot`` block, through
``magctl.core.simulation``, for B = 1 (rig) and per trial for B = 100 and B = 10 000 (Monte Carlo).
"""

from __future__ import annotations

import time

from rows import fmt, row

from magctl.core import Diagram, simulate
from magctl.plant.drive import ActuatedRobot, actuated_robot

TARGET_B100_US_PER_STEP = 100.0  # whole chain, per lockstep step of 100 trials
TARGET_B10000_US_PER_TRIAL_STEP = 2.0


def _fused() -> Diagram:
    return Diagram("p", [ActuatedRobot("plant")], inputs={"speed": "plant.speed", "heading": "plant.heading"},
                   outputs={"position": "plant.position"})


def _time(diagram, batch, steps, repeats=3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate(diagram, steps, batch=batch, inputs={"speed": 4e-4, "heading": 0.5}, record=[])
        best = min(best, time.perf_counter() - t0)
    return best / steps * 1e6


def run(quick: bool = False) -> dict:
    steps = 100 if quick else 600
    out = {}
    for label, make in (("diagram", actuated_robot), ("fused", _fused)):
        d = make()
        b1 = _time(d, 1, steps)
        b100 = _time(d, 100, steps)
        b10k = _time(d, 10_000, max(steps // 10, 20), repeats=1)
        out[label] = {
            "B1_us_per_frame": b1,
            "B100_us_per_frame": b100,
            "B10000_us_per_trial_frame": b10k / 10_000,
        }
    f = out["fused"]
    out["targets"] = {
        "B100_us_per_frame": {"target": TARGET_B100_US_PER_STEP, "measured": f["B100_us_per_frame"],
                              "met": f["B100_us_per_frame"] <= TARGET_B100_US_PER_STEP},
        "B10000_us_per_trial_frame": {"target": TARGET_B10000_US_PER_TRIAL_STEP,
                                      "measured": f["B10000_us_per_trial_frame"],
                                      "met": f["B10000_us_per_trial_frame"] <= TARGET_B10000_US_PER_TRIAL_STEP},
    }
    out["met"] = all(t["met"] for t in out["targets"].values())
    d = out["diagram"]
    out["rows"] = [
        row("actuator + robot (drive → coils → robot, fused block) per trial-frame in B = 10,000",
            f["B10000_us_per_trial_frame"], "µs", le=TARGET_B10000_US_PER_TRIAL_STEP,
            note=f"three-block diagram {fmt(d['B10000_us_per_trial_frame'])} µs; "
                 f"B = 1: {fmt(f['B1_us_per_frame'])} µs fused, {fmt(d['B1_us_per_frame'])} µs diagram per frame"),
        row("actuator + robot (fused block) per lockstep frame of B = 100", f["B100_us_per_frame"], "µs",
            le=TARGET_B100_US_PER_STEP, note=f"three-block diagram {fmt(d['B100_us_per_frame'])} µs"),
    ]
    return out
