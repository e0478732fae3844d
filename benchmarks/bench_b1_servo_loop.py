"""B1: the visual-servo reference loop — magctl vs python-control vs a hand-vectorised numpy loop.

All timings come from one run, so their ratios are comparable on a shared machine.
Per-trial time includes drawing the camera noise in every implementation.
"""

from __future__ import annotations

import time

import numpy as np
from rows import fmt, row

from magctl.core import simulate
from magctl.testing import STEPS, b1_diagram, b1_noise, b1_numpy, b1_python_control

SEED = 2026
RATIO_TO_NUMPY_LE = 1.0
SPEEDUP_VS_CONTROL_GE = 500.0
BATCH1_STEP_US_LE = 15.0
AGREEMENT_UM_LE = 1e-6


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def run(quick: bool = False) -> dict:
    batch = 100 if quick else 1000
    repeat = 2 if quick else 3
    diagram = b1_diagram()

    # agreement of the three implementations on the same trials
    check = [0, 1, 2]
    noise = b1_noise(SEED, check)
    p_numpy = b1_numpy(noise)
    p_magctl = simulate(diagram, STEPS, batch=len(check), seed=SEED, record=[])["p"]
    p_control = np.stack([b1_python_control(noise[i]) for i in range(len(check))])
    max_diff_um = float(max(np.abs(p_magctl - p_numpy).max(), np.abs(p_control - p_numpy).max()))
    if max_diff_um > AGREEMENT_UM_LE:
        raise AssertionError(f"B1 implementations disagree by {max_diff_um} µm")

    t_control = _best(lambda: b1_python_control(b1_noise(SEED, [0])[0]), 1 if quick else 2)
    t_numpy_1 = _best(lambda: b1_numpy(b1_noise(SEED, [0])), repeat)
    t_numpy_b = _best(lambda: b1_numpy(b1_noise(SEED, range(batch))), repeat) / batch
    t_magctl_1 = _best(lambda: simulate(diagram, STEPS, batch=1, seed=SEED, record=[]), repeat)
    t_magctl_b = _best(lambda: simulate(diagram, STEPS, batch=batch, seed=SEED, record=[]), repeat) / batch

    per_step_b1_us = t_magctl_1 / STEPS * 1e6
    ratio_numpy = t_magctl_b / t_numpy_b
    speedup_control = t_control / t_magctl_b
    b = f"B = {batch:,}"
    rows = [
        row(f"B1 servo loop: magctl vs python-control, per trial in a {b} batch", speedup_control, "×",
            ge=SPEEDUP_VS_CONTROL_GE,
            note=f"{fmt(t_magctl_b * 1e3)} ms vs {fmt(t_control * 1e3)} ms per trial"),
        row(f"B1: magctl vs the hand-vectorised numpy loop, same {b} batch", ratio_numpy, "×",
            le=RATIO_TO_NUMPY_LE,
            note=f"{fmt(t_magctl_b * 1e3)} vs {fmt(t_numpy_b * 1e3)} ms per trial"),
        row("B1: magctl stepping one trial (rig path), per step", per_step_b1_us, "µs",
            le=BATCH1_STEP_US_LE,
            note=f"the hand-written numpy loop at B = 1: {fmt(t_numpy_1 / STEPS * 1e6)} µs"),
        row("B1: the three implementations agree (max trajectory difference)", max_diff_um, "µm",
            le=AGREEMENT_UM_LE),
    ]
    return {
        "steps": STEPS,
        "batch": batch,
        "max_trajectory_difference_um": max_diff_um,
        "python_control_per_trial_ms": t_control * 1e3,
        "numpy_loop_per_trial_ms": {"batch_1": t_numpy_1 * 1e3, f"batch_{batch}": t_numpy_b * 1e3},
        "magctl_per_trial_ms": {"batch_1": t_magctl_1 * 1e3, f"batch_{batch}": t_magctl_b * 1e3},
        "magctl_batch1_per_step_us": per_step_b1_us,
        "ratio_magctl_to_numpy_in_batch": ratio_numpy,
        "speedup_magctl_batch_vs_python_control": speedup_control,
        "targets": {
            "ratio_magctl_to_numpy_in_batch_le": RATIO_TO_NUMPY_LE,
            "speedup_vs_python_control_ge": SPEEDUP_VS_CONTROL_GE,
            "batch1_per_step_us_le": BATCH1_STEP_US_LE,
        },
        "met": {
            "ratio_to_numpy": ratio_numpy <= RATIO_TO_NUMPY_LE,
            "speedup_vs_python_control": speedup_control >= SPEEDUP_VS_CONTROL_GE,
            "batch1_per_step": per_step_b1_us <= BATCH1_STEP_US_LE,
        },
        "rows": rows,
    }
