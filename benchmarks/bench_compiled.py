"""The compiled engine beside the interpreted one, a hand-vectorised numpy loop, a hand-written numba loop
and the figures of the block-diagram peers, all measured in one run (ratios matter on a shared machine).

* **B1** (the visual-servo reference loop of ``magctl.testing``, 1 800 steps): per trial in a batch of
  1 000, and per step at B = 1 inside ``simulate``; every implementation draws the camera noise.
* **Rig path**: one controller step per call (B = 1) for the front-push controller (task → servo →
  drive), compiled stepper against the interpreted ``Diagram.step``.
* **Closed loop**: front and side push (``magctl.loops.push_loop``) at B = 1, 100 and 1 000 on both
  engines, in simulated seconds per wall second.
* **Compile times**: the closed front-push loop compiled in a fresh process with empty caches (numba's
  and the generated sources'), then again with them warm.

The peers' numbers are those measured side by side when the engine was specified (Collimator 2.2 with
JAX, Drake 1.5x with C++ blocks, bdsim, PathSim, python-control); they are quoted, not re-run here.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core import simulate
from magctl.core.compiled import NotCompilable
from magctl.testing import DELAY, KI, KP, NOISE_SIGMA, REFERENCE, SPEED_LIMIT, STEPS, b1_diagram, b1_noise, b1_numpy

SEED = 2026
PEERS = {
    "collimator_2_2_jax": {"b1_ratio_to_numpy_per_trial": 0.39, "b1_per_step_us": 0.34},
    "drake_1_5x_cpp_serial": {"b1_ratio_to_numpy_per_trial": 100.0, "b1_per_step_us": 13.0},
    "bdsim": {"b1_ratio_to_numpy_per_trial": 1800.0, "b1_per_step_us": 139.0},
    "pathsim": {"b1_ratio_to_numpy_per_trial": 2100.0, "b1_per_step_us": 128.0},
    "python_control": {"b1_ratio_to_numpy_per_trial": 7000.0, "b1_per_step_us": 408.0},
}
TARGETS = {"b1_ratio_to_numpy_le": 0.2, "b1_batch1_per_step_us_le": 0.1, "rig_step_us_le": 3.0,
           "front_b100_speed_x_ge": 20000.0, "side_b100_speed_x_ge": 30000.0, "b1_closed_loop_speed_x_ge": 10000.0,
           "first_compile_s_le": 20.0, "cached_compile_s_le": 1.0}


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
    batch, repeat = (100, 2) if quick else (1000, 3)
    d = b1_diagram()
    loop = b1_numba_loop()
    check = [0, 1, 2]
    ref = b1_numpy(b1_noise(SEED, check))
    compiled = simulate(d, STEPS, batch=len(check), seed=SEED, record=[], engine="compiled")["p"]
    by_numba = loop(b1_noise(SEED, check))
    agree = {"compiled_vs_numpy_um": float(np.abs(compiled - ref).max()),
             "numba_loop_vs_numpy_um": float(np.abs(by_numba - ref).max())}
    t_numpy = _best(lambda: b1_numpy(b1_noise(SEED, range(batch))), repeat) / batch
    t_numba = _best(lambda: loop(b1_noise(SEED, range(batch))), repeat) / batch
    t_interp = _best(lambda: simulate(d, STEPS, batch=batch, seed=SEED, record=[]), repeat) / batch
    t_comp = _best(lambda: simulate(d, STEPS, batch=batch, seed=SEED, record=[], engine="compiled"), repeat) / batch
    t_comp_1 = _best(lambda: simulate(d, STEPS, batch=1, seed=SEED, record=[], engine="compiled"), 5)
    t_interp_1 = _best(lambda: simulate(d, STEPS, batch=1, seed=SEED, record=[]), 3)
    return {
        "batch": batch, "agreement": agree,
        "per_trial_ms": {"numpy_loop": t_numpy * 1e3, "numba_loop": t_numba * 1e3,
                         "interpreted": t_interp * 1e3, "compiled": t_comp * 1e3},
        "ratio_to_numpy": {"numba_loop": t_numba / t_numpy, "interpreted": t_interp / t_numpy,
                           "compiled": t_comp / t_numpy},
        "batch1_per_step_us": {"interpreted": t_interp_1 / STEPS * 1e6, "compiled": t_comp_1 / STEPS * 1e6},
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
        best = _best(lambda c=ctrl: [c.step(obs) for _ in range(calls)], 3) / calls
        out["compiled" if ctrl.compiled else f"{engine} (not compiled)"] = best * 1e6
        if ctrl.compiled:   # the compiled step alone, without the runtime's observation → signals → command
            u = {n: v for n, v in obs.controller_inputs().items() if n in ctrl.diagram.inputs}
            st = ctrl._stepper
            out["compiled_step_only"] = _best(lambda st=st, u=u: [st.step(u) for _ in range(calls)], 3) / calls * 1e6
    return {"task": "front-push", "calls": calls, "per_call_us": out,
            "note": "compiled: Controller.step (observation to command); compiled_step_only: the compiled diagram step"}


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
    out = {"targets": TARGETS, "peers": PEERS}
    out["b1"] = b1(quick)
    out["rig_path"] = rig_path(quick)
    out["closed_loop"] = closed_loop(quick)
    out["compile"] = compile_times()
    c = out["closed_loop"]
    out["met"] = {
        "b1_ratio_to_numpy": out["b1"]["ratio_to_numpy"]["compiled"] <= TARGETS["b1_ratio_to_numpy_le"],
        "b1_batch1_per_step": out["b1"]["batch1_per_step_us"]["compiled"] <= TARGETS["b1_batch1_per_step_us_le"],
        "rig_step": out["rig_path"]["per_call_us"].get("compiled_step_only", np.inf) <= TARGETS["rig_step_us_le"],
        "front_b100": c.get("front_compiled_B100_speed_x", 0.0) >= TARGETS["front_b100_speed_x_ge"],
        "side_b100": c.get("side_compiled_B100_speed_x", 0.0) >= TARGETS["side_b100_speed_x_ge"],
        "closed_loop_b1": min(c.get("front_compiled_B1_speed_x", 0.0), c.get("side_compiled_B1_speed_x", 0.0))
        >= TARGETS["b1_closed_loop_speed_x_ge"],
        "first_compile": out["compile"].get("first_compile_s", np.inf) <= TARGETS["first_compile_s_le"],
        "cached_compile": out["compile"].get("cached_s", np.inf) <= TARGETS["cached_compile_s_le"],
    }
    return out


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
