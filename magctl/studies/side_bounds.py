"""The side push's minimum gap taken from the plant in use, not borrowed from the paper's (docs/push-control.md §4).

The paper bounds the side gap at 370 µm, where its simulated robot touched the sphere (§IV-D). A
controller on another plant must take the bound from that plant: the gap below which the passing
robot touches the sphere (:func:`magctl.plant.fluid.scenarios.contact_threshold`, on the plant's own
flow and robot–sphere lubrication), plus the distance by which the closed loop's robot may pass closer to the sphere
than it was told — the servo's cross-track error.

:func:`cross_track` measures that error in the closed loop: side pushes of the default controller
(curve learning) on the studies' plant; for each pass, the robot's smallest distance from the
sphere's starting centre, across the pass direction, while the robot is alongside (within 300 µm
along the line), against the gap the task commanded. The margin is the 99th percentile of the
shortfall over every pass. :func:`min_gap` adds the two; ``models/push.toml [side] min_gap_um``
holds the result and a test recomputes it.
"""

from __future__ import annotations

import numpy as np

from magctl.control.phases import SidePhase
from magctl.core import simulate
from magctl.loops import Experiment, Variability, push_loop
from magctl.plant.fluid.scenarios import contact_threshold
from magctl.studies.trials import study_engine

TRIALS, SEED, FRAMES = 32, 3, 3000
"""Closed-loop side pushes measured, their root seed and length (frames: about five attempts each)."""
ALONGSIDE = 300e-6
"""A frame counts while the robot is within this distance of the sphere along the pass."""
PERCENTILE = 99.0
CONTROLLER = {"learning": "curve", "model": "exp-fit"}


def cross_track(trials: int = TRIALS, seed: int = SEED, frames: int = FRAMES, min_gap: float | None = None) -> dict:
    """The shortfall of the robot's closest approach across the pass against the commanded gap [m], per pass.

    Returns ``shortfall`` (P,), ``commanded`` (P,), ``margin`` (the :data:`PERCENTILE` th percentile of the
    shortfall) and ``passes``.
    """
    task = CONTROLLER | ({} if min_gap is None else {"min_gap": float(min_gap)})
    exp = Experiment("side", task=task, max_frames=frames, variability=Variability(release_scatter=0.1))
    res = simulate(push_loop(exp), frames, batch=trials, seed=seed, engine=study_engine(),
                   record=["controller/task.phase", "controller/task.gap", "plant/robot.position",
                           "plant/spheres.spheres"])
    phase, gap = res["controller/task.phase"], res["controller/task.gap"]
    robot, sphere = res["plant/robot.position"], res["plant/spheres.spheres"][:, :, 0]
    commanded, closest = [], []
    for b in range(phase.shape[0]):
        passing = phase[b] == int(SidePhase.PASS)
        starts = np.flatnonzero(passing & ~np.r_[False, passing[:-1]])
        for s0 in starts:
            e = s0 + int(np.argmin(passing[s0:])) if not passing[s0:].all() else len(passing)
            way = robot[b, e - 1] - robot[b, s0]
            if e - s0 < 2 or not np.any(way):
                continue
            u = way / np.linalg.norm(way)
            rel = robot[b, s0:e] - sphere[b, s0]
            along = rel @ u
            across = np.abs(rel[:, 0] * u[1] - rel[:, 1] * u[0])
            near = np.abs(along) < ALONGSIDE
            if near.any():
                commanded.append(gap[b, s0])
                closest.append(across[near].min())
    if not commanded:
        raise RuntimeError("no side pass came alongside its sphere: cannot measure the cross-track error")
    shortfall = np.asarray(commanded) - np.asarray(closest)
    return {"shortfall": shortfall, "commanded": np.asarray(commanded),
            "margin": float(np.percentile(shortfall, PERCENTILE)), "passes": int(shortfall.size)}


def min_gap() -> dict:
    """The plant's side-push bound: contact threshold + cross-track margin [m], with both parts."""
    threshold = contact_threshold()
    track = cross_track()
    return {"threshold": threshold, "margin": track["margin"], "passes": track["passes"],
            "min_gap": threshold + track["margin"]}
