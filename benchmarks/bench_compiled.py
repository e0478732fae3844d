"""The compiled engine beside the interpreted one, a hand-vectorised numpy loop and a hand-written numba loop,
all measured in one run (ratios matter on a shared machine); the block-diagram peers' figures are quoted.

* **B1** (the visual-servo reference loop of ``magctl.testing``, 1 800 steps): per trial in a batch of
  1 000 against the numpy loop given the same noise, with the camera noise fed as a diagram input (as
  every peer gets it) and drawn inside from the per-trial counter-based streams; per step at B = 1
  inside ``simulate``; memory kept between runs.
* **Rig path**: the rig's whole controller step, observation → command (``Controller.step``), for the
  front-push controller (task → servo → drive), compiled against interpreted.
* **Closed loop**: front and side push (``magctl.loops.push_loop``) at B = 1, 100 and 1 000 on both
  engines, in simulated seconds per wall second.
* **Compile times**: the closed front-push loop compiled in a fresh process with empty caches (numba's
  and the generated sources'), then again with them warm.

``rows`` lists what the benchmark table of docs/benchmarks.md shows (``benchmarks/readme.py``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from rows import row

from magctl import FRAME_PERIOD_S
from magctl.core import simulate
from magctl.core.compiled import NotCompilable
from magctl.testing import DELAY, KI, KP, NOISE_SIGMA, REFERENCE, SPEED_LIMIT, STEPS, b1_diagram, b1_noise, b1_numpy

SEED = 2026
QUOTED = {
    "source": "measured side by side with magctl on 2026-12-04 on this project's 2-core machine (issue #26); "
              "quoted, not re-run here",
    "collimator_2_2_jax": {"b1_fed_ratio_to_numpy": 0.33, "b1_per_step_us": 0.048},
}
TARGETS = {"b1_fed_ratio_le": 0.2, "b1_drawn_ratio_le": 0.35, "b1_fed_step_us_le": 0.04, "b1_drawn_step_us_le": 0.08,
           "rig_step_us_le": 3.0, "front_b100_speed_x_ge": 60000.0, "side_b100_speed_x_ge": 60000.0,
           "planned_b100_speed_x_ge": 5000.0, "first_compile_s_le": 20.0, "cached_compile_s_le": 1.0,
           "kept_mb_le": 1.0}


def _best(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def b1_numba_loop():
    """The B1 loop written by hand in numba: the practical limit of a compiled engine."""
    import numba

    T = FRAME_PERIOD_S
    r0, r1 = REFERENCE

    @numba.njit(cache=True, error_model="numpy")
    def loop(noise):
        batch = noise.shape[0]
        out = np.empty((batch, STEPS, 2))
        for b in range(batch):
            p0 = p1 = i0 = i1 = 0.0
            a0 = a1 = c0 = c1 = 0.0     # p[k-2], p[k-1]
            for k in range(STEPS):
                out[b, k, 0], out[b, k, 1] = p0, p1
                e0 = r0 - (a0 + noise[b, k, 0])
                e1 = r1 - (a1 + noise[b, k, 1])
                u0, u1 = KP * e0 + KI * i0, KP * e1 + KI * i1
                s = np.hypot(u0, u1)
                if s > SPEED_LIMIT:
                    u0, u1 = u0 * (SPEED_LIMIT / s), u1 * (SPEED_LIMIT / s)
                else:
                    i0, i1 = i0 + T * e0, i1 + T * e1
                a0, a1, c0, c1 = c0, c1, p0, p1
                p0, p1 = p0 + T * u0, p1 + T * u1
        return out

    assert DELAY == 2 and NOISE_SIGMA > 0
    return loop


def b1(quick: bool) -> dict:
    import tracemalloc

    batch, repeat = (100, 2) if quick else (1000, 3)
    drawn, fed = b1_diagram(), b1_diagram("input")
    loop = b1_numba_loop()
    noise = b1_noise(SEED, range(batch))
    check = [0, 1, 2]
    ref = b1_numpy(noise[check])
    agree = {"compiled_drawn_vs_numpy_um": float(np.abs(
                 simulate(drawn, STEPS, batch=3, seed=SEED, record=[], engine="compiled")["p"] - ref).max()),
             "compiled_fed_vs_numpy_um": float(np.abs(simulate(
                 fed, STEPS, batch=3, inputs={"n": noise[check]}, record=[], engine="compiled")["p"] - ref).max()),
             "numba_loop_vs_numpy_um": float(np.abs(loop(noise[check]) - ref).max())}

    def run_fed(b=batch):
        return simulate(fed, STEPS, batch=b, inputs={"n": noise[:b]}, record=[], engine="compiled")

    def run_drawn(b=batch):
        return simulate(drawn, STEPS, batch=b, seed=SEED, record=[], engine="compiled")

    t_numpy = _best(lambda: b1_numpy(noise), repeat) / batch
    t_numba = _best(lambda: loop(noise), repeat) / batch
    t_interp = _best(lambda: simulate(drawn, STEPS, batch=batch, seed=SEED, record=[]), 1) / batch
    t_fed = _best(run_fed, repeat) / batch
    t_drawn = _best(run_drawn, repeat) / batch
    t_fed_1 = _best(lambda: run_fed(1), 7)
    t_drawn_1 = _best(lambda: run_drawn(1), 7)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for _ in range(3):
        run_drawn()
    kept = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return {
        "batch": batch, "agreement": agree,
        "per_trial_ms": {"numpy_loop_noise_given": t_numpy * 1e3, "numba_loop_noise_given": t_numba * 1e3,
                         "interpreted_drawn": t_interp * 1e3, "compiled_fed": t_fed * 1e3,
                         "compiled_drawn": t_drawn * 1e3},
        "ratio_to_numpy": {"numba_loop": t_numba / t_numpy, "interpreted_drawn": t_interp / t_numpy,
                           "compiled_fed": t_fed / t_numpy, "compiled_drawn": t_drawn / t_numpy},
        "batch1_per_step_us": {"compiled_fed": t_fed_1 / STEPS * 1e6, "compiled_drawn": t_drawn_1 / STEPS * 1e6},
        "kept_after_3_runs_mb": kept / 1e6,
    }


def rig_path(quick: bool) -> dict:
    from magctl.rig.interface import Observation
    from magctl.rig.tasks import Controller, build_task

    obs = Observation(t=0.0, frame=0, robot_est=np.array([1.0e-3, 1.0e-3]), heading_est=0.0,
                      spheres_est=np.array([[2.0e-3, 1.5e-3]]), lost=False)
    task = build_task("front-push", obs, {})
    calls = 2000 if quick else 20000
    out = {}
    for engine in ("interpreted", "auto"):
        ctrl = Controller(task, engine=engine)
        ctrl.step(obs)
        n = calls if ctrl.compiled else calls // 20
        best = _best(lambda c=ctrl, n=n: [c.step(obs) for _ in range(n)], 3) / n
        out["compiled" if ctrl.compiled else f"{engine} (not compiled)"] = best * 1e6
    return {"task": "front-push", "calls": calls, "controller_step_us": out,
            "note": "Controller.step: observation → controller inputs → compiled step → command"}


def closed_loop(quick: bool) -> dict:
    from magctl.loops import Experiment, push_loop

    exps = {"front": Experiment("front", task=dict(kc=1.0, delta0=127e-6)), "side": Experiment("side")}
    frames = 150 if quick else 600
    out = {}
    for name, exp in exps.items():
        d = push_loop(exp)
        try:
            d.compile()
            engines = ("interpreted", "compiled")
        except NotCompilable as err:
            engines = ("interpreted",)
            out[f"{name}_not_compiled"] = str(err)
        for engine in engines:
            for batch in ((1, 100) if quick else (1, 100, 1000)):
                simulate(d, 2, batch=batch, seed=0, engine=engine)     # caches, compilation
                n = frames if batch < 1000 else frames // 3
                wall = _best(lambda d=d, n=n, batch=batch, engine=engine: simulate(
                    d, n, batch=batch, seed=0, record=["controller/task.status"], engine=engine),
                    1 if quick or batch == 1000 else 2)
                out[f"{name}_{engine}_B{batch}_speed_x"] = batch * n * FRAME_PERIOD_S / wall
    return out


def planned_loop(quick: bool) -> dict:
    """The planned three-sphere assembly (IPOPT on the pass map, the paper's wavefront path) in the closed loop at
    B = 100: the frames compiled, each pass planned in Python as the frame's event."""
    from magctl.loops import Experiment, push_loop

    d = push_loop(Experiment("assembly-3", task={"planner": "optimal"}))
    batch, frames = (10, 300) if quick else (100, 1800)
    simulate(d, 2, batch=2, seed=0, engine="compiled")          # compilation, the planner's generated code
    t0 = time.perf_counter()
    res = simulate(d, frames, batch=batch, seed=0, record=["controller/task.attempt"], engine="compiled")
    wall = time.perf_counter() - t0
    passes = int(res["controller/task.attempt"][:, -1].sum()) + batch     # measured, and the next one planned
    return {"batch": batch, "frames": frames, "wall_s": wall, "passes_planned": passes,
            "speed_x": batch * frames * FRAME_PERIOD_S / wall}


COMPILE_CHILD = """
import time, sys
t0 = time.perf_counter()
from magctl.loops import Experiment, push_loop
from magctl.core import simulate
d = push_loop(Experiment("front", task=dict(kc=1.0, delta0=127e-6)))
simulate(d, 1, batch=1, seed=0)          # flow map and the interpreted caches, not the compilation
t1 = time.perf_counter()
simulate(d, 2, batch=1, seed=0, engine="compiled")
print(time.perf_counter() - t1)
"""


def compile_times() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=os.path.join(tmp, "numba"),
                   MAGCTL_COMPILED_CACHE=os.path.join(tmp, "compiled"))
        times = []
        for _ in range(2):
            res = subprocess.run([sys.executable, "-c", COMPILE_CHILD], env=env, capture_output=True, text=True)
            if res.returncode != 0:
                return {"error": res.stderr.strip().splitlines()[-1] if res.stderr else "failed"}
            times.append(float(res.stdout.strip().splitlines()[-1]))
    return {"first_compile_s": times[0], "cached_s": times[1]}


