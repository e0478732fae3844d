"""Iteration-domain analysis speed: 1000 x 1000 (gain, model ratio) verdict sweeps, attempt maps."""

from __future__ import annotations

import time

import numpy as np
from rows import row

from magctl.stability import iteration as S

SWEEP_TARGET_S = 1.0


def _best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(quick: bool = False) -> dict:
    n = 1000
    gains, ratios = np.linspace(0, 4, n), np.linspace(0.01, 3, n)
    reps = 2 if quick else 5
    paper = _best(lambda: S.sweep(gains, ratios, "paper"), reps)
    full = _best(lambda: S.sweep(gains, ratios, "full"), reps)
    # spot check of the closed form against python-control eigenvalues on a few grid points
    out = S.sweep(gains, ratios, "full")
    idx = [(10, 20), (400, 300), (999, 999), (250, 600)]
    agree = all(
        abs(out["spectral_radius"][i, j] - np.max(np.abs(S.side_full_poles(gains[i], ratios[j])))) < 1e-6
        for i, j in idx
    )
    trials = 2000 if quick else 20000
    rel = np.random.default_rng(0).normal(300e-6, 75e-6, size=(trials, 10))
    front_map = _best(lambda: S.front_attempt_map(1.0, 0.0, rel), reps)
    markov = _best(lambda: S.front_attempts_markov(1.0, 0.0), 1 if quick else 3)
    side_range = _best(lambda: S.side_nonlinear_gain_range("lin"), 1)
    task_frame = _task_frame(1000 if quick else 10000)
    return {
        "sweep_paper_1000x1000_s": paper, "sweep_full_1000x1000_s": full,
        "sweep_target_s": SWEEP_TARGET_S,
        "sweep_paper_met": paper <= SWEEP_TARGET_S, "sweep_full_met": full <= SWEEP_TARGET_S,
        "sweep_matches_python_control": agree,
        "front_attempt_map_trials": trials, "front_attempt_map_s": front_map,
        "front_markov_chain_s": markov, "side_nonlinear_gain_range_s": side_range,
        "side_push_task_frame_us_per_trial": task_frame,
        "rows": [
            row(f"{n:,} × {n:,} (gain, model ratio) stability grid, eq 20", paper, "s",
                le=SWEEP_TARGET_S),
            row(f"{n:,} × {n:,} (gain, model ratio) stability grid, with the feed-forward state",
                full, "s", le=SWEEP_TARGET_S,
                note="spot-checked against python-control's eigenvalues" + ("" if agree else ": **disagrees**")),
        ],
    }


def _task_frame(batch: int) -> float:
    """Wall time of one 30 Hz frame (output + update) of the side-push task, per trial (µs)."""
    from magctl.control.push.side import SidePushTask

    task = SidePushTask(goal=(300e-6, 0.0))
    st = task.initial_state(batch)
    rng = np.random.default_rng(1)
    u = {"robot_est": rng.normal(0, 1e-3, (batch, 2)), "spheres_est": rng.normal(0, 1e-4, (batch, 1, 2)),
         "lost": np.zeros(batch, bool)}
    frames = 50
    t0 = time.perf_counter()
    for _ in range(frames):
        task.output(st, u)
        st = task.update(st, u)
    return (time.perf_counter() - t0) / frames / batch * 1e6


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2, default=float))
