"""Fluid plant: Fig 6 from a cold start (flow solve included) and flow evaluation per trial-step in a batch.

Targets (issue 4): the Fig 6 curve with >= 20 gaps from a cold start in <= 2 s;
flow evaluation per trial-step inside a batched simulation in <= 5 us.

A cold process reads the solved flow from the on-disk cache (``magctl.plant.fluid.flow``);
the boundary-element solve itself, without that cache, is timed separately (full runs only).
"""

from __future__ import annotations

import time

import numpy as np

from magctl.plant.fluid.flow import RobotFlow, clear_cache, robot_flow
from magctl.plant.fluid.scenarios import sidepush_curve
from magctl.plant.sphere import Spheres

COLD_TARGET_S = 2.0
EVAL_TARGET_US = 5.0


def run(quick: bool = False) -> dict:
    gaps = np.linspace(200e-6, 650e-6, 24)
    clear_cache()
    t0 = time.perf_counter()
    flow = robot_flow()
    t_solve = time.perf_counter() - t0
    sidepush_curve(gaps)
    cold = time.perf_counter() - t0
    t1 = time.perf_counter()
    sidepush_curve(gaps)
    warm = time.perf_counter() - t1

    batch = 1000 if quick else 10000
    steps = 10 if quick else 30
    rng = np.random.default_rng(0)
    block = Spheres(np.array([[0.0, 450e-6]]))
    state = block.initial_state(batch)
    state["xy"] = rng.uniform(-1.2e-3, 1.2e-3, (batch, 1, 2))
    pos = np.zeros((batch, 2))
    heading = rng.uniform(-np.pi, np.pi, batch)
    vel = 4e-4 * np.column_stack([np.cos(heading), np.sin(heading)])
    rel = rng.uniform(-1.2e-3, 1.2e-3, (batch, 1, 2))
    vb = np.broadcast_to(np.array([4e-4, 0.0]), rel.shape)
    t2 = time.perf_counter()
    for _ in range(steps):
        flow.lookup(rel, vb)
    lookup_us = (time.perf_counter() - t2) / (steps * batch) * 1e6
    t3 = time.perf_counter()
    for _ in range(steps):
        block.sphere_velocity(state["xy"], state["gap"], state["mobility"], pos, heading, vel)
    eval_us = (time.perf_counter() - t3) / (steps * batch) * 1e6
    t4 = time.perf_counter()
    for _ in range(max(steps // 3, 2)):
        state = block.update(state, {"position": pos, "heading": heading, "velocity": vel})
    update_us = (time.perf_counter() - t4) / (max(steps // 3, 2) * batch) * 1e6
    uncached = None
    if not quick:
        t5 = time.perf_counter()
        RobotFlow(flow.geometry, flow.viscosity, flow.height, flow.domain, disk_cache=False)
        uncached = time.perf_counter() - t5
    return {
        "flow_solve_uncached_s": uncached, "robot_panels": int(flow.robot_panels.sum()),
        "fig6_gaps": len(gaps),
        "fig6_cold_s": cold, "flow_solve_s": t_solve, "fig6_warm_s": warm,
        "fig6_cold_target_s": COLD_TARGET_S, "fig6_cold_met": cold <= COLD_TARGET_S,
        "batch": batch,
        "map_lookup_us_per_trial_step": lookup_us,
        "flow_eval_us_per_trial_step": eval_us,
        "flow_eval_target_us": EVAL_TARGET_US, "flow_eval_met": eval_us <= EVAL_TARGET_US,
        "block_update_us_per_trial_step": update_us,
        "substeps_per_frame": block.params.substeps,
        "far_field_points": len(flow.points), "map_nodes": int(flow.maps.shape[1] * flow.maps.shape[2]),
    }