def run(quick: bool = False) -> dict:
    out = {"targets": TARGETS, "quoted": QUOTED}
    out["b1"] = b1(quick)
    out["rig_path"] = rig_path(quick)
    out["closed_loop"] = closed_loop(quick)
    out["planned_loop"] = planned_loop(quick)
    out["compile"] = compile_times()
    b, c, T = out["b1"], out["closed_loop"], TARGETS
    ratio, step = b["ratio_to_numpy"], b["batch1_per_step_us"]
    col = QUOTED["collimator_2_2_jax"]
    out["rows"] = [
        row("B1 per trial, B = 1 000, noise fed as an input, ratio to the numpy loop", ratio["compiled_fed"], "×",
            le=T["b1_fed_ratio_le"], note=f"hand numba loop {ratio['numba_loop']:.2f}×; Collimator 2.2 "
                                           f"{col['b1_fed_ratio_to_numpy']}× (quoted)"),
        row("B1 per trial, B = 1 000, noise drawn from the per-trial streams, ratio to the numpy loop",
            ratio["compiled_drawn"], "×", le=T["b1_drawn_ratio_le"]),
        row("B1 per step at B = 1 inside simulate, noise fed", step["compiled_fed"], "µs", le=T["b1_fed_step_us_le"],
            note=f"Collimator 2.2 {col['b1_per_step_us']} µs (quoted)"),
        row("B1 per step at B = 1 inside simulate, noise drawn", step["compiled_drawn"], "µs",
            le=T["b1_drawn_step_us_le"]),
        row("memory kept after three B = 1 000 runs", b["kept_after_3_runs_mb"], "MB", le=T["kept_mb_le"]),
        row("rig: whole controller step, observation → command (front push)",
            out["rig_path"]["controller_step_us"].get("compiled", np.inf), "µs", le=T["rig_step_us_le"]),
        row("closed-loop front push, B = 100, real-time factor", c.get("front_compiled_B100_speed_x", 0.0), "×",
            ge=T["front_b100_speed_x_ge"]),
        row("closed-loop side push, B = 100, real-time factor", c.get("side_compiled_B100_speed_x", 0.0), "×",
            ge=T["side_b100_speed_x_ge"]),
        row("closed-loop planned three-sphere assembly, B = 100, real-time factor", out["planned_loop"]["speed_x"],
            "×", ge=T["planned_b100_speed_x_ge"],
            note=f"{out['planned_loop']['passes_planned']} passes planned in {out['planned_loop']['wall_s']:.0f} s"),
        row("first compile of the closed loop, empty caches", out["compile"].get("first_compile_s", np.inf), "s",
            le=T["first_compile_s_le"]),
    ]
    return out


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
