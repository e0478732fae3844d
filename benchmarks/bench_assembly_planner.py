"""Planning time per pass of the N-sphere assembly planner (casadi + IPOPT), one core.

Target: ≤ 1 s per pass. Each arrangement is planned pass after pass from its study layout on the pass map
itself (the receding horizon without the plant), so every pass of a whole assembly is timed; the sampling and
the IPOPT refinements are timed apart.
"""

from __future__ import annotations

import time

import numpy as np

TARGET_S = 1.0
CASES = (("pair", "assembly"), ("line", "assembly-3"), ("triangle", "assembly-3"), ("line", "assembly-4"))


def run(quick: bool = False) -> dict:
    from magctl.control.arrangement import arrangement
    from magctl.control.assembly_planner import AssemblyPlanner
    from magctl.loops import geometry

    passes = 10 if quick else 30
    out = {"target_s": TARGET_S, "passes_per_case": passes}
    for name, kind in CASES:
        spheres = geometry(kind)["spheres"].copy()
        t0 = time.perf_counter()
        pl = AssemblyPlanner(arrangement(name, len(spheres)))
        build = time.perf_counter() - t0
        times, solvers = [], []
        for _ in range(passes):
            plan = pl.plan(spheres)
            times.append(plan.seconds)
            solvers.append(plan.solver)
            spheres = plan.predicted
            if pl.target.assembled(spheres):
                break
        out[f"{len(spheres)} {name}"] = {
            "build_s": build, "passes": len(times), "mean_s": float(np.mean(times)),
            "p95_s": float(np.percentile(times, 95)), "max_s": float(np.max(times)),
            "refined_by_ipopt": solvers.count("ipopt") / len(solvers), "met": float(np.max(times)) <= TARGET_S}
    out["all_met"] = all(v["met"] for v in out.values() if isinstance(v, dict))
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
